"""The live view and the replay: payloads, drawing data, the observer's rights on a router with
access control, identical numbers with ``--live``, and the pages in headless Chromium.

Lockstep runs here use agent processes (the default layout): an in-process run once ended here
with "agent 1 did not settle at tick 0" (once in 18 runs, no live view involved), probably a
follower's rod subscription reaching the leader's peer session after tick 0 had started.

Browser tests need Debian's ``chromium`` (``.ci/run`` installs it) and Playwright; they write
their screenshots to ``$SWARM_SCREENSHOT_DIR`` when set (``docs/live/`` keeps the committed
ones: ``SWARM_SCREENSHOT_DIR=docs/live pytest tests/test_live.py`` renews them), else to the
test's temporary folder. They read what the page shows from its Bokeh models and its legend
canvases (:data:`MAP_STATE_JS`) and check that neither the command's output nor the browser's
console holds a warning.
"""
from __future__ import annotations

import csv
import json
import logging
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from protocol import keys
from protocol.config import RunConfig, load_config
from protocol.messages import ProtocolError
from protocol.session import free_port, free_tcp_endpoint, undeclare_all, zenoh_config
from protocol.view import (
    MAP_CELLS,
    MAX_VIEW_BYTES,
    ROWS_PER_CHUNK,
    TICK_COLUMNS,
    decode_map,
    decode_tick,
    encode_map,
    encode_tick,
    tick_payloads,
)
from swarm.deploy import OBSERVER
from swarm.launch import RunCredentials, launch
from swarm.live.draw import follower_series, heading, hillshade, map_columns
from swarm.live.store import (
    COMPLETE,
    INCOMPLETE,
    NO_ESTIMATE,
    RUNNING,
    STARTING,
    WAITING,
    Frame,
    RunStore,
    load_run,
)
from tests.boundaries import check_imports
from tests.deployment import Inbox
from tests.waiting import until
from world.main import resolve_with_surface
from world.sim import WorldSim
from world.view import map_payload

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
WAIT_S = 20.0  # upper bound of a wait for something that must happen (a loaded machine)
RUN_TIMEOUT_S = 90.0  # a whole short run with the page server (about 10 s here)
STATUS = re.compile(r"tick (\d+) of (\d+)")


def _world_map(surface: str = "elliptic", followers: int = 3) -> tuple[dict, WorldSim]:
    config, surf = resolve_with_surface(RunConfig(run_id="view", surface=surface,
                                                  followers=followers))
    sim = WorldSim(config, surf)
    return map_payload(config, surf, sim.ideal), sim


# --- payloads ------------------------------------------------------------------------------------


def test_a_viewer_closing_the_tab_is_not_a_warning_but_other_bokeh_warnings_are(caplog):
    import swarm.live.server  # noqa: F401  (installs the filter on Bokeh's websocket log)
    ws = logging.getLogger("bokeh.server.views.ws")
    with caplog.at_level(logging.WARNING, logger=ws.name):
        ws.warning("Failed sending message as connection was closed")
        ws.warning("Refusing websocket connection from Origin 'http://evil'")
    assert [r.getMessage() for r in caplog.records] == [
        "Refusing websocket connection from Origin 'http://evil'"]


@pytest.mark.parametrize("surface", ["elliptic", "wavy", "hemisphere"])
def test_map_covers_the_ideal_column_within_the_size_limit(surface):
    view_map, sim = _world_map(surface)
    assert len(encode_map(view_map)) <= MAX_VIEW_BYTES
    assert decode_map(encode_map(view_map))["shape"] == view_map["shape"]
    ny, nx = view_map["shape"]
    assert ny * nx <= MAP_CELLS and min(nx, ny) >= 20
    x0, x1, y0, y1 = view_map["box"]
    ideal = sim.ideal[np.isfinite(sim.ideal).all(axis=2)]
    assert (ideal[:, 0] > x0).all() and (ideal[:, 0] < x1).all()
    assert (ideal[:, 1] > y0).all() and (ideal[:, 1] < y1).all()
    # the grid's corners are the surface's heights there (32-bit on the wire)
    wire = decode_map(encode_map(view_map))
    for i, j in ((0, 0), (ny - 1, nx - 1)):
        p = np.array([x0 if j == 0 else x1, y0 if i == 0 else y1])
        inside = getattr(sim.surface, "contains", lambda _: True)(p)
        expected = sim.surface.height(p) if inside else None
        got = wire["heights"][i * nx + j]
        assert got == (None if expected is None else pytest.approx(expected, rel=1e-6, abs=1e-6))
    if surface == "hemisphere":  # outside the domain: no height
        assert any(h is None for h in view_map["heights"])


def test_height_grid_leaves_out_points_a_surface_refuses():
    from world.geometry import SurfaceDomainError
    from world.view import height_grid

    class HalfPlane:  # defined for x >= 0 only, and says so by raising
        def height(self, p):
            if p[0] < 0:
                raise SurfaceDomainError(f"{p} is outside")
            return 2.0 * p[0]

    z = height_grid(HalfPlane(), np.array([-1.0, 0.0]), np.array([1.0, 1.0]), (2, 3))
    assert np.isnan(z[:, 0]).all() and z[:, 1:].tolist() == [[0.0, 2.0], [0.0, 2.0]]


def test_tick_rows_travel_in_chunks_and_bad_payloads_are_refused():
    rows = [{"tick": 7, "t": 8.96, "agent": k, "pos_x": float(k), "pos_y": -float(k),
             **({} if k == 0 else {"ideal_x": 1.0, "ideal_y": 2.0, "stay_range": 0.5,
                                   "persist_range": 0.1, "lost": 1, "missed": 0})}
            for k in range(2 * ROWS_PER_CHUNK + 5)]
    chunks = tick_payloads(rows, n_agents=len(rows))
    assert [len(c["rows"]) for c in chunks] == [ROWS_PER_CHUNK, ROWS_PER_CHUNK, 5]
    for chunk in chunks:
        assert len(encode_tick(chunk)) <= MAX_VIEW_BYTES
        assert decode_tick(encode_tick(chunk)) == chunk
    first = dict(zip(TICK_COLUMNS, chunks[0]["rows"][1]))
    assert first["pos_x"] == 1.0 and first["lost"] == 1 and first["est_x"] is None
    store = RunStore()
    store.add_tick(chunks[0])
    store.add_tick(chunks[1])
    assert store.snapshot().frames == ()  # the tick counts once every row is in
    store.add_tick(chunks[2])
    [frame] = store.snapshot().frames
    assert frame.tick == 7 and len(frame.rows) == len(rows) and store.snapshot().status == RUNNING
    bad = dict(chunks[0], rows=[[0, math.nan] + [None] * (len(TICK_COLUMNS) - 2)])
    with pytest.raises(ProtocolError, match="pos_x"):
        encode_tick(bad)
    with pytest.raises(ProtocolError, match="agent 9"):
        encode_tick(dict(chunks[0], agents=9, rows=[[9] + [1.0] * (len(TICK_COLUMNS) - 1)]))
    with pytest.raises(ProtocolError, match="version"):
        decode_tick(b"\x81\xa1v\x02")


def test_store_status_and_a_vanished_world():
    from swarm.live.page import status_text

    store = RunStore()
    assert "python -m swarm replay RUN_DIR" in status_text(store.snapshot(), None)
    store.world_seen()  # the world's token, before its first tick
    assert store.snapshot().status == STARTING
    assert status_text(store.snapshot(), None).endswith(STARTING)
    store.world_gone()
    assert (store.snapshot().status, store.snapshot().reason) == (
        INCOMPLETE, "the world process disappeared")
    store = RunStore()
    store.world_gone()
    assert (store.snapshot().status, store.snapshot().reason) == (
        INCOMPLETE, "the world process disappeared")
    store.world_seen()  # back before any tick (paused, or resumed): the run goes on
    assert (store.snapshot().status, store.snapshot().reason) == (STARTING, "")
    store = RunStore()
    store.finish(True)
    store.world_gone()  # the world leaves after world/done: still complete
    assert store.snapshot().status == COMPLETE
    store = RunStore()
    store.finish(False, "agent 1 did not settle")
    store.world_seen()  # a run that ended stays ended
    assert (store.snapshot().status, store.snapshot().reason) == (
        INCOMPLETE, "agent 1 did not settle")


def test_a_world_back_after_vanishing_is_running_again():
    store = RunStore()
    store.world_seen()
    rows = [{"tick": 3, "t": 3.84, "agent": k, "pos_x": float(k), "pos_y": 0.0}
            for k in range(2)]
    for chunk in tick_payloads(rows, n_agents=len(rows)):
        store.add_tick(chunk)
    assert store.snapshot().status == RUNNING
    store.world_gone()  # paused beyond the lease, or killed
    assert store.snapshot().status == INCOMPLETE
    store.world_seen()  # it runs again
    assert (store.snapshot().status, store.snapshot().reason) == (RUNNING, "")


# --- drawing data --------------------------------------------------------------------------------


def _frame(tick: int, positions: list[tuple[float, float]], ideals, estimates) -> Frame:
    rows = {}
    for k, (x, y) in enumerate(positions):
        row = dict.fromkeys(TICK_COLUMNS)
        row.update(agent=k, pos_x=x, pos_y=y, lost=0, missed=0)
        if k > 0:
            row.update(ideal_x=ideals[k][0], ideal_y=ideals[k][1], stay_range=1.0,
                       persist_range=0.1)
            if estimates[k] is not None:
                row.update(est_x=estimates[k][0], est_y=estimates[k][1], required_range=0.01)
        rows[k] = row
    return Frame(tick, 1.28 * tick, rows)


def test_map_columns_draw_every_agent_and_rod_with_headings():
    """Four agents in a column moving +y: rods from agent k−1 to follower k's true rod end."""
    ideals = {k: (3.0 * k, 1.0) for k in (1, 2, 3)}
    before = _frame(0, [(3.0 * k, 0.0) for k in range(4)], ideals, dict.fromkeys(range(4)))
    now = _frame(1, [(3.0 * k, 1.0) for k in range(4)], ideals,
                 {1: (3.1, 1.0), 2: (6.0, 1.2), 3: None})
    frames = {0: before, 1: now}
    cols = map_columns(frames, 1, sensing_range=0.5, nose=0.5)
    assert len(cols["agents"]["x"]) == 4 and len(cols["rods"]["x0"]) == 3
    assert cols["rods"]["x0"] == [0.0, 3.0, 6.0] and cols["rods"]["x1"] == [3.0, 6.0, 9.0]
    assert len(cols["estimates"]["x"]) == 2 and cols["ranges"]["radius"] == [0.5, 0.5]
    # heading +y: the heading segments point up from every agent
    assert cols["headings"]["x1"] == pytest.approx(cols["agents"]["x"])
    assert cols["headings"]["y1"] == pytest.approx([1.5] * 4)
    assert heading(frames, 0, 2) == pytest.approx(math.pi / 2)  # tick 0: its first move
    assert map_columns(frames, 1, sensing_range=None, nose=0.5)["ranges"]["x"] == []
    assert [len(xs) for xs in cols["paths"]["xs"]] == [2, 2, 2, 2]
    series = follower_series([before, now], 3)
    assert series["ranges"]["required"][1] != series["ranges"]["required"][1]  # NaN: no estimate
    assert series["ranges"]["stay"] == [1.0, 1.0]
    # a missed tick whose ranges are all zero (its leader did not move) is marked at the floor
    stuck = _frame(2, [(3.0 * k, 1.0) for k in range(4)], ideals, dict.fromkeys(range(4)))
    stuck.rows[3].update(stay_range=0.0, persist_range=0.0, missed=1)
    series = follower_series([before, now, stuck], 3)
    assert series["missed"] == {"tick": [2], "y": [0.1]} and series["lost"]["tick"] == []


def test_hillshade_lights_slopes_facing_the_light():
    """Light from the north-west: a slope rising to the east (facing west) is brighter than one
    rising to the west; cells outside the domain are transparent."""
    def plane(slope: float, hole: bool = False) -> dict:
        xs, ys = np.linspace(0, 10, 20), np.linspace(0, 10, 20)
        z = [slope * x for y in ys for x in xs]
        if hole:
            z[0] = None
        return {"shape": [20, 20], "box": [0.0, 10.0, 0.0, 10.0], "heights": z}

    east, west = hillshade(plane(0.5)), hillshade(plane(-0.5))
    assert east.shape == (20, 20, 4) and east.dtype == np.uint8
    assert east[..., :3].mean() > west[..., :3].mean() + 20
    holed = hillshade(plane(0.5, hole=True))
    assert holed[0, 0, 3] == 0 and (holed[..., 3] == 255).sum() == 399


def test_view_fits_the_box_and_every_agent_at_true_aspect():
    from swarm.live.draw import fit_view
    from swarm.live.page import MAP_SIDE, MIN_SIDE, frame_size

    box = [0.0, 40.0, 0.0, 20.0]
    assert frame_size(box) == (MAP_SIDE, MAP_SIDE // 2)
    assert frame_size([0.0, 20.0, 0.0, 40.0]) == (MAP_SIDE // 2, MAP_SIDE)
    assert frame_size([0.0, 100.0, 0.0, 1.0]) == (MAP_SIDE, MIN_SIDE)  # never a thin strip
    # agents inside the box: the view is the box, widened to the frame's ratio only
    assert fit_view(box, np.array([[5.0, 5.0]]), 1.0, 2.0) == (0.0, 40.0, 0.0, 20.0)
    assert fit_view(box, np.empty((0, 2)), 1.0, 4.0) == (-20.0, 60.0, 0.0, 20.0)
    # an agent past the box's corner: the view grows to hold it with the margin, same ratio
    x0, x1, y0, y1 = fit_view(box, np.array([[45.0, -4.0]]), 1.0, 2.0)
    assert x1 >= 46.0 and y0 <= -5.0 and x0 <= 0.0 and y1 >= 20.0
    assert (x1 - x0) / (y1 - y0) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="aspect"):
        fit_view(box, np.empty((0, 2)), 1.0, 0.0)


def test_labels_closer_than_the_gap_are_left_out():
    from swarm.live.draw import sparse_labels

    xs, ys = [0.0, 1.0, 2.5, 2.6, 10.0], [0.0] * 5
    assert sparse_labels(xs, ys, ["L", "1", "2", "3", "4"], gap=2.0) == ["L", "", "2", "", "4"]
    assert sparse_labels(xs, ys, ["L", "1", "2", "3", "4"], gap=0.05) == ["L", "1", "2", "3",
                                                                          "4"]


def test_log_axis_span_from_the_series():
    from swarm.live.draw import log_span

    assert log_span({"tick": [0, 1], "required": [math.nan, 0.02], "stay": [2.0, 0.0]},
                    pad=2.0) == (0.01, 4.0)
    assert log_span({"tick": [], "required": []}) == (1e-3, 1.0)


def test_a_box_is_widened_about_its_centre_to_the_aspect():
    from protocol.view import widen_to_aspect

    low, high = np.array([0.0, 0.0]), np.array([10.0, 2.0])
    for aspect in (0.5, 2.0, 5.0, 8.0):
        wide_low, wide_high = widen_to_aspect(low, high, aspect)
        width, height = wide_high - wide_low
        assert width / height == pytest.approx(aspect)
        assert (wide_low <= low).all() and (wide_high >= high).all()
        np.testing.assert_allclose((wide_low + wide_high) / 2, [5.0, 1.0])
    # at most 8:1 either way: a 5:1 box is kept, 1:20 widened to 1:8
    assert [b.tolist() for b in widen_to_aspect(low, high, 8.0, at_most=True)] == [
        [0.0, 0.0], [10.0, 2.0]]
    tall_low, tall_high = widen_to_aspect(np.array([0.0, 0.0]), np.array([1.0, 20.0]), 8.0,
                                          at_most=True)
    assert (tall_high - tall_low).tolist() == [2.5, 20.0]
    with pytest.raises(ValueError, match="aspect"):
        widen_to_aspect(low, high, 0.0)


def test_map_box_is_never_a_narrow_strip():
    from world.view import MAX_MAP_ASPECT, map_box

    ideal = np.array([[0.0, 0.0], [100.0, 1.0]])
    low, high = map_box(ideal, spacing=1.0)
    width, height = high - low
    assert width / height == pytest.approx(MAX_MAP_ASPECT)
    assert (low <= ideal.min(axis=0)).all() and (high >= ideal.max(axis=0)).all()
    low, high = map_box(np.array([[0.0, 0.0], [10.0, 8.0]]), spacing=1.0)  # about square: as is
    assert (high - low) == pytest.approx([10.0 + 2 * 1.0, 8.0 + 2 * 1.0])


def test_hillshade_goes_on_flat_past_the_domain():
    """A plane rising to the north, cut by the domain's east edge: along a row every cell has
    the same height and slope, so the same colour, up to the edge (filling the outside with
    the lowest height once made a cliff there, which shaded the edge cells apart)."""
    xs = np.linspace(0, 10, 20)
    z = [0.2 * y if x < 7 else None for y in xs for x in xs]
    rgba = hillshade({"shape": [20, 20], "box": [0.0, 10.0, 0.0, 10.0], "heights": z})
    inside = xs < 7
    assert (rgba[:, inside, 3] == 255).all() and (rgba[:, ~inside, 3] == 0).all()
    rows = rgba[:, inside, :3].astype(int)
    assert np.abs(rows - rows[:, :1]).max() <= 3  # the cliff made 70 levels
    assert len({tuple(row[0]) for row in rows}) > 5  # rows differ: the plane does rise


# --- the observer never needs the world ----------------------------------------------------------


def test_observer_does_not_import_world():
    """Static check of swarm/live, and a fresh interpreter that loads every live module."""
    check_imports(ROOT / "swarm" / "live",
                  tuple(f"swarm.live.{m}" for m in ("observer", "page", "server", "store", "feed",
                                                    "draw")), ("world", "agents"))


# --- the observer role on a router with access control -------------------------------------------


def _acl_router(endpoint: str, folder: Path) -> zenoh.Config:
    """A router where ``world`` and ``agent`` may do anything under ``swarm/**`` and
    ``observer`` may only subscribe (samples and liveliness) and receive."""
    (folder / "credentials.txt").write_text("world:w-pw\nagent:a-pw\nobserver:o-pw\n")
    everything = ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable",
                  "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
    acl = {
        "enabled": True, "default_permission": "deny",
        "rules": [
            {"id": "all", "permission": "allow", "flows": ["ingress", "egress"],
             "messages": everything, "key_exprs": ["swarm/**"]},
            {"id": "observe", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_subscriber", "declare_liveliness_subscriber"],
             "key_exprs": ["swarm/**"]},
            {"id": "observed", "permission": "allow", "flows": ["egress"],
             "messages": ["put", "delete", "liveliness_token"], "key_exprs": ["swarm/**"]},
        ],
        "subjects": [{"id": "trusted", "usernames": ["world", "agent"]},
                     {"id": "observer", "usernames": ["observer"]}],
        "policies": [{"id": "trusted", "subjects": ["trusted"], "rules": ["all"]},
                     {"id": "observer", "subjects": ["observer"],
                      "rules": ["observe", "observed"]}],
    }
    conf = zenoh_config("router", listen=[endpoint])
    conf.insert_json5("transport/auth/usrpwd/dictionary_file",
                      json.dumps(str(folder / "credentials.txt")))
    conf.insert_json5("access_control", json.dumps(acl))
    return conf


def _until(condition, timeout: float = WAIT_S) -> bool:
    return until(condition, timeout)


def test_observer_can_subscribe_but_neither_query_the_world_nor_publish(tmp_path):
    run = "acl"
    endpoint = free_tcp_endpoint()

    def client(user: str, password: str) -> zenoh.Session:
        return zenoh.open(zenoh_config("client", connect=[endpoint], user=user,
                                       password=password, connect_timeout=WAIT_S))

    def replies(session: zenoh.Session, key: str, timeout: float = 1.0) -> list[bytes]:
        return [r.ok.payload.to_bytes() for r in session.get(key, timeout=timeout)
                if r.ok is not None]

    with (zenoh.open(_acl_router(endpoint, tmp_path)), client("world", "w-pw") as world,
          client("agent", "a-pw") as agent, client("observer", "o-pw") as observer):
        heard, seen = Inbox(), Inbox()
        handles = [world.declare_queryable(keys.sense(run), lambda q: q.reply(q.key_expr, b"w")),
                   world.declare_subscriber(f"swarm/{run}/**", heard),
                   observer.declare_subscriber(keys.view(run), seen)]
        # positive controls: the agent's query is answered and its sample heard; the world's
        # view sample reaches the observer
        assert _until(lambda: replies(agent, keys.sense(run, 1)) == [b"w"])
        view_tick = keys.view(run, "tick")
        def delivered() -> bool:
            world.put(view_tick, b"t")
            return seen.wait_for((view_tick, b"t"), 0.1)

        assert _until(delivered)
        assert replies(observer, keys.sense(run, 1), timeout=0.5) == []
        rod = keys.rod(run, 1)
        for key in (rod, keys.tick(run), view_tick):
            observer.put(key, b"forged")
        agent.put(rod, b"after")  # sent later, so it would arrive after the forged ones
        assert heard.wait_for((rod, b"after"), WAIT_S)
        assert not [item for item in heard.items if item[1] == b"forged"]
        undeclare_all(handles)


# --- runs with the live view ---------------------------------------------------------------------


def _swarm(*args: str, log: Path) -> subprocess.Popen:
    with log.open("w") as fh:
        return subprocess.Popen([sys.executable, "-m", "swarm", *args], cwd=ROOT, stdout=fh,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env={**os.environ, "PYTHONPATH": str(ROOT)})


def _served_after_run(log: Path) -> bool:
    return "live view still at http://127.0.0.1:" in log.read_text()


def _ended(status: str) -> bool:
    """Whether the page's status reads a complete run: ``· complete``, or, where a realtime
    tick missed under the machine's load left a follower out of formation (design §7),
    ``· complete, formation broken: N follower-ticks beyond the tolerance``."""
    return re.search(r"· complete(, formation broken: \d+ follower-ticks beyond the "
                     r"tolerance)?$", status) is not None


def _complete(out: Path) -> bool:
    try:
        return json.loads((out / "summary.json").read_text())["complete"]
    except (OSError, ValueError, KeyError):
        return False


def _interrupt(proc: subprocess.Popen) -> int:
    """Ctrl-C the served page (it stays up until then); kill if it does not end."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=30)  # its own cleanup is bounded by 8 s (bounded_interrupt)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise


def test_live_run_gives_the_same_numbers(tmp_path):
    flags = ["--followers", "3", "--ticks", "12", "--run-id", "same", "--seed", "4"]
    proc = _swarm("run", "--live", "--live-port", "0", *flags,
                  "--out", str(tmp_path / "live"), log=tmp_path / "live.log")
    try:  # the page stays up after the run, until Ctrl-C
        assert _until(lambda: _served_after_run(tmp_path / "live.log"), RUN_TIMEOUT_S), \
            (tmp_path / "live.log").read_text()[-2000:]
    finally:
        code = _interrupt(proc)
    log = (tmp_path / "live.log").read_text()
    assert code == 0, log[-2000:]
    assert "live view: http://127.0.0.1:" in log and _complete(tmp_path / "live")
    config = load_config(tmp_path / "live" / "config.toml")
    launch(config, tmp_path / "plain")
    for name in ("ticks.csv", "view_map.json"):
        assert (tmp_path / "live" / name).read_bytes() == (tmp_path / "plain" / name).read_bytes()


def test_replay_store_reads_the_run_folder(tmp_path):
    config = RunConfig(run_id="folder", followers=2, ticks=8, sensing_range=2e-4)
    summary = launch(config, tmp_path / "run")
    snap = load_run(tmp_path / "run").snapshot()
    assert [f.tick for f in snap.frames] == list(range(8))
    assert snap.status == COMPLETE and snap.map["sensing_range"] == 2e-4
    lost = sum(f.rows[k]["lost"] for f in snap.frames for k in (1, 2))
    assert lost == sum(s["lost_ticks"] for s in summary["followers"].values()) > 0
    # what each follower followed: nothing at tick 0 (no reading yet), persist standing in
    # at tick 1 (edmd not ready), edmd-b itself from tick 2
    for k in (1, 2):
        assert [snap.choices[(j, k)] for j in range(8)] == [
            NO_ESTIMATE, "persist (fallback)"] + ["edmd-b"] * 6
    with pytest.raises(ValueError, match="cannot replay"):
        load_run(tmp_path)
    # an older observations.csv (no followed, no fallback): the estimator where it predicted
    path = tmp_path / "run" / "observations.csv"
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, ["tick", "agent", "estimator", "lost", "measurement",
                                     "prediction"], extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    old = load_run(tmp_path / "run").snapshot().choices
    assert [old[(j, 1)] for j in range(3)] == [NO_ESTIMATE, "edmd-b", "edmd-b"]


# --- in the browser ------------------------------------------------------------------------------


def _shots(tmp_path: Path) -> Path:
    folder = Path(os.environ.get("SWARM_SCREENSHOT_DIR", tmp_path))
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _status(page) -> str:
    return page.get_by_text(STATUS).inner_text(timeout=WAIT_S * 1000)


def _page_says(page) -> str:
    """What the page's status reads, for a failure message: a tick, waiting, or neither."""
    from playwright.sync_api import Error

    for text in (STATUS, WAITING):
        try:
            return page.get_by_text(text).first.inner_text(timeout=2000)
        except Error:
            continue
    return f"(neither 'tick N of M' nor {WAITING!r} on the page)"


def _shown_tick(page) -> int:
    return int(STATUS.search(_status(page)).group(1))


def _count(page, renderer: str, column: str) -> int:
    return page.evaluate(f"Bokeh.documents[0].get_model_by_name('{renderer}')"
                         f".data_source.data['{column}'].length")


MAP_STATE_JS = """
() => {
  const doc = Bokeh.documents[0];
  const map = doc.get_model_by_name('map');
  const finite = (arrays) => arrays.flatMap((a) => Array.from(a)).filter(Number.isFinite);
  const contours = doc.get_model_by_name('contours');
  const lines = contours.line_renderer.data_source.data;
  const agents = doc.get_model_by_name('agents').data_source.data;
  const glyphs = {};
  const walk = (root) => {
    for (const el of root.querySelectorAll('*')) {
      if (el.shadowRoot) walk(el.shadowRoot);
      if (el.classList.contains('bk-item')) {
        const canvas = el.querySelector('canvas.bk-glyph');
        const label = el.querySelector('.bk-label').textContent;
        let painted = 0;
        if (canvas && canvas.width && canvas.height) {
          const px = canvas.getContext('2d').getImageData(0, 0, canvas.width, canvas.height).data;
          for (let i = 3; i < px.length; i += 4) painted += px[i] > 0;
        }
        glyphs[label] = painted;
      }
    }
  };
  walk(document);
  return {
    view: [map.x_range.start, map.x_range.end, map.y_range.start, map.y_range.end],
    frame: [map.frame_width, map.frame_height],
    contour_x: [Math.min(...finite(lines.xs)), Math.max(...finite(lines.xs))],
    contour_y: [Math.min(...finite(lines.ys)), Math.max(...finite(lines.ys))],
    agents: {x: Array.from(agents.x), y: Array.from(agents.y), label: Array.from(agents.label)},
    relief: doc.get_model_by_name('relief') !== null,
    strip: doc.get_model_by_name('choices-plot').title.text,
    glyphs: glyphs,
  };
}
"""
"""What the page shows, from its Bokeh models and its legends' glyph canvases (in the
shadow DOM): the map's view and frame, the contour lines' extent, the agents and their labels,
whether a relief image is drawn, the estimator strip's title, and per legend entry the painted
pixels of its glyph."""


def _check_map(page, relief: bool, contour_slack: float) -> dict:
    """The map at true aspect; contour lines reaching every edge of the view (within
    ``contour_slack`` of its width or height: a DEM's edge may lie inside the view); every
    legend entry with a glyph; every agent in view and the labels at least ``LABEL_GAP``
    pixels apart; the strip titled by the run's estimator."""
    from swarm.live.page import LABEL_GAP

    state = page.evaluate(MAP_STATE_JS)
    x0, x1, y0, y1 = state["view"]
    width, height = state["frame"]
    assert (x1 - x0) / (y1 - y0) == pytest.approx(width / height, rel=1e-6), state
    for (low, high), (v0, v1) in ((state["contour_x"], (x0, x1)), (state["contour_y"], (y0, y1))):
        slack = contour_slack * (v1 - v0)
        assert low <= v0 + slack and high >= v1 - slack, state
    assert state["relief"] == relief
    assert state["glyphs"] and all(n > 0 for n in state["glyphs"].values()), state["glyphs"]
    assert "(estimator edmd" in state["strip"] and "auto" not in state["strip"]
    agents = state["agents"]
    assert all(x0 < x < x1 and y0 < y < y1
               for x, y in zip(agents["x"], agents["y"], strict=True))
    scale = width / (x1 - x0)  # pixels per metre, the same on both axes
    shown = [(x * scale, y * scale) for x, y, label in
             zip(agents["x"], agents["y"], agents["label"], strict=True) if label]
    assert "L" in agents["label"] and len(shown) >= 2
    assert all(math.dist(a, b) >= LABEL_GAP - 1e-6 for i, a in enumerate(shown)
               for b in shown[i + 1:])
    return state


def _warnings(log: str) -> list[str]:
    """Lines of a command's output that are warnings or errors (Bokeh's validation warnings
    such as ``W-1002 (EMPTY_LAYOUT)`` included)."""
    return [line for line in log.splitlines()
            if re.search(r"\b[WE]-\d{4}\b|WARNING|Warning|ERROR|Traceback", line)]


@pytest.fixture
def browser():
    if not CHROMIUM.exists():
        if os.environ.get("SWARM_NO_BROWSER"):  # .ci/run, not root, could not install it
            pytest.skip(os.environ["SWARM_NO_BROWSER"])
        if os.environ.get("CI"):  # CI installs it (.ci/run): a missing browser is a failure there
            pytest.fail("Debian's chromium is not installed although .ci/run installs it")
        pytest.skip("Debian's chromium is not installed (.ci/run installs it as root)")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


def _open(browser, url: str, requests: list[str], console: list[str] | None = None):
    """A new page at ``url``, recording its requests and, in ``console``, its console's
    warnings and errors."""
    page = browser.new_page(viewport={"width": 1300, "height": 820})
    page.on("request", lambda r: requests.append(r.url))
    if console is not None:
        page.on("console", lambda m: m.type in ("warning", "error")
                and console.append(f"{m.type}: {m.text}"))
    page.goto(url, timeout=WAIT_S * 4000)
    return page


def _external(requests: list[str], port: int) -> list[str]:
    local = (f"http://127.0.0.1:{port}/", f"ws://127.0.0.1:{port}/")
    return [u for u in requests if not u.startswith(local) and not u.startswith("data:")]


@pytest.mark.slow  # a paced run in the browser; fast tier: the page's document and the store
@pytest.mark.timeout(240)
def test_live_page_follows_a_run_and_replay_reaches_the_last_tick(browser, tmp_path):
    """A realtime 3-follower run over Zenoh with ``--live``: the page's tick advances, it draws
    4 agents and 3 rods and ends reading complete; then ``replay`` of the same folder, whose
    slider dragged to its end shows the last tick, and play runs it from the start. No request
    leaves the machine."""
    out, port, ticks = tmp_path / "run", free_port(), 30
    proc = _swarm("run", "--live", "--live-port", str(port), "--followers", "3",
                  "--ticks", str(ticks), "--mode", "realtime", "--time-scale", "0.2",
                  "--run-id", "browser", "--out", str(out), log=tmp_path / "run.log")
    requests: list[str] = []
    console: list[str] = []
    try:
        assert _until(lambda: "live view: " in (tmp_path / "run.log").read_text(), 30.0)
        page = _open(browser, f"http://127.0.0.1:{port}/", requests, console)
        page.get_by_text(re.compile(r"tick \d+ of \d+ · t =")).wait_for(timeout=30_000)
        first = _shown_tick(page)
        assert _until(lambda: _shown_tick(page) > first)
        assert _count(page, "agents", "x") == 4 and _count(page, "rods", "x0") == 3
        page.get_by_text(f"tick {ticks - 1} of {ticks - 1}").wait_for(timeout=RUN_TIMEOUT_S * 1000)
        assert _until(lambda: _ended(_status(page))), _status(page)
        assert _count(page, "agents", "x") == 4 and _count(page, "rods", "x0") == 3
        _check_map(page, relief=False, contour_slack=0.01)
        page.screenshot(path=str(_shots(tmp_path) / "live-view.png"), full_page=True)
        page.close()
        assert _until(lambda: _served_after_run(tmp_path / "run.log"), 15.0)
    finally:
        code = _interrupt(proc)
    log = (tmp_path / "run.log").read_text()
    # a tick missed under the machine's load leaves its follower out of formation (design
    # §7): then, and only then, the run's verdict is a failure
    broken = json.loads((out / "summary.json").read_text())["formation_broken"]
    assert code == (1 if broken else 0), log[-2000:]
    assert _warnings(log) == [] and console == [], (_warnings(log), console)
    assert _external(requests, port) == []

    port = free_port()
    proc = _swarm("replay", str(out), "--live-port", str(port), log=tmp_path / "replay.log")
    requests = []
    try:
        assert _until(lambda: "live view: " in (tmp_path / "replay.log").read_text(), 30.0)
        page = _open(browser, f"http://127.0.0.1:{port}/", requests, console)
        page.get_by_text(f"tick 0 of {ticks - 1}").wait_for(timeout=30_000)
        handle, track = page.locator(".noUi-handle"), page.locator(".noUi-base")
        box, end = handle.bounding_box(), track.bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.down()
        page.mouse.move(end["x"] + end["width"] + 20, box["y"] + box["height"] / 2, steps=10)
        page.mouse.up()
        page.get_by_text(f"tick {ticks - 1} of {ticks - 1}").wait_for(timeout=WAIT_S * 1000)
        assert _ended(_status(page)), _status(page)
        assert _count(page, "agents", "x") == 4 and _count(page, "rods", "x0") == 3
        _check_map(page, relief=False, contour_slack=0.01)
        page.screenshot(path=str(_shots(tmp_path) / "replay.png"), full_page=True)
        page.get_by_role("button", name="play").click()  # at the end: plays from the start
        assert _until(lambda: 0 < _shown_tick(page) < ticks - 1)
        page.close()
    finally:
        code = _interrupt(proc)
    log = (tmp_path / "replay.log").read_text()
    assert code == 0, log[-2000:]
    assert _warnings(log) == [] and console == [], (_warnings(log), console)
    assert _external(requests, port) == []


@pytest.mark.slow  # the fitting and the labels are fast unit tests above; this is the browser
@pytest.mark.timeout(240)
def test_live_page_of_a_dem_run(browser, tmp_path):
    """``swarm run --live`` on the committed DEM with 8 followers: the page shows the relief
    and contour lines at true aspect over the whole view, every agent in view with labels
    apart, legend glyphs, the strip titled ``edmd``; no warning in the log or the console."""
    port, out = free_port(), tmp_path / "run"
    proc = _swarm("run", "--live", "--live-port", str(port), "--surface",
                  "dem:tests/data/hills.tif", "--leader-start", "6,8,1,0", "--followers", "8",
                  "--ticks", "24", "--run-id", "dem", "--out", str(out), log=tmp_path / "run.log")
    console: list[str] = []
    try:
        assert _until(lambda: _served_after_run(tmp_path / "run.log"), RUN_TIMEOUT_S), \
            (tmp_path / "run.log").read_text()[-2000:]
        page = _open(browser, f"http://127.0.0.1:{port}/", [], console)
        page.get_by_text("tick 23 of 23").wait_for(timeout=WAIT_S * 1000)
        assert _until(lambda: _ended(_status(page))), _status(page)
        assert _count(page, "agents", "x") == 9
        state = _check_map(page, relief=True, contour_slack=0.05)
        x0, x1, y0, y1 = state["view"]
        assert 0.5 < (x1 - x0) / (y1 - y0) < 2.0  # this column's box is about square
        page.screenshot(path=str(_shots(tmp_path) / "live-dem.png"), full_page=True)
        page.close()
    finally:
        code = _interrupt(proc)
    log = (tmp_path / "run.log").read_text()
    assert code == 0 and _complete(out), log[-2000:]
    assert _warnings(log) == [] and console == [], (_warnings(log), console)


@pytest.mark.parametrize("relief", ["analytic", "dem"])
def test_page_draws_contours_and_relief_for_a_dem(tmp_path, relief):
    """The page built on a document (no browser): contour lines always, hillshade for DEMs, one
    range plot per follower, the newest tick live."""
    from bokeh.document import Document
    from bokeh.models import ContourRenderer, GlyphRenderer, ImageRGBA

    from swarm.live.page import Page

    view_map, _ = _world_map(followers=2)
    store = RunStore()
    store.set_map({**view_map, "relief": relief})
    rows = [{"tick": 0, "t": 0.0, "agent": k, "pos_x": float(k), "pos_y": 0.0,
             **({"ideal_x": float(k), "ideal_y": 0.0} if k else {})} for k in range(3)]
    for chunk in tick_payloads(rows, n_agents=3):
        store.add_tick(chunk)
    doc = Document()
    page = Page(doc, store, replay=False)
    renderers = page.map.renderers
    images = [r for r in renderers
              if isinstance(r, GlyphRenderer) and isinstance(r.glyph, ImageRGBA)]
    assert len(images) == (1 if relief == "dem" else 0)
    assert any(isinstance(r, ContourRenderer) for r in renderers)
    assert sorted(page.range_plots) == [1, 2]
    assert len(page.sources["agents"].data["x"]) == 3 and len(page.sources["rods"].data["x0"]) == 2
    assert page.status.text == "tick 0 of 39 · t = 0.00 · running"


def test_late_observer_gets_the_map_and_the_rest_of_the_run(tmp_path):
    """What ``watch`` does, joining a realtime run after tick 5: the map still arrives (the
    world republishes it), then every later tick and the final status."""
    from swarm.live.observer import LiveView

    config = RunConfig(run_id="late", followers=3, ticks=40, mode="realtime", time_scale=0.08)
    endpoint, ticked, result = free_tcp_endpoint(), threading.Event(), {}
    credentials = RunCredentials.create(tmp_path / "credentials", config.followers)

    def run() -> None:
        result["summary"] = launch(config, tmp_path / "late", in_process=True, endpoint=endpoint,
                                   on_tick=lambda j: j >= 5 and ticked.set(),
                                   credentials=credentials)

    world = threading.Thread(target=run, daemon=True)
    world.start()
    live = LiveView(port=0, run_id="late")
    try:
        assert ticked.wait(RUN_TIMEOUT_S)
        live.connect(zenoh_config("client", connect=[endpoint], user=OBSERVER,
                                  password=credentials.passwords[OBSERVER]))
        assert _until(lambda: live.store.snapshot().map is not None, 3.0)
        world.join(RUN_TIMEOUT_S)
        assert not world.is_alive() and result["summary"]["complete"]
        assert _until(lambda: live.store.snapshot().status == COMPLETE)
    finally:
        live.close()
    snap = live.store.snapshot()
    ticks = [f.tick for f in snap.frames]
    assert ticks[0] > 5 and ticks == list(range(ticks[0], 40))
    assert {snap.choices[(39, k)] for k in (1, 2, 3)} == {"edmd-b"}  # from agent/<id>/obs
    on_disk = json.loads((tmp_path / "late" / "view_map.json").read_text())
    assert {**snap.map, "heights": None} == {**on_disk, "heights": None}
    assert snap.map["heights"] == pytest.approx(on_disk["heights"], rel=1e-6)  # 32-bit on the wire


def test_replay_page_plays_one_tick_per_refresh(tmp_path):
    from bokeh.document import Document

    from swarm.live.page import Page

    launch(RunConfig(run_id="play", followers=1, ticks=6), tmp_path / "run")
    page = Page(Document(), load_run(tmp_path / "run"), replay=True)
    assert (page.slider.start, page.slider.end, page.slider.value) == (0, 5, 0)
    page.slider.value = 5
    page.play.active = True  # at the end, play starts over
    seen = []
    for _ in range(8):
        page.on_timer()
        seen.append(page.slider.value)
    assert seen == [1, 2, 3, 4, 5, 5, 5, 5] and page.play.active is False
    assert page.status.text == "tick 5 of 5 · t = 6.40 · complete"
    page.slider.value = 2
    assert page.status.text.startswith("tick 2 of 5 · t = 2.56")


def test_page_panels_are_labelled_and_show_what_was_followed_at_estimated_ticks(tmp_path):
    """Every panel's axes say what they hold (lengths in m); the estimator strip shows what a
    follower followed only at the ticks the range plots cover, the estimated ones (its
    observations name a choice from tick 0 on)."""
    from bokeh.document import Document

    from swarm.live.page import Page

    config = RunConfig(run_id="labels", followers=2, ticks=8)
    launch(config, tmp_path / "run", in_process=True)
    store = load_run(tmp_path / "run")
    assert min(j for j, _ in store.snapshot().choices) == 0
    page = Page(Document(), store, replay=True)
    plots = [page.map, page.choice_plot, *page.map.document.select({"type": type(page.map)})]
    for plot in plots:
        assert plot.xaxis[0].axis_label and plot.yaxis[0].axis_label, plot.name
    assert page.map.xaxis[0].axis_label == "x (m)"
    ranges = [p for p in plots if (p.name or "").startswith("ranges-")]
    assert len(ranges) == 2 and {p.yaxis[0].axis_label for p in ranges} == {"range (m)"}
    shown = set(zip(page.choices.data["tick"], page.choices.data["follower"]))
    ranged = {(j, str(k)) for k, (sources, _, _) in page.range_plots.items()
              for j, r in zip(sources["ranges"].data["tick"], sources["ranges"].data["required"])
              if not math.isnan(r)}
    assert shown == ranged
    assert min(j for j, _ in shown) == config.init_ticks


def test_cli_refuses_bad_live_arguments(tmp_path, capsys):
    from swarm.cli import main

    assert main(["watch", "--connect", "tcp/127.0.0.1:7447", "--run-id", "no spaces"]) == 2
    assert "run_id must be" in capsys.readouterr().err
    assert main(["replay", str(tmp_path)]) == 2
    assert "cannot replay" in capsys.readouterr().err
    assert main(["run", "--live", "--live-port", "70000", "--out", str(tmp_path / "r")]) == 2
    assert "port must be" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # nothing ran


def test_watch_without_a_router_names_replay(capsys):
    """A watcher pointed at a router that is gone (a `swarm run` that ended) says so in one
    line, and announces no page first."""
    from swarm.cli import main

    assert main(["watch", "--connect", free_tcp_endpoint(), "--run-id", "gone", "--live-port",
                 "0", "--cfg", "connect/timeout_ms:500"]) == 1
    out, err = capsys.readouterr()
    assert "live view" not in out
    assert err.startswith("error: the live view cannot connect to Zenoh")
    assert "swarm replay RUN_DIR" in err and ".rs:" not in err and len(err.splitlines()) == 1


def test_watch_refuses_incomplete_tls_flags(capsys, tmp_path):
    """``watch`` takes the connection flags of every command; its TLS files are used, so a
    partial set is refused before anything starts."""
    from swarm.cli import main

    (tmp_path / "ca.pem").write_text("not a certificate")
    assert main(["watch", "--connect", "tls/127.0.0.1:7447", "--run-id", "r", "--tls-ca",
                 str(tmp_path / "ca.pem")]) == 2
    assert capsys.readouterr().err == ("error: --tls-ca, --tls-cert and --tls-key must be "
                                       "given together\n")


@pytest.mark.slow  # a browser; fast tier: the page's document, the store, the observer's rights
def test_watch_page_of_a_run_assembled_elsewhere(browser, tmp_path):
    """``swarm watch`` started before the world (its router) exists: it keeps trying to
    connect, announces its page once connected, and the page follows the run (world and
    agents as processes on their own router) to its last tick and end. The run is paced
    (realtime, about 5 s): a lockstep run of 20 ticks can end in half a second, before the
    watcher's connection retry (every 0.5 s at most) has reached the world's router, and then
    the watcher has nothing to show (seen once in CI)."""
    endpoint, port = free_tcp_endpoint(), free_port()
    config = RunConfig(run_id="watched", followers=3, ticks=20, mode="realtime", time_scale=0.2)
    credentials = RunCredentials.create(tmp_path / "credentials", config.followers)
    proc = _swarm("watch", "--connect", endpoint, "--run-id", "watched", "--live-port", str(port),
                  "--user", OBSERVER, "--password-file", str(credentials.password_file(OBSERVER)),
                  log=tmp_path / "watch.log")
    result: dict = {}
    console: list[str] = []  # the page waits, then follows the run: never a warning

    def run() -> None:  # a run that fails says why, instead of the page timing out
        try:
            result["summary"] = launch(config, tmp_path / "run", endpoint=endpoint,
                                       credentials=credentials)
        except BaseException as exc:
            result["error"] = repr(exc)
            raise

    world = threading.Thread(target=run, daemon=True)
    try:
        time.sleep(1.0)  # the watcher is up, retrying: no page without a router behind it
        assert "live view: " not in (tmp_path / "watch.log").read_text()
        world.start()
        assert _until(lambda: "live view: " in (tmp_path / "watch.log").read_text(), 30.0)
        page = _open(browser, f"http://127.0.0.1:{port}/", [], console)
        last = page.get_by_text("tick 19 of 19")
        assert _until(lambda: last.is_visible() or "error" in result, RUN_TIMEOUT_S), (
            _page_says(page), result, (tmp_path / "watch.log").read_text()[-2000:])
        assert "error" not in result, result["error"]
        assert _until(lambda: _ended(_status(page))), _status(page)
        assert _count(page, "agents", "x") == 4 and _count(page, "rods", "x0") == 3
        page.close()
        world.join(RUN_TIMEOUT_S)
        assert result["summary"]["complete"]
        assert console == []
    finally:
        code = _interrupt(proc)
        if world.is_alive():
            world.join(RUN_TIMEOUT_S)
    log = (tmp_path / "watch.log").read_text()
    assert code == 0, log[-2000:]
    assert _warnings(log) == []  # Bokeh's W-1002 (EMPTY_LAYOUT) once came before the map


def test_page_shows_each_followers_formation_health_as_the_summary_counts_it(tmp_path):
    """The health table under the status: at the last tick, each follower's mean and worst
    formation error and broken ticks are ``summary.json``'s (design §7); a follower with
    broken ticks is in red, the others are not; at tick 0 nothing has broken yet."""
    from bokeh.document import Document

    from swarm.live.page import Page

    summary = launch(RunConfig(run_id="health", surface="wavy", followers=3, ticks=12, seed=9,
                               noise_range=0.05, noise_bearing=0.03, formation_tolerance=0.1),
                     tmp_path / "run", in_process=True)
    page = Page(Document(), load_run(tmp_path / "run"), replay=True)
    page.slider.value = 11
    rows = page.health.text.split("<tr")[2:]  # after the header
    assert "broken ticks (beyond 0.1 m)" in page.health.text and len(rows) == 3
    for k, row in enumerate(rows, start=1):
        s = summary["followers"][str(k)]
        cells = re.findall(r"<td>([^<]*)</td>", row)
        assert cells[0] == str(k) and cells[2:] == [
            f"{s['mean_formation_error']:.3g}", f"{s['worst_formation_error']:.3g}",
            str(s["broken_ticks"])]
        assert ("#c00000" in row) == (s["broken_ticks"] > 0)
    assert {s["broken_ticks"] > 0 for s in summary["followers"].values()} == {True, False}
    page.slider.value = 0
    assert "#c00000" not in page.health.text


def test_a_complete_run_whose_formation_broke_says_so_in_its_status():
    from types import SimpleNamespace

    from swarm.live.page import status_text

    store = RunStore()
    store.finish(True)

    def frame(broken):
        rows = {0: {"broken_ticks": None}, 1: {"broken_ticks": 0}, 2: {"broken_ticks": broken}}
        return SimpleNamespace(tick=9, t=11.52, rows=rows)

    assert status_text(store.snapshot(), frame(0)).endswith("· complete")
    text = status_text(store.snapshot(), frame(3))
    assert "formation broken: 3 follower-ticks" in text and not text.endswith("· complete")
    assert _ended(text) and _ended(status_text(store.snapshot(), frame(0)))
    assert not _ended(text.replace("3 follower", "3 more follower"))
