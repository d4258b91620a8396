"""The docker-compose deployment without Docker: the same router configuration, credentials and
service commands run locally; the router's access control checked with real sessions; and
what the world's sensing replies reveal (never absolute positions unless the run enables GPS).

The router is a Zenoh session opened in router mode from ``deploy/zenoh/router.json5`` (the
file the compose ``zenoh`` service runs), with its listen endpoint moved to a free loopback
port and its credentials path mapped through the compose volume that mounts it.
"""
from __future__ import annotations

import dataclasses
import json
import math
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path

import pytest
import yaml
import zenoh

from protocol import keys
from protocol.config import RunConfig, load_config
from protocol.messages import Sensing, encode
from protocol.session import free_tcp_endpoint, zenoh_config
from swarm.local import run_local
from world.sim import WorldSim

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]
ROUTER_IN_COMPOSE = "tcp/zenoh:7447"
AGENTS = ("leader", "follower-1", "follower-2", "follower-3")
RUN_ID = load_config(ROOT / "deploy" / "run.toml").run_id
WAIT_S = 5.0  # upper bound of every wait for something that must happen
ABSENT_S = 0.5  # how long a message that must not arrive is given to arrive anyway
POLL_S = 0.05
RUN_TIMEOUT_S = 60.0  # the whole compose run (about 3 s here)


# --- compose services, mapped to this machine -------------------------------------------------


def _mounts(service: str, volumes_dir: Path) -> dict[str, Path]:
    """Container path -> local path of ``service``'s volumes; named volumes in ``volumes_dir``."""
    mounts = {}
    for spec in SERVICES[service].get("volumes", []):
        source, target = spec.split(":")[:2]
        mounts[target] = ROOT / source if source.startswith(".") else volumes_dir / source
    return mounts


def _local_path(arg: str, mounts: dict[str, Path]) -> str:
    """``arg`` with a container path replaced by the local path mounted there."""
    for target, local in mounts.items():
        if arg == target or arg.startswith(target + "/"):
            return str(local / Path(arg).relative_to(target))
    return arg


def _local_command(service: str, endpoint: str, volumes_dir: Path) -> list[str]:
    """The compose ``command`` of ``service``, runnable here."""
    mounts = _mounts(service, volumes_dir)
    program, *args = SERVICES[service]["command"]
    if program != "python":
        raise ValueError(f"service {service!r} does not run python: {program!r}")
    return [sys.executable] + [endpoint if a == ROUTER_IN_COMPOSE else _local_path(a, mounts)
                               for a in args]


def _option(service: str, flag: str) -> str:
    command = SERVICES[service]["command"]
    return command[command.index(flag) + 1]


def _router_config(endpoint: str) -> zenoh.Config:
    """The compose router's configuration, listening on ``endpoint`` with local paths."""
    mounts = _mounts("zenoh", Path("/nonexistent"))  # the router has no named volume
    command = SERVICES["zenoh"]["command"]
    path = _local_path(command[command.index("-c") + 1], mounts)
    conf = zenoh.Config.from_json5(Path(path).read_text())
    dictionary_key = "transport/auth/usrpwd/dictionary_file"
    dictionary = json.loads(conf.get_json(dictionary_key))
    conf.insert_json5(dictionary_key, json.dumps(_local_path(dictionary, mounts)))
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return conf


@pytest.fixture
def router():
    """A running router from the compose configuration; yields its loopback endpoint."""
    endpoint = free_tcp_endpoint()
    with zenoh.open(_router_config(endpoint)):
        yield endpoint


def _client(endpoint: str, service: str, password: str | None = None,
            connect_timeout: float = WAIT_S) -> zenoh.Session:
    """A client session with ``service``'s compose credentials (or another password)."""
    return zenoh.open(zenoh_config(
        "client", connect=[endpoint], user=_option(service, "--user"),
        password=_option(service, "--password") if password is None else password,
        connect_timeout=connect_timeout))


# --- the deployment files agree with one another -----------------------------------------------


def test_compose_matches_router_and_credentials():
    dictionary = json.loads(_router_config("tcp/127.0.0.1:7447").get_json(
        "transport/auth/usrpwd/dictionary_file"))
    credentials = dict(line.split(":", 1) for line in Path(dictionary).read_text().splitlines())
    assert Path(dictionary) == ROOT / "deploy" / "zenoh" / "credentials.txt"
    assert set(credentials) == {"world", *AGENTS}
    for service in ("world", *AGENTS):
        command = SERVICES[service]["command"]
        assert command[command.index("--connect") + 1] == ROUTER_IN_COMPOSE
        assert credentials[_option(service, "--user")] == _option(service, "--password")
        assert _local_path(_option(service, "--config"), _mounts(service, Path())) == str(
            ROOT / "deploy" / "run.toml")
    for agent in AGENTS:
        assert _option(agent, "--mode") == "client"
    assert [_option(f"follower-{k}", "--id") for k in (1, 2, 3)] == ["1", "2", "3"]
    assert load_config(ROOT / "deploy" / "run.toml").followers == 3
    image_version = SERVICES["zenoh"]["image"].rpartition(":")[2]
    assert image_version.split(".")[:2] == version("eclipse-zenoh").split(".")[:2]


def test_compose_services_complete_a_run(router, tmp_path):
    """Every compose service's command, run here against the compose router config."""
    procs, logs = {}, {}
    try:
        for service in ("world", *AGENTS):
            logs[service] = tmp_path / f"{service}.log"
            with logs[service].open("w") as log:
                procs[service] = subprocess.Popen(
                    _local_command(service, router, tmp_path), cwd=ROOT, stdout=log,
                    stderr=subprocess.STDOUT)
        deadline = time.monotonic() + RUN_TIMEOUT_S
        codes = {service: proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                 for service, proc in procs.items()}
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    output = {service: log.read_text()[-2000:] for service, log in logs.items()}
    assert codes == dict.fromkeys(procs, 0), output
    out = Path(_local_path(_option("world", "--out"), _mounts("world", tmp_path)))
    summary = json.loads((out / "summary.json").read_text())
    config = load_config(ROOT / "deploy" / "run.toml")
    assert summary["complete"] and summary["ticks_completed"] == config.ticks
    assert set(summary["followers"]) == {"1", "2", "3"}
    for stats in summary["followers"].values():
        assert stats["estimated_ticks"] == config.ticks - config.init_ticks
        assert stats["missed_ticks"] == 0


# --- access control ------------------------------------------------------------------------------


class Inbox:
    """What a subscriber or liveliness subscriber received: (key, payload) pairs, with waits."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cond.notify_all()

    def wait_for(self, item: tuple[str, bytes], timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: item in self.items, timeout)

    def keys(self) -> set[str]:
        with self._cond:
            return {key for key, _ in self.items}


def _until(condition: Callable[[], bool], timeout: float = WAIT_S) -> bool:
    """Poll ``condition`` until it holds (True) or ``timeout`` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(POLL_S)
    return False


def _delivered(send: Callable[[], None], inbox: Inbox, item: tuple[str, bytes]) -> bool:
    """Send until ``item`` arrives (routes are declared asynchronously); False on timeout."""
    def attempt() -> bool:
        send()
        return inbox.wait_for(item, 0.1)
    return _until(attempt)


def _undeclare(handles: list) -> None:
    for handle in reversed(handles):
        handle.undeclare()


def _replies(session: zenoh.Session, key: str, timeout: float = 1.0) -> list[tuple[bool, bytes]]:
    """Every reply to a query on ``key`` from every queryable (no consolidation): (ok, payload)."""
    replies = session.get(key, target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
    return [(True, r.ok.payload.to_bytes()) if r.ok is not None
            else (False, r.err.payload.to_bytes()) for r in replies]


def test_agent_cannot_publish_as_another_agent_or_as_the_world(router):
    rod_1, rod_2 = keys.rod(RUN_ID, 1), keys.rod(RUN_ID, 2)
    tick = keys.tick(RUN_ID)
    with (_client(router, "world") as world, _client(router, "leader") as leader,
          _client(router, "follower-1") as follower):
        rods, ticks = Inbox(), Inbox()
        handles = [world.declare_subscriber(keys.rod(RUN_ID), rods),
                   leader.declare_subscriber(tick, ticks)]
        # Positive controls: follower 1's own rod reaches the world, the world's tick the leader.
        assert _delivered(lambda: follower.put(rod_1, b"own"), rods, (rod_1, b"own"))
        assert _delivered(lambda: world.put(tick, b"world"), ticks, (tick, b"world"))
        # Follower 1 as follower 2: sent before a legitimate sample on the same link, so it
        # would have arrived first.
        follower.put(rod_2, b"forged")
        follower.put(rod_1, b"after")
        assert rods.wait_for((rod_1, b"after"), WAIT_S)
        assert rod_2 not in rods.keys()
        # Follower 1 as the world: the leader never sees the forged tick.
        follower.put(tick, b"forged")
        world.put(tick, b"after")
        assert ticks.wait_for((tick, b"after"), WAIT_S)
        assert not ticks.wait_for((tick, b"forged"), ABSENT_S)
        _undeclare(handles)


def test_followers_hear_missed_ticks_only_from_the_world(router):
    missed = keys.missed(RUN_ID)
    with (_client(router, "world") as world, _client(router, "follower-1") as follower,
          _client(router, "follower-2") as other):
        inbox = Inbox()
        handles = [other.declare_subscriber(missed, inbox)]
        assert _delivered(lambda: world.put(missed, b"world"), inbox, (missed, b"world"))
        follower.put(missed, b"forged")
        world.put(missed, b"after")
        assert inbox.wait_for((missed, b"after"), WAIT_S)
        assert not inbox.wait_for((missed, b"forged"), ABSENT_S)
        _undeclare(handles)


def test_agent_queries_only_its_own_sensing_and_motion(router):
    asked = []

    def answer(query: zenoh.Query) -> None:
        asked.append(str(query.key_expr))
        if "/act/" in str(query.key_expr):
            query.reply_err(b"refused")
        else:
            query.reply(query.key_expr, b"world")

    with _client(router, "world") as world, _client(router, "follower-1") as follower:
        handles = [world.declare_queryable(keys.sense(RUN_ID), answer),
                   world.declare_queryable(keys.act(RUN_ID), answer)]
        # Positive controls: its own sensing is answered, and an error reply comes through.
        assert _until(lambda: _replies(follower, keys.sense(RUN_ID, 1)) == [(True, b"world")])
        assert _replies(follower, keys.act(RUN_ID, 1)) == [(False, b"refused")]
        for other in (0, 2):
            assert _replies(follower, keys.sense(RUN_ID, other), ABSENT_S) == []
            assert _replies(follower, keys.act(RUN_ID, other), ABSENT_S) == []
        assert not any(key.endswith(("/0", "/2")) for key in asked)
        _undeclare(handles)


def test_agent_cannot_serve_world_queries_or_hold_another_token(router):
    """Follower 1 can neither answer follower 2's sensing queries nor claim its liveliness."""
    sense_2 = keys.sense(RUN_ID, 2)
    with (_client(router, "world") as world, _client(router, "follower-1") as follower,
          _client(router, "follower-2") as victim):
        tokens = Inbox()
        handles = [
            world.declare_queryable(keys.sense(RUN_ID), lambda q: q.reply(q.key_expr, b"world")),
            world.liveliness().declare_subscriber(keys.alive(RUN_ID, "*"), tokens, history=True),
            follower.declare_queryable(sense_2, lambda q: q.reply(q.key_expr, b"forged")),
            follower.liveliness().declare_token(keys.alive(RUN_ID, 2)),
            # Declared last on the same link: once the world sees it, the router has handled
            # the forged declarations above.
            follower.liveliness().declare_token(keys.alive(RUN_ID, 1)),
        ]
        assert tokens.wait_for((keys.alive(RUN_ID, 1), b""), WAIT_S)
        assert keys.alive(RUN_ID, 2) not in tokens.keys()
        assert _until(lambda: (True, b"world") in _replies(victim, sense_2))
        assert _replies(victim, sense_2) == [(True, b"world")]
        _undeclare(handles)


def _agent_id(service: str) -> int:
    return 0 if service == "leader" else int(_option(service, "--id"))


@pytest.mark.parametrize("service", AGENTS)
def test_agent_sees_the_world_and_its_own_token(router, service):
    """What liveliness an agent needs: the world's token, and its own (a second process with
    the same id finds it and refuses to start)."""
    own = keys.alive(RUN_ID, _agent_id(service))
    with _client(router, "world") as world, _client(router, service) as agent:
        world_seen = Inbox()
        handles = [world.liveliness().declare_token(keys.alive(RUN_ID, "world")),
                   agent.liveliness().declare_subscriber(keys.alive(RUN_ID, "world"), world_seen,
                                                          history=True),
                   agent.liveliness().declare_token(own)]
        assert world_seen.wait_for((keys.alive(RUN_ID, "world"), b""), WAIT_S)
        with _client(router, service) as twin:
            assert _until(lambda: [str(r.ok.key_expr) for r in twin.liveliness().get(
                own, timeout=1.0) if r.ok is not None] == [own])
        _undeclare(handles)


def test_follower_receives_only_its_leaders_rod(router):
    rod_0 = keys.rod(RUN_ID, 0)
    with (_client(router, "world") as world, _client(router, "leader") as leader,
          _client(router, "follower-1") as follower, _client(router, "follower-2") as other):
        tokens, own, foreign = Inbox(), Inbox(), Inbox()
        handles = [world.liveliness().declare_subscriber(keys.alive(RUN_ID, "*"), tokens,
                                                          history=True),
                   other.declare_subscriber(rod_0, foreign),
                   # Declared after the subscription: once the world sees the token, the
                   # router has handled the subscription.
                   other.liveliness().declare_token(keys.alive(RUN_ID, 2))]
        assert tokens.wait_for((keys.alive(RUN_ID, 2), b""), WAIT_S)
        handles.append(follower.declare_subscriber(rod_0, own))
        assert _delivered(lambda: leader.put(rod_0, b"rod"), own, (rod_0, b"rod"))
        assert not foreign.wait_for((rod_0, b"rod"), ABSENT_S)
        _undeclare(handles)


def test_wrong_credentials_are_refused(router):
    with _client(router, "follower-1"):  # positive control: the right password opens
        pass
    for service, password in (("follower-1", "wrong"), ("world", _option("leader", "--password"))):
        with pytest.raises(zenoh.ZError):
            _client(router, service, password=password, connect_timeout=1.0).close()
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh_config("client", connect=[router], connect_timeout=1.0)).close()


# --- what sensing reveals ------------------------------------------------------------------------


def _sensing_log(monkeypatch, config: RunConfig) -> list[tuple[int, Sensing, list[tuple]]]:
    """Run ``config`` locally; every sensing reply, with its agent and every agent's (x, y, z)."""
    log = []
    original = WorldSim.sense

    def sense(self: WorldSim, agent: int, tick: int, phase: str) -> Sensing:
        reply = original(self, agent, tick, phase)
        poses = [(*map(float, s.pos), float(self.surface.height(s.pos))) for s in self.agents]
        log.append((agent, reply, poses))
        return reply

    monkeypatch.setattr(WorldSim, "sense", sense)
    run_local(config)
    return log


def _numbers(msg: Sensing) -> list[float]:
    """Every number a sensing reply carries."""
    values = []
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        values += [float(x) for x in (value if isinstance(value, tuple) else [value])
                   if isinstance(x, float)]
    return values


def _reveals(reply: Sensing, pose: tuple[float, float, float]) -> bool:
    """Whether any coordinate of ``pose`` is in ``reply``, as a number or as wire bytes."""
    wire = encode(reply)
    return any(struct.pack(">d", c) in wire
               or any(math.isclose(x, c, rel_tol=0, abs_tol=1e-9) for x in _numbers(reply))
               for c in pose)


def test_sensing_never_reveals_absolute_positions_without_gps(monkeypatch):
    log = _sensing_log(monkeypatch, RunConfig(run_id="privacy", followers=2, ticks=8,
                                              velocity="oracle"))
    assert len(log) >= 2 * 8 * 2  # every follower senses at least twice a tick
    for _, reply, poses in log:
        assert reply.gps is None and reply.leader_gps is None
        assert not any(_reveals(reply, pose) for pose in poses)


def test_sensing_reveals_positions_when_the_run_enables_gps(monkeypatch):
    """Positive control of the test above: with GPS on, the same checks see the positions."""
    log = _sensing_log(monkeypatch, RunConfig(run_id="privacy", followers=2, ticks=8, gps=True))
    for agent, reply, poses in log:
        assert reply.gps == pytest.approx(poses[agent], abs=1e-12)
        assert reply.leader_gps == pytest.approx(poses[agent - 1], abs=1e-12)
        assert _reveals(reply, poses[agent]) and _reveals(reply, poses[agent - 1])
