"""``--ros2``: the world publishes the run's topics on its own Zenoh session as rmw_zenoh would
(design §10). A plain Zenoh client, joining the run's router as its observer, listens the way a
ROS 2 subscriber does and decodes every pose with rosbags; the graph is visible through a
liveliness query; a run with ``--ros2`` records byte-identical results; ``ros2 topic echo``
where ROS 2 is installed."""
from __future__ import annotations

import itertools
import os
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh

from protocol import ros2
from protocol.config import RunConfig
from protocol.record import CONTROLS_FILE, OBS_FILE, TICKS_FILE, read_controls, read_ticks
from protocol.session import free_tcp_endpoint, zenoh_config
from swarm.deploy import OBSERVER
from swarm.launch import launch
from swarm.local import run_local
from world.ros2 import stamp_parts
from world.surfaces import make_surface

DOMAIN, FOLLOWERS, TICKS = 17, 3, 12
DRIVE = {"motion": "drive", "control_steps": 4, "snap_steps": 2, "noise_speed": 0.02,
         "noise_turn": 0.02}


class Listener:
    """What a ROS 2 subscriber would get: every sample's key, payload and attachment."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.samples: list[tuple[str, bytes, bytes | None]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        attachment = None if sample.attachment is None else sample.attachment.to_bytes()
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes(), attachment))


def _ros_run(out: Path, ros: bool, listen: bool, drive: bool = False,
             topics: tuple[str, ...] = ("pose", "required_range"),
             keys: tuple[str, ...] = (), **options) -> tuple[dict, Listener, list[str]]:
    """A 3-follower wavy run (agents in-process; ``drive``: driving followers; ``options``
    for its config); with ``listen``, an observer session subscribed to the domain's ROS 2
    data on ``topics`` (and to the key expressions ``keys``) and a liveliness query of its
    graph made once the world is up."""
    config = RunConfig(run_id=f"ros-live-{int(ros)}", surface="wavy", followers=FOLLOWERS,
                       ticks=TICKS, seed=9,
                       **(DRIVE if drive else {"noise_move": 0.02}),
                       **({"ros2": True, "ros_domain": DOMAIN} if ros else {}), **options)
    endpoint = free_tcp_endpoint()
    listener, tokens, sessions = Listener(), [], []

    def join(credentials) -> None:
        session = zenoh.open(zenoh_config("client", connect=[endpoint], user=OBSERVER,
                                          password=credentials.passwords[OBSERVER]))
        sessions.append(session)
        # as rmw_zenoh's subscriptions: one key per topic (here with wildcards over the
        # agents and types), and the graph through a liveliness query on the domain
        for key in [f"{DOMAIN}/swarm/*/{topic}/**" for topic in topics] + list(keys):
            session.declare_subscriber(key, listener)
        tokens.extend(str(r.ok.key_expr) for r in session.liveliness().get(
            ros2.graph_keys(DOMAIN)[1], timeout=10.0) if r.ok is not None)

    try:
        summary = launch(config, out, in_process=True, endpoint=endpoint,
                         before_agents=join if listen else None)
    finally:
        for session in sessions:
            session.close()
    assert summary["complete"], summary["reason"]
    return summary, listener, tokens


def test_a_zenoh_client_listening_as_ros2_decodes_every_pose(tmp_path):
    _, listener, tokens = _ros_run(tmp_path / "run", ros=True, listen=True)
    # the graph: the world's node and one publisher per topic, as rmw_zenoh declares them
    zids = {ros2.parse_token(t).zid for t in tokens}
    assert len(zids) == 1
    assert sorted(tokens) == sorted(ros2.world_tokens(DOMAIN, FOLLOWERS, zids.pop()))
    gids = {}
    for token in tokens:
        entity = ros2.parse_token(token)
        if entity.topic is not None:
            gids[ros2.topic_key(DOMAIN, entity.topic, entity.msgtype, entity.type_hash)] = (
                ros2.gid(token), entity.msgtype)
    rows = read_ticks(tmp_path / "run" / "ticks.csv")
    ticks = [list(g) for _, g in itertools.groupby(rows, key=lambda r: r["tick"])]
    surface = make_surface("wavy")
    store = ros2.typestore()
    by_key: dict[str, list] = {}
    for key, payload, attachment in listener.samples:
        assert payload[:4] == b"\x00\x01\x00\x00"  # CDR, little endian
        by_key.setdefault(key, []).append((payload, ros2.parse_attachment(attachment)))
    for k in range(FOLLOWERS + 1):
        key = ros2.topic_key(DOMAIN, ros2.agent_topic(k, "pose"),
                             "geometry_msgs/msg/PoseStamped",
                             ros2.type_hash("geometry_msgs/msg/PoseStamped"))
        samples = by_key.pop(key)
        assert len(samples) == TICKS  # every tick, in order, none lost
        for j, (payload, (sequence, _, gid)) in enumerate(samples):
            assert sequence == j + 1 and gid == gids[key][0]
            pose = store.deserialize_cdr(payload, "geometry_msgs/msg/PoseStamped")
            row = ticks[j][k]
            assert (pose.header.stamp.sec, pose.header.stamp.nanosec) == stamp_parts(row["t"])
            p = pose.pose.position
            assert (p.x, p.y) == (row["pos_x"], row["pos_y"])
            assert p.z == surface.height(np.array([p.x, p.y]))
    for k in range(1, FOLLOWERS + 1):
        key = ros2.topic_key(DOMAIN, ros2.agent_topic(k, "required_range"),
                             "std_msgs/msg/Float64", ros2.type_hash("std_msgs/msg/Float64"))
        values = [store.deserialize_cdr(payload, "std_msgs/msg/Float64").data
                  for payload, _ in by_key.pop(key)]
        assert values == [t[k]["required_range"] for t in ticks
                          if t[k]["required_range"] is not None]
    assert by_key == {}


def test_a_zenoh_client_decodes_every_command_of_a_drive_run(tmp_path):
    """A drive run with ``--ros2``: each follower's ``cmd_vel`` carries one Twist per control
    step, in order (sequence numbers 1, 2, …, the GID of its publisher's token), equal to
    ``controls.csv``; the graph holds the ``cmd_vel`` publishers; and the record is
    byte-identical to the same run's without ROS 2 (in memory)."""
    out = tmp_path / "run"
    _, listener, tokens = _ros_run(out, ros=True, listen=True, drive=True, topics=("cmd_vel",))
    zid = ros2.parse_token(tokens[0]).zid
    assert sorted(tokens) == sorted(ros2.world_tokens(DOMAIN, FOLLOWERS, zid, drive=True))
    controls = read_controls(out / CONTROLS_FILE)
    store, twist = ros2.typestore(), "geometry_msgs/msg/Twist"
    by_key: dict[str, list] = {}
    for key, payload, attachment in listener.samples:
        by_key.setdefault(key, []).append((payload, ros2.parse_attachment(attachment)))
    for k in range(1, FOLLOWERS + 1):
        topic = ros2.agent_topic(k, "cmd_vel")
        [token] = [t for t in tokens if ros2.parse_token(t).topic == topic]
        samples = by_key.pop(ros2.topic_key(DOMAIN, topic, twist, ros2.type_hash(twist)))
        rows = [c for c in controls if c["agent"] == k]
        assert len(samples) == len(rows) == TICKS * (4 + 2)
        assert [a for _, a in samples] == [(n, a[1], ros2.gid(token))
                                           for n, (_, a) in enumerate(samples, start=1)]
        messages = [store.deserialize_cdr(payload, twist) for payload, _ in samples]
        assert [(m.linear.x, m.angular.z) for m in messages] == [
            (c["speed"], c["turn"]) for c in rows]
    assert by_key == {}
    reference = tmp_path / "reference"
    run_local(RunConfig(run_id="ros-live-0", surface="wavy", followers=FOLLOWERS, ticks=TICKS,
                        seed=9, **DRIVE), reference)
    for name in (TICKS_FILE, OBS_FILE, CONTROLS_FILE):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name


def test_a_run_with_ros2_records_byte_identical_results(tmp_path):
    for ros in (False, True):
        _ros_run(tmp_path / f"run-{ros}", ros=ros, listen=False)
    for name in ("ticks.csv", "observations.csv"):
        assert (tmp_path / "run-True" / name).read_bytes() == (
            tmp_path / "run-False" / name).read_bytes()


@pytest.mark.skipif(shutil.which("ros2") is None, reason="no ROS 2 installation (ros2 not on "
                    "PATH)")
def test_ros2_topic_echo_receives_a_pose(tmp_path):
    """On a ROS 2 Jazzy machine with rmw_zenoh_cpp: ``ros2 topic echo`` as a client of the
    run's router, logged in as its observer."""
    config = RunConfig(run_id="ros-echo", surface="wavy", followers=1, ticks=400,
                       ros2=True, ros_domain=DOMAIN, mode="realtime", time_scale=0.05)
    endpoint = free_tcp_endpoint()
    result: list[subprocess.CompletedProcess] = []
    threads: list[threading.Thread] = []

    def echo(credentials) -> None:
        override = (f'mode="client";connect/endpoints=["{endpoint}"];'
                    f'transport/auth/usrpwd/user="{OBSERVER}";'
                    f'transport/auth/usrpwd/password="{credentials.passwords[OBSERVER]}"')
        env = {**os.environ, "RMW_IMPLEMENTATION": "rmw_zenoh_cpp",
               "ROS_DOMAIN_ID": str(DOMAIN), "ZENOH_CONFIG_OVERRIDE": override}

        def run() -> None:
            result.append(subprocess.run(
                ["ros2", "topic", "echo", "--once", "/swarm/agent_1/pose",
                 "geometry_msgs/msg/PoseStamped"], env=env, text=True, capture_output=True,
                timeout=60))
        threads.append(threading.Thread(target=run, daemon=True))
        threads[0].start()

    launch(config, tmp_path / "run", in_process=True, endpoint=endpoint, before_agents=echo)
    threads[0].join(timeout=90)
    assert result and result[0].returncode == 0, result
    assert "frame_id: map" in result[0].stdout


def test_formation_health_agrees_everywhere(tmp_path):
    """Design §7, one owner (:mod:`protocol.health`): a run whose formation breaks at some
    ticks (a tolerance below its noisy errors) shows every follower's same mean and worst
    formation error and broken ticks in ``summary.json``, the console table, the live view
    (the world's last ``world/view/tick``, and a replay of the folder), and on
    ``/diagnostics``: live (rmw_zenoh's key, attachment, type hash and GID) and in the
    exported bag, whose messages are byte-identical to the live ones."""
    from rosbags.rosbag2 import Reader

    from protocol import keys
    from protocol.view import TICK_COLUMNS, decode_tick
    from swarm.cli import format_summary
    from swarm.grid import table_number
    from swarm.live.store import load_run
    from swarm.ros2_export import export_run

    out, tolerance = tmp_path / "run", 0.1
    topic, msgtype = ros2.DIAGNOSTICS
    diagnostics = ros2.topic_key(DOMAIN, topic, msgtype, ros2.type_hash(msgtype))
    view = keys.view("ros-live-1", "tick")
    summary, listener, tokens = _ros_run(
        out, ros=True, listen=True, topics=(), keys=(diagnostics, view), noise_range=0.05,
        noise_bearing=0.03, formation_tolerance=tolerance)
    health = {k: (s["mean_formation_error"], s["worst_formation_error"], s["broken_ticks"])
              for k, s in ((int(k), s) for k, s in summary["followers"].items())}
    assert summary["formation_broken"] and any(b == 0 for _, _, b in health.values()) \
        and any(0 < b < TICKS for _, _, b in health.values()), health  # OK, WARN and ERROR
    # the console table: the last three columns of each follower's line
    lines = format_summary(summary).splitlines()
    for k, (mean, worst, broken) in health.items():
        [line] = [line for line in lines if line.split()[:1] == [str(k)]]
        assert line.split()[-3:] == [table_number(mean), table_number(worst), str(broken)]
    # the live view: the last tick the world published, and a replay of the folder
    views = [decode_tick(payload) for key, payload, _ in listener.samples if key == view]
    last = {row[0]: dict(zip(TICK_COLUMNS, row)) for body in views if body["tick"] == TICKS - 1
            for row in body["rows"]}
    replayed = load_run(out).snapshot().frames[-1].rows
    for shown in (last, replayed):
        assert {k: (shown[k]["mean_formation_error"], shown[k]["worst_formation_error"],
                    shown[k]["broken_ticks"]) for k in health} == health
    # ROS 2, live: one DiagnosticArray per tick, as rmw_zenoh sends it
    [token] = [t for t in tokens if ros2.parse_token(t).topic == topic]
    samples = [(payload, ros2.parse_attachment(a)) for key, payload, a in listener.samples
               if key == diagnostics]
    assert [(n, gid) for _, (n, _, gid) in samples] == [
        (n, ros2.gid(token)) for n in range(1, TICKS + 1)]
    store = ros2.typestore()
    message = store.deserialize_cdr(samples[-1][0], msgtype)
    Status = store.types["diagnostic_msgs/msg/DiagnosticStatus"]
    for k, status in enumerate(message.status, start=1):
        values = {v.key: v.value for v in status.values}
        mean, worst, broken = health[k]
        assert (float(values["mean_formation_error"]), float(values["worst_formation_error"]),
                int(values["broken_ticks"])) == (mean, worst, broken)
        assert float(values["formation_tolerance"]) == tolerance
        error = float(values["formation_error"])
        assert status.level == (Status.ERROR if error > tolerance else
                                Status.WARN if broken else Status.OK), (status, error)
        assert (status.name, status.hardware_id) == (f"swarm_world: agent_{k} formation",
                                                     f"agent_{k}")
    assert len(message.status) == FOLLOWERS
    # ... and in the bag: the same messages, byte for byte
    with Reader(export_run(out)) as reader:
        [connection] = [c for c in reader.connections if c.topic == topic]
        assert (connection.msgtype, connection.digest) == (msgtype, ros2.type_hash(msgtype))
        recorded = [bytes(raw) for _, _, raw in reader.messages(connections=[connection])]
    assert recorded == [payload for payload, _ in samples]
