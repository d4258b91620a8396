"""``python -m swarm export``: a finished run as a rosbag2/MCAP bag (design §10), read back with
rosbags and, independently, with ``mcap`` + ``mcap-ros2-support``; refusals; the [ros] extra
missing; ``ros2 topic echo`` where a ROS 2 installation exists."""
from __future__ import annotations

import itertools
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from protocol import ros2
from protocol.config import RunConfig
from protocol.distribution import missing_extra_message
from protocol.folder import LOCK_FILE
from protocol.record import read_controls, read_ticks
from swarm.cli import main as swarm_main
from swarm.launch import launch
from swarm.ros2_export import export_run
from world.ros2 import stamp_ns, stamp_parts
from world.surfaces import make_surface

ROOT = Path(__file__).resolve().parents[1]
FOLLOWERS, TICKS = 3, 14


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ros2-export") / "run"
    config = RunConfig(run_id="ros-export", surface="wavy", followers=FOLLOWERS, ticks=TICKS,
                       noise_range=0.01, seed=4)
    summary = launch(config, out, in_process=True)
    assert summary["complete"], summary["reason"]
    return out


@pytest.fixture(scope="module")
def bag(run_dir) -> Path:
    return export_run(run_dir)


def _ticks(run_dir: Path) -> list[list[dict]]:
    rows = read_ticks(run_dir / "ticks.csv")
    return [list(g) for _, g in itertools.groupby(rows, key=lambda r: r["tick"])]


def _rosbags_messages(bag: Path) -> dict[str, list[tuple[int, object]]]:
    from rosbags.rosbag2 import Reader

    store = ros2.typestore()
    out: dict[str, list] = {}
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["storage_identifier"] == "mcap"
    assert metadata["relative_file_paths"] == ["bag.mcap"]
    with Reader(bag) as reader:
        for connection, stamp, raw in reader.messages():
            out.setdefault(connection.topic, []).append(
                (stamp, store.deserialize_cdr(raw, connection.msgtype)))
    return out


def _mcap_messages(bag: Path) -> tuple[dict[str, list[tuple[int, object]]], dict[str, str]]:
    """Every message decoded by mcap_ros2 from the schemas embedded in the file, and each
    channel's schema encoding."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    [path] = bag.glob("*.mcap")
    out: dict[str, list] = {}
    encodings = {}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            encodings[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out, encodings


def _check_run_topics(messages: dict, ticks: list[list[dict]], surface) -> None:
    """Every pose, point and required range of ``messages`` (either reader's) against
    ``ticks.csv``: positions exactly, heights F(x, y), stamps the tick's time."""
    n_agents = FOLLOWERS + 1
    assert set(messages) == {topic for topic, _ in ros2.run_topics(FOLLOWERS)}
    assert len(messages["/clock"]) == len(messages["/tf"]) == len(ticks)
    for k in range(n_agents):
        poses = messages[ros2.agent_topic(k, "pose")]
        paths = messages[ros2.agent_topic(k, "path")]
        assert len(poses) == len(paths) == len(ticks)
        for j, ((stamp, pose), (_, path)) in enumerate(zip(poses, paths, strict=True)):
            row = ticks[j][k]
            assert stamp == stamp_ns(row["t"])
            assert (pose.header.stamp.sec, pose.header.stamp.nanosec) == stamp_parts(row["t"])
            assert pose.header.frame_id == "map"
            p = pose.pose.position
            assert (p.x, p.y) == (row["pos_x"], row["pos_y"])
            assert p.z == surface.height(np.array([p.x, p.y]))
            q = pose.pose.orientation
            yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
            assert math.isclose(yaw, math.atan2(row["heading_y"], row["heading_x"]),
                                abs_tol=1e-9)
            assert len(path.poses) == j + 1
            assert [(s.pose.position.x, s.pose.position.y) for s in path.poses] == [
                (ticks[i][k]["pos_x"], ticks[i][k]["pos_y"]) for i in range(j + 1)]
        if k == 0:
            continue
        ideal = messages[ros2.agent_topic(k, "ideal")]
        assert [(m.point.x, m.point.y) for _, m in ideal] == [
            (t[k]["ideal_x"], t[k]["ideal_y"]) for t in ticks]
        estimated = [t[k] for t in ticks if t[k]["est_x"] is not None]
        assert len(estimated) == TICKS - 4
        estimates = messages[ros2.agent_topic(k, "estimate")]
        assert [(m.point.x, m.point.y) for _, m in estimates] == [
            (r["est_x"], r["est_y"]) for r in estimated]
        ranges = messages[ros2.agent_topic(k, "required_range")]
        assert [m.data for _, m in ranges] == [r["required_range"] for r in estimated]
        assert [s for s, _ in ranges] == [stamp_ns(r["t"]) for r in estimated]


def test_bag_read_back_with_rosbags_matches_ticks_csv(run_dir, bag):
    assert bag == run_dir / "bag" and (bag / "metadata.yaml").is_file()
    ticks = _ticks(run_dir)
    surface = make_surface("wavy")
    messages = _rosbags_messages(bag)
    _check_run_topics(messages, ticks, surface)
    markers = messages["/swarm/markers"]
    # the terrain first, and again every 5 s of simulation time (T_c 1.28 s: ticks 0, 4, 8,
    # 12) before that tick's markers: a triangle mesh on the surface, at most 100 x 100 nodes
    terrains = [(stamp, array) for stamp, array in markers
                if any(m.ns == "terrain" for m in array.markers)]
    assert any(m.ns == "terrain" for m in markers[0][1].markers)
    assert [stamp for stamp, _ in terrains] == [stamp_ns(ticks[j][0]["t"]) for j in (0, 4, 8, 12)]
    [terrain] = terrains[0][1].markers
    assert terrain.ns == "terrain" and terrain.type == terrain.TRIANGLE_LIST
    assert len(terrain.points) % 3 == 0 and 0 < len(terrain.points) <= 2 * 99 * 99 * 3
    assert len(terrain.colors) == len(terrain.points)
    for v in terrain.points[::97]:
        assert v.z == pytest.approx(surface.height(np.array([v.x, v.y])), abs=1e-12)
    for _, again in terrains[1:]:
        [copy] = again.markers
        assert [(v.x, v.y, v.z) for v in copy.points] == [(v.x, v.y, v.z) for v in terrain.points]
    per_tick = [(stamp, array) for stamp, array in markers
                if all(m.ns != "terrain" for m in array.markers)]
    assert len(per_tick) + len(terrains) == len(markers)
    # each tick: the agents, and the rods along the geodesic from holder to rod end
    for (_, array), tick in zip(per_tick, ticks, strict=True):
        agents, *rods = array.markers
        assert agents.type == agents.SPHERE_LIST and len(agents.points) == FOLLOWERS + 1
        assert [r.id for r in rods] == list(range(1, FOLLOWERS + 1))
        for rod in rods:
            holder, follower = tick[rod.id - 1], tick[rod.id]
            assert rod.type == rod.LINE_STRIP and len(rod.points) == 9
            assert (rod.points[0].x, rod.points[0].y) == (holder["pos_x"], holder["pos_y"])
            end = np.array([rod.points[-1].x, rod.points[-1].y])
            np.testing.assert_allclose(end, [follower["ideal_x"], follower["ideal_y"]],
                                       atol=1e-6)
            length = sum(math.dist((a.x, a.y, a.z), (b.x, b.y, b.z))
                         for a, b in itertools.pairwise(rod.points))
            assert length == pytest.approx(3.57, rel=5e-3)  # chords of the geodesic


def test_bag_read_back_with_mcap_matches_ticks_csv(run_dir, bag):
    messages, encodings = _mcap_messages(bag)
    _check_run_topics(messages, _ticks(run_dir), make_surface("wavy"))
    for topic, msgtype in ros2.run_topics(FOLLOWERS):
        assert encodings[topic] == (msgtype, "ros2msg", "cdr")


def test_bag_metadata_names_types_and_hashes(bag):
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    expected = {topic: (msgtype, ros2.type_hash(msgtype))
                for topic, msgtype in ros2.run_topics(FOLLOWERS)}
    with Reader(bag) as reader:
        found = {c.topic: (c.msgtype, c.digest) for c in reader.connections}
        assert reader.ros_distro == "jazzy"
        assert {(q.reliability.name, q.durability.name, q.history.name, q.depth)
                for c in reader.connections for q in c.ext.offered_qos_profiles} == {
            ("RELIABLE", "VOLATILE", "KEEP_LAST", 10)}
    assert found == expected
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["ros_distro"] == "jazzy"
    # the MCAP file as rosbag2 Jazzy writes it: per channel the offered QoS and the type
    # hash, and the bag's metadata in a "rosbag2" record
    with (bag / "bag.mcap").open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        records = {m.name: m.metadata for m in reader.iter_metadata()}
    channels = {c.topic: c for c in summary.channels.values()}
    assert set(channels) == set(expected)
    for topic, channel in channels.items():
        assert set(channel.metadata) == {"offered_qos_profiles", "topic_type_hash"}
        assert channel.metadata["topic_type_hash"] == expected[topic][1]
        [qos] = yaml.safe_load(channel.metadata["offered_qos_profiles"])
        assert (qos["reliability"], qos["durability"], qos["history"], qos["depth"]) == (
            "reliable", "volatile", "keep_last", 10)
        assert qos["deadline"] == {"sec": 9223372036, "nsec": 854775807}  # infinite
    stored = yaml.safe_load(records["rosbag2"]["serialized_metadata"])
    assert stored["ros_distro"] == "jazzy"
    assert stored["topics_with_message_count"] == metadata["topics_with_message_count"]


def test_a_player_that_starts_at_half_time_still_gets_the_terrain(run_dir, bag):
    """Read from the middle of the bag on (a late start, a seek), with either reader: the
    terrain arrives within 5 s of simulation time."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.rosbag2 import Reader

    store = ros2.typestore()
    with Reader(bag) as reader:
        half = (reader.start_time + reader.end_time) // 2
        connection = [c for c in reader.connections if c.topic == "/swarm/markers"]
        seen = [(stamp, store.deserialize_cdr(raw, c.msgtype)) for c, stamp, raw in
                reader.messages(connections=connection, start=half)]
    with (bag / "bag.mcap").open("rb") as fh:
        decoded = [(message.log_time, ros_msg) for _, _, message, ros_msg in
                   make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                       topics=["/swarm/markers"]) if message.log_time >= half]
    for messages in (seen, decoded):
        assert messages and messages[0][0] >= half
        terrain = [stamp for stamp, array in messages
                   if any(m.ns == "terrain" for m in array.markers)]
        assert terrain and terrain[0] - half <= 5e9


@pytest.fixture(scope="module")
def drive_run(tmp_path_factory) -> Path:
    """A small run of driving followers with actuation noise (commanded ≠ achieved)."""
    out = tmp_path_factory.mktemp("ros2-export-drive") / "run"
    config = RunConfig(run_id="ros-export-drive", surface="wavy", followers=2, ticks=8,
                       motion="drive", control_steps=4, snap_steps=2, noise_speed=0.02,
                       noise_turn=0.02, seed=6)
    summary = launch(config, out, in_process=True)
    assert summary["complete"], summary["reason"]
    return out


def _check_cmd_vel(messages: dict, controls: list[dict], followers: int) -> None:
    """Each follower's ``cmd_vel`` (either reader's): one twist per row of ``controls.csv``,
    in order, ``linear.x`` the commanded speed, ``angular.z`` the commanded turn, recorded at
    the step's time."""
    for k in range(1, followers + 1):
        rows = [c for c in controls if c["agent"] == k]
        twists = messages[ros2.agent_topic(k, "cmd_vel")]
        assert len(twists) == len(rows) == 8 * (4 + 2)
        stamps = [stamp for stamp, _ in twists]
        assert stamps == [stamp_ns(c["t"]) for c in rows] and stamps == sorted(set(stamps))
        assert [(m.linear.x, m.angular.z) for _, m in twists] == [
            (c["speed"], c["turn"]) for c in rows]
        assert all((m.linear.y, m.linear.z, m.angular.x, m.angular.y) == (0, 0, 0, 0)
                   for _, m in twists)


def test_a_drive_runs_bag_holds_every_command(drive_run):
    bag = export_run(drive_run)
    controls = read_controls(drive_run / "controls.csv")
    assert any(c["speed"] != c["achieved_speed"] for c in controls)
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        found = {c.topic: (c.msgtype, c.digest) for c in reader.connections}
    assert found == {topic: (msgtype, ros2.type_hash(msgtype))
                     for topic, msgtype in ros2.run_topics(2, drive=True)}
    _check_cmd_vel(_rosbags_messages(bag), controls, 2)
    messages, encodings = _mcap_messages(bag)
    _check_cmd_vel(messages, controls, 2)
    assert encodings["/swarm/agent_1/cmd_vel"] == ("geometry_msgs/msg/Twist", "ros2msg", "cdr")
    # a drive run's record without its controls is refused (one line)
    (drive_run / "controls.csv").rename(drive_run / "controls.kept")
    try:
        with pytest.raises(ValueError, match="drive run without controls.csv"):
            export_run(drive_run, drive_run / "bag2")
    finally:
        (drive_run / "controls.kept").rename(drive_run / "controls.csv")


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: "), err
    return err


def test_refusals(run_dir, bag, tmp_path, capsys):
    assert swarm_main(["export", str(run_dir)]) == 2  # the bag exists
    assert "already exists" in _one_error_line(capsys)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("x")
    assert swarm_main(["export", str(foreign)]) == 2
    assert "not a run folder" in _one_error_line(capsys)
    assert swarm_main(["export", str(tmp_path / "missing")]) == 2
    assert "not a folder" in _one_error_line(capsys)
    unfinished = tmp_path / "unfinished"
    shutil.copytree(run_dir, unfinished, ignore=shutil.ignore_patterns("bag"))
    summary = json.loads((unfinished / "summary.json").read_text())
    (unfinished / "summary.json").write_text(json.dumps({**summary, "complete": False,
                                                         "reason": "interrupted"}))
    assert swarm_main(["export", str(unfinished)]) == 2
    assert "unfinished run" in _one_error_line(capsys)
    (unfinished / "summary.json").unlink()
    assert swarm_main(["export", str(unfinished)]) == 2
    assert "unfinished run" in _one_error_line(capsys)
    # --force replaces a bag, never another folder
    assert swarm_main(["export", str(run_dir), "--out", str(foreign), "--force"]) == 2
    assert "holds other files" in _one_error_line(capsys)
    assert (foreign / "notes.txt").exists()
    assert swarm_main(["export", str(run_dir), "--out", str(run_dir), "--force"]) == 2
    assert "is not one" in _one_error_line(capsys)
    before = (bag / "metadata.yaml").stat().st_mtime_ns
    assert swarm_main(["export", str(run_dir), "--force"]) == 0
    assert capsys.readouterr().out.strip() == f"bag: {bag}"
    assert (bag / "metadata.yaml").stat().st_mtime_ns != before
    assert sorted(p.name for p in bag.iterdir()) == ["bag.mcap", "metadata.yaml"]
    # no temporary file left (the folder's lock file is the run's own)
    assert not [p for p in run_dir.iterdir() if p.name.startswith(".") and p.name != LOCK_FILE]


_WITHOUT_ROS = """
import sys
for name in ("rosbags", "mcap", "mcap_ros2"):
    sys.modules[name] = None  # as if the [ros] extra were not installed
from swarm.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("argv", [["export", "RUN"],
                                  ["run", "--ros2", "--ticks", "4", "--out", "OUT"]])
def test_without_the_ros_extra_one_line_says_what_to_install(run_dir, tmp_path, argv):
    argv = [str(run_dir) if a == "RUN" else str(tmp_path / "out") if a == "OUT" else a
            for a in argv]
    proc = subprocess.run([sys.executable, "-c", _WITHOUT_ROS, *argv], cwd=ROOT, text=True,
                          capture_output=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1
    assert missing_extra_message("ros") in proc.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(shutil.which("ros2") is None, reason="no ROS 2 installation (ros2 not on "
                    "PATH)")
def test_ros2_bag_info_reads_the_export(bag):
    proc = subprocess.run(["ros2", "bag", "info", str(bag)], text=True, capture_output=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "/swarm/agent_1/pose" in proc.stdout and "geometry_msgs/msg/PoseStamped" in proc.stdout
