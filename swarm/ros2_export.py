"""``python -m swarm export RUN_DIR [--out BAG_DIR] [--force]``: a finished run as a rosbag2
bag in MCAP storage (design §10), written with ``rosbags`` (types, CDR, RIHS01 hashes and the
embedded message definitions all from its Jazzy type store).

The bag holds the topics of :func:`protocol.ros2.run_topics`, one message per agent per tick
on each per-agent topic (``estimate`` and ``required_range`` on estimated ticks only), each
recorded and stamped at the tick's simulation time; the first ``/swarm/markers`` message is
the terrain (at most :data:`world.ros2.EXPORT_TERRAIN_CELLS` nodes over the box the run
covers), recorded again every :data:`world.ros2.TERRAIN_EVERY_S` of simulation time as the
live publisher sends it again, so a player that starts late or seeks still shows it. A drive
run's bag also holds each follower's control steps on ``cmd_vel``, one twist per step,
recorded at the step's time (``controls.csv``'s ``t``). Messages come from
:class:`world.ros2.RosScene`, the builder the live publisher uses, fed with ``ticks.csv`` and
``controls.csv`` read back (floats round-trip exactly; each follower's formation health on
``/diagnostics`` counted again from ``ticks.csv`` by :class:`protocol.health.ColumnHealth`,
as the world's recorder counted it). The bag is written in a scratch
folder beside ``BAG_DIR`` and renamed into place when complete.

The container is what rosbag2 Jazzy's MCAP storage plugin writes: each channel's metadata
holds ``offered_qos_profiles`` (the world's publishers': reliable, volatile, keep last 10) and
``topic_type_hash`` (the RIHS01 hash), and ``metadata.yaml`` and the file's ``rosbag2``
metadata record say ``ros_distro: jazzy``. rosbags' :class:`~rosbags.rosbag2.Writer` keeps
the bag (connections, definitions, hashes, ``metadata.yaml``) through its storage-writer
interface, here over the ``mcap`` library's writer (:func:`_writer_class`).
"""
from __future__ import annotations

import itertools
import json
import os
import re
import shutil
from functools import cache
from pathlib import Path

import numpy as np

from protocol import ros2
from protocol.config import load_config
from protocol.distribution import version
from protocol.health import ColumnHealth
from protocol.record import CONTROLS_FILE, SUMMARY_FILE, TICKS_FILE, read_controls, read_ticks

BAG_VERSION = 9  # rosbag2's metadata version of Jazzy
BAG_FILES = {"metadata.yaml"}
ROS_DISTRO = "jazzy"
_ROSBAGS_DISTRO = re.compile(r"^(\s*ros_distro: )rosbags$", re.MULTILINE)


@cache
def _writer_class():
    """rosbags' bag writer with its MCAP storage written by the ``mcap`` library as rosbag2
    Jazzy writes it (see the module docstring); imported on first use (the ``[ros]``
    extra)."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapFileWriter
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.rosbag2 import StoragePlugin, Writer

    def jazzy(text: str) -> str:
        """rosbags' metadata YAML saying ``ros_distro: jazzy`` (one line of it changed: YAML
        parsed and dumped again costs a second for a bag of many topics)."""
        text, found = _ROSBAGS_DISTRO.subn(rf"\g<1>{ROS_DISTRO}", text)
        if found != 1:
            raise RuntimeError("rosbags wrote no single 'ros_distro: rosbags' line; this "
                               "rosbags version is not one this export knows")
        return text

    class McapStorage:
        """rosbags' storage-writer interface (``add_msgtype``, ``add_connection``, ``write``,
        ``close``, ``abort``) over ``mcap.writer.Writer``, its chunks zstd-compressed (what
        rosbag2's ``zstd_fast`` preset writes): the terrain recorded every 5 s makes an
        uncompressed bag five times larger (docs/ros2.md, Benchmarks)."""

        def __init__(self, path: Path, compression) -> None:
            self.path = path / f"{path.name}.mcap"
            self._file = self.path.open("xb")
            self._writer = McapFileWriter(self._file, compression=CompressionType.ZSTD)
            self._writer.start(profile="ros2", library=f"koopman-swarm {version()}")
            self._schemas: dict[str, int] = {}
            self._channels: dict[int, int] = {}

        def add_msgtype(self, connection) -> None:
            encoding = ("ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG
                        else "ros2idl")
            self._schemas[connection.msgtype] = self._writer.register_schema(
                connection.msgtype, encoding, connection.msgdef.data.encode())

        def add_connection(self, connection, offered_qos_profiles: str) -> None:
            self._channels[connection.id] = self._writer.register_channel(
                connection.topic, connection.ext.serialization_format,
                self._schemas[connection.msgtype],
                {"offered_qos_profiles": offered_qos_profiles,
                 "topic_type_hash": connection.digest})

        def write(self, connection, timestamp: int, data) -> None:
            self._writer.add_message(self._channels[connection.id], timestamp, bytes(data),
                                     timestamp)

        def close(self, version_: int, metadata: str) -> None:
            self._writer.add_metadata("rosbag2", {"serialized_metadata": jazzy(metadata)})
            self._writer.finish()
            self._file.close()

        def abort(self) -> None:
            self._file.close()

    class JazzyWriter(Writer):
        STORAGE_PLUGINS = {StoragePlugin.MCAP: McapStorage}

        def close(self) -> None:
            super().close()
            path = self.metapath
            path.write_text(jazzy(path.read_text(encoding="utf-8")), encoding="utf-8")

    return JazzyWriter


def offered_qos():
    """The world's publishers' QoS (:data:`protocol.ros2.PUBLISHER_QOS`) as rosbags' Qos: what
    rosbag2 records as a topic's offered profile (an infinite duration as rmw's)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    q = ros2.PUBLISHER_QOS

    def duration(value):
        return QosTime(*(value or ros2.DURATION_INFINITE))

    return Qos(history=QosHistory(q.history), depth=q.depth,
               reliability=QosReliability(q.reliability), durability=QosDurability(q.durability),
               deadline=duration(q.deadline), lifespan=duration(q.lifespan),
               liveliness=QosLiveliness(q.liveliness),
               liveliness_lease_duration=duration(q.lease),
               avoid_ros_namespace_conventions=False)


def check_run_dir(run_dir: Path) -> None:
    """Refuse (ValueError, one line) a folder that is no finished run of this tool."""
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir} is not a folder")
    if not (run_dir / "config.toml").is_file() or not (run_dir / TICKS_FILE).is_file():
        raise ValueError(f"{run_dir} is not a run folder (no config.toml or ticks.csv)")
    try:
        summary = json.loads((run_dir / SUMMARY_FILE).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{run_dir} is an unfinished run (no summary.json); only a complete "
                         "run is exported") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{run_dir / SUMMARY_FILE} is unreadable ({exc})") from None
    if not isinstance(summary, dict) or summary.get("complete") is not True:
        reason = summary.get("reason", "") if isinstance(summary, dict) else ""
        raise ValueError(f"{run_dir} is an unfinished run (summary.json: complete is not true"
                         + (f"; {reason}" if reason else "") + "); only a complete run is "
                         "exported")


def _check_out(out: Path, run_dir: Path, force: bool) -> None:
    """Refuse an existing ``out`` unless ``force`` and it is a bag (never a run folder)."""
    if not out.exists() and not out.is_symlink():
        return
    if not force:
        raise ValueError(f"{out} already exists; choose another --out or pass --force to "
                         "replace it")
    if out.is_symlink() or not out.is_dir() or out.resolve() == run_dir.resolve():
        raise ValueError(f"--force replaces only a bag folder; {out} is not one")
    names = {p.name for p in out.iterdir()}
    if not names <= BAG_FILES | {n for n in names if n.endswith(".mcap")}:
        raise ValueError(f"--force replaces only a bag folder (metadata.yaml and .mcap files); "
                         f"{out} holds other files")


def _tick_rows(rows: list[dict], n_agents: int) -> list[list[dict]]:
    """``ticks.csv``'s rows grouped by tick (each complete, agents in order)."""
    ticks = [list(group) for _, group in itertools.groupby(rows, key=lambda r: r["tick"])]
    for j, tick in enumerate(ticks):
        if tick[0]["tick"] != j or [r["agent"] for r in tick] != list(range(n_agents)):
            raise ValueError(f"ticks.csv: tick {tick[0]['tick']} does not hold one row per agent "
                             "in order")
        if any(r.get("heading_x") is None for r in tick):
            raise ValueError("ticks.csv has no headings (heading_x, heading_y): the run was "
                             "made by an older version; run it again to export it")
    return ticks


def _tick_controls(run_dir: Path, n_ticks: int) -> list[list[dict]]:
    """``controls.csv``'s rows grouped by tick, one (possibly empty) list per tick of
    ``ticks.csv``."""
    path = run_dir / CONTROLS_FILE
    if not path.is_file():
        raise ValueError(f"{run_dir} is a drive run without {CONTROLS_FILE}: the run was made "
                         "by an older version; run it again to export it")
    by_tick: list[list[dict]] = [[] for _ in range(n_ticks)]
    for row in read_controls(path):
        if row["tick"] >= n_ticks:
            raise ValueError(f"{path}: tick {row['tick']} is not in {TICKS_FILE}")
        by_tick[row["tick"]].append(row)
    return by_tick


def export_run(run_dir: str | Path, out: str | Path | None = None, *,
               force: bool = False) -> Path:
    """Write the bag of the finished run in ``run_dir`` to ``out`` (default ``run_dir/bag``).

    Raises ValueError (one line) for a folder that is no finished run or an existing ``out``
    without ``force``; :class:`protocol.distribution.MissingExtra` (an ImportError) without
    the ``[ros]`` extra.
    """
    from world.main import resolve_with_surface
    from world.ros2 import EXPORT_TERRAIN_CELLS, TERRAIN_EVERY_S, Period, RosScene, stamp_ns

    store = ros2.typestore()  # MissingExtra before anything else
    from rosbags.rosbag2 import StoragePlugin

    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "bag"
    check_run_dir(run_dir)
    _check_out(out, run_dir, force)

    config, surface = resolve_with_surface(load_config(run_dir / "config.toml"))
    ticks = _tick_rows(read_ticks(run_dir / TICKS_FILE), config.followers + 1)
    if not ticks:
        raise ValueError(f"{run_dir / TICKS_FILE} holds no tick")
    drive = config.drives
    controls = _tick_controls(run_dir, len(ticks)) if drive else [[] for _ in ticks]
    scene = RosScene(config, surface)
    health = ColumnHealth(config.followers, config.formation_tolerance)  # as the world counts
    points = np.array([[r[a], r[b]] for tick in ticks for r in tick
                       for a, b in (("pos_x", "pos_y"), ("ideal_x", "ideal_y"))
                       if r.get(a) is not None])
    out.parent.mkdir(parents=True, exist_ok=True)
    scratch = out.with_name(f".{out.name}.partial-{os.getpid()}")
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    partial = scratch / out.name  # rosbags names the .mcap file after its folder
    try:
        with _writer_class()(partial, version=BAG_VERSION,
                             storage_plugin=StoragePlugin.MCAP) as writer:
            connections = {
                topic: writer.add_connection(topic, msgtype, typestore=store,
                                             offered_qos_profiles=[offered_qos()])
                for topic, msgtype in ros2.run_topics(config.followers, drive)}
            first = ticks[0][0]["t"]
            markers = ros2.MARKERS
            terrain = store.serialize_cdr(scene.terrain(points, EXPORT_TERRAIN_CELLS, first),
                                          markers[1])
            terrain_due = Period(TERRAIN_EVERY_S)
            for tick, steps in zip(ticks, controls, strict=True):
                stamp = stamp_ns(tick[0]["t"])
                if terrain_due(tick[0]["t"]):  # the same message, as live
                    writer.write(connections[markers[0]], stamp, terrain)
                for topic, msgtype, message in scene.tick_messages(health.add_tick(tick)):
                    writer.write(connections[topic], stamp, store.serialize_cdr(message, msgtype))
                # the tick's control steps, in time order (they fill its comm interval)
                for topic, msgtype, message, t in sorted(scene.control_messages(steps),
                                                         key=lambda m: m[3]):
                    writer.write(connections[topic], stamp_ns(t),
                                 store.serialize_cdr(message, msgtype))
        if out.exists():
            shutil.rmtree(out)
        os.replace(partial, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return out
