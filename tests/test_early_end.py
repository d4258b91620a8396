"""A run that ends early (design §7): it keeps the ticks before the earliest one at which an agent
met the end (the leader leaving a DEM, a follower's rod leaving it), the same ticks, rows and
numbers whatever the layout, the pipelining or the repeat."""
from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from protocol.config import RunConfig
from swarm.cli import main
from swarm.launch import launch
from swarm.local import LocalLink, run_local
from world.main import resolve_with_surface
from world.sim import RunEnded, WorldSim

HILLS = Path(__file__).parent / "data" / "hills.tif"  # 50 m x 40 m
RESULTS = ("ticks.csv", "observations.csv")
CASES = {
    # the leader drives east off the DEM (x 6 -> 57 m over 40 ticks)
    "leader-leaves": dict(leader_start=(6.0, 8.0, 1.0, 0.0)),
    # heading south-east with rods on the right: follower 2's rod end leaves the south edge
    # long before the leader leaves (an agent behind meets the end after the leader went on)
    "rod-leaves": dict(leader_start=(6.0, 10.0, 1.0, -0.15), side="right"),
}


def _config(case: str, pipelined: bool = True) -> RunConfig:
    return RunConfig(run_id=f"end-{case}", surface=f"dem:{HILLS}", followers=2, ticks=40,
                     estimator="auto", noise_range=0.02, noise_bearing=0.01, noise_move=0.01,
                     seed=4, agent_timeout=20.0, pipelined=pipelined, **CASES[case])


def _record(out: Path) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    return {"files": {name: (out / name).read_bytes() for name in RESULTS},
            "ticks": summary["ticks_completed"], "complete": summary["complete"],
            "reason": summary["reason"], "followers": summary["followers"]}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The unpipelined order in memory, per case."""
    refs = {}
    for case in CASES:
        out = tmp_path_factory.mktemp(case)
        summary, _ = run_local(_config(case, pipelined=False), out)
        assert not summary["complete"] and 5 < summary["ticks_completed"] < 40
        refs[case] = _record(out)
    return refs


@pytest.mark.parametrize("case", list(CASES))
def test_the_end_is_where_it_is_met_first(reference, case):
    ticks, reason = reference[case]["ticks"], reference[case]["reason"]
    if case == "leader-leaves":
        assert "the leader left the surface's domain" in reason
        assert ticks == 34  # x = 6 + 1.28 j leaves [0, 50] between ticks 34 and 35
    else:
        assert "agent 1's rod leaves" in reason or "agent 2 would leave" in reason, reason


class NotesTheEnd(LocalLink):
    """A follower's link that notes the message of every RunEnded its requests met."""

    told: list[str] = []

    def sense(self, tick, look=False):
        try:
            return super().sense(tick, look)
        except RunEnded as exc:
            self.told.append(str(exc))
            raise

    def act(self, request):
        try:
            return super().act(request)
        except RunEnded as exc:
            self.told.append(str(exc))
            raise


def test_agents_are_told_why_the_run_ends_not_where(tmp_path):
    """Absolute coordinates are the world's: its summary says where the swarm met the end of
    the domain, the agents are told only why (the same text goes into ``world/done``): a
    follower whose rod end or move leaves the domain, and the leader leaving it."""
    decimal = re.compile(r"\d\.\d")
    NotesTheEnd.told = []
    summary, _ = run_local(_config("rod-leaves", pipelined=False), tmp_path,
                           link_factory=NotesTheEnd)
    told = NotesTheEnd.told
    assert told and not summary["complete"]
    assert decimal.search(summary["reason"]), summary["reason"]
    assert not any(decimal.search(text) for text in told), told
    assert all(summary["reason"].startswith(text + ": ") for text in told)
    config, surface = resolve_with_surface(_config("leader-leaves"))
    sim = WorldSim(config, surface)
    with pytest.raises(RunEnded) as ended:
        for tick in range(config.ticks):
            sim.open_tick(tick)
            sim.drive(0, tick, sim.time_of(tick))
    assert str(ended.value) == sim.end_reason == "the leader left the surface's domain"
    assert decimal.search(sim.end_detail) and sim.end_detail.startswith(sim.end_reason + ": ")


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("repeat", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_in_memory_wavefront_ends_alike(tmp_path, reference, case, repeat):
    run_local(_config(case), tmp_path)
    assert _record(tmp_path) == reference[case]


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("layout", ["in-process", "processes", pytest.param(
    "in-process-unpipelined", marks=pytest.mark.slow)])
@pytest.mark.parametrize("repeat", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_zenoh_layouts_end_alike(tmp_path, reference, case, layout, repeat):
    config = _config(case, pipelined=not layout.endswith("unpipelined"))
    summary = launch(config, tmp_path / "run", in_process=layout.startswith("in-process"))
    assert not summary["complete"]
    assert _record(tmp_path / "run") == reference[case]


def test_the_readme_dem_example_completes(tmp_path, capsys):
    """The README's DEM command (30 ticks: the leader stays on the 50 m raster)."""
    status = main(["run", "--surface", f"dem:{HILLS}", "--leader-start", "6,8,1,0",
                   "--ticks", "30", "--in-process", "--out", str(tmp_path / "dem")])
    assert status == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "dem" / "summary.json").read_text())
    assert summary["complete"] and summary["ticks_completed"] == 30



def test_a_tick_whose_ideal_place_is_off_the_surface_is_broken(tmp_path):
    """Noisy enough that the ideal column's rod leaves the DEM a tick before the actual one:
    at that tick the world has no formation error to give (the cell is empty), and the tick
    counts as broken, never as kept formation (design §7); the mean and the worst are those of
    the measured ticks."""
    config = dataclasses.replace(_config("rod-leaves", pipelined=False), seed=1,
                                 noise_range=0.1, noise_bearing=0.05, noise_move=0.05)
    summary, rows = run_local(config, tmp_path)
    unmeasured = [r for r in rows if r["agent"] > 0 and r["formation_error"] is None]
    assert unmeasured, "the case no longer has a tick whose ideal place is off the DEM"
    assert summary["formation_broken"]
    for k in (1, 2):
        mine = [r["formation_error"] for r in rows if r["agent"] == k]
        measured = [e for e in mine if e is not None]
        health = summary["followers"][str(k)]
        assert health["broken_ticks"] == sum(e is None or e > config.formation_tolerance
                                             for e in mine)
        assert health["worst_formation_error"] == max(measured)
        assert health["mean_formation_error"] == pytest.approx(sum(measured) / len(measured))
