"""Pipelined lockstep (design §4): the column advances as a wavefront, and the numbers are
byte-identical to the unpipelined order, with noise, for 1, 3 and 10 followers, in memory,
in-process over Zenoh and as processes; for driving followers (``--motion drive``) too."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from protocol.config import RunConfig
from swarm.launch import launch
from swarm.local import run_local

RESULTS = ("ticks.csv", "observations.csv")
DRIVE_RESULTS = (*RESULTS, "controls.csv")


def _config(followers: int, pipelined: bool) -> RunConfig:
    return RunConfig(run_id=f"pipe{followers}", surface="wavy", followers=followers, ticks=16,
                     estimator="auto", noise_range=0.01,
                     noise_bearing=0.005, noise_velocity=0.02, noise_move=0.01, seed=5,
                     agent_timeout=30.0, pipelined=pipelined)


def _drive_config(pipelined: bool) -> RunConfig:
    """Three driving followers with every drive noise (no teleport actuation noise)."""
    return dataclasses.replace(_config(3, pipelined), run_id="pipedrive", motion="drive",
                               noise_move=0.0, noise_speed=0.02, noise_turn=0.02,
                               control_steps=6, snap_steps=3)


def _same(out: Path, reference: Path, names: tuple[str, ...] = RESULTS) -> None:
    for name in names:
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name


@pytest.fixture(scope="module")
def unpipelined(tmp_path_factory):
    """The unpipelined order, in memory (tests/test_end_to_end.py shows that it equals the
    Zenoh layouts), per number of followers: each made on first use (10 followers is for the
    slow tier only)."""
    refs: dict[int, Path] = {}

    def reference(n: int) -> Path:
        if n not in refs:
            refs[n] = tmp_path_factory.mktemp(f"ref{n}")
            run_local(_config(n, pipelined=False), refs[n])
        return refs[n]

    return reference


@pytest.mark.parametrize("followers", [1, 3, pytest.param(10, marks=pytest.mark.slow)])
def test_in_memory_wavefront_matches(tmp_path, unpipelined, followers):
    run_local(_config(followers, pipelined=True), tmp_path)
    _same(tmp_path, unpipelined(followers))


@pytest.mark.parametrize("in_process", [True, False], ids=["in-process", "processes"])
@pytest.mark.parametrize("followers", [1, 3, pytest.param(10, marks=pytest.mark.slow)])
def test_pipelined_run_matches_unpipelined(tmp_path, unpipelined, followers, in_process):
    summary = launch(_config(followers, pipelined=True), tmp_path / "run", in_process=in_process)
    assert summary["complete"], summary["reason"]
    _same(tmp_path / "run", unpipelined(followers))


@pytest.fixture(scope="module")
def drive_unpipelined(tmp_path_factory):
    ref = tmp_path_factory.mktemp("drive-ref")
    run_local(_drive_config(pipelined=False), ref)
    return ref


@pytest.mark.parametrize("layout", ["in-memory", "in-process", "processes"])
def test_drive_column_matches_in_every_layout(tmp_path, drive_unpipelined, layout):
    """Control steps, odometry and the driven poses: the same bytes pipelined or not, in
    memory, in-process over Zenoh and as processes."""
    config = _drive_config(pipelined=True)
    if layout == "in-memory":
        run_local(config, tmp_path)
        _same(tmp_path, drive_unpipelined, DRIVE_RESULTS)
        return
    summary = launch(config, tmp_path / "run", in_process=layout == "in-process")
    assert summary["complete"], summary["reason"]
    _same(tmp_path / "run", drive_unpipelined, DRIVE_RESULTS)


def test_unpipelined_over_zenoh_matches(tmp_path, unpipelined):
    """The comparison option: ``pipelined = false`` still gives the same numbers."""
    summary = launch(_config(3, pipelined=False), tmp_path / "run", in_process=True)
    assert summary["complete"], summary["reason"]
    _same(tmp_path / "run", unpipelined(3))


def test_the_column_really_overlaps_ticks(tmp_path, monkeypatch):
    """In a pipelined run the leader gets ahead of the last follower: when tick 0 completes
    (the last follower is through it) the world has already opened later ticks."""
    from world.service import WorldService

    opened_at_first_complete = []
    original = WorldService._complete_tick

    def spy(self, tick):
        if tick == 0:
            opened_at_first_complete.append(self.sim.tick)
        return original(self, tick)

    monkeypatch.setattr(WorldService, "_complete_tick", spy)
    config = dataclasses.replace(_config(10, pipelined=True), ticks=30)
    assert launch(config, tmp_path / "run", in_process=True)["complete"]
    assert opened_at_first_complete and opened_at_first_complete[0] > 0


def test_the_wavefront_is_no_deeper_than_the_column(tmp_path, monkeypatch):
    """The leader, faster than its column, gets no further ahead of the last complete tick
    than one tick per agent: without the bound (world.schedule.may_open) it ran ahead without
    end, and the world kept and iterated over every tick it was ahead by. Measured at every
    tick's completion, in-process over Zenoh and as processes alike (one service)."""
    from world.service import WorldService

    depths = []
    original = WorldService._complete_tick

    def spy(self, tick):
        depths.append(self.sim.tick - tick)
        return original(self, tick)

    monkeypatch.setattr(WorldService, "_complete_tick", spy)
    config = dataclasses.replace(_config(3, pipelined=True), ticks=60, estimator="persist")
    assert launch(config, tmp_path / "run", in_process=True)["complete"]
    assert len(depths) == 60
    assert max(depths) <= 3  # the leader opens at most 4 agents - 1 ticks beyond a completion
    assert max(depths) > 0  # still a wavefront
