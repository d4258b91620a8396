"""A stall is not a death (design §4): a follower paused with SIGSTOP for longer than Zenoh's
lease, then continued, joins again and the run goes on: in lockstep with the numbers of an
undisturbed run, in realtime without its successor missing a tick because of it. A paused world
(the router too) is waited for by its agents, which join it again, with the same numbers. A
follower killed in realtime is recorded and the run goes on.

The pause's moment and length are drawn from a printed seed (``FAULT_SEED=...`` replays them).
Faults come from outside (signals); every process is ended by its own handle.
"""
from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from protocol.config import RunConfig, load_config
from protocol.record import read_ticks
from swarm.local import run_local
from tests.deployment import hand_started
from tests.waiting import children, ticks_done, wait_for
from world.results import run_failure

ROOT = Path(__file__).resolve().parents[1]
SEED = int(os.environ.get("FAULT_SEED", str(int(time.time()) % 100_000)))
LEASE_S = 10.0  # Zenoh's default lease: a pause longer than this cuts the session
REJOINED = "its session to the world was cut and is back"


def _pid(swarm: subprocess.Popen, agent: int | None) -> int:
    """The process of follower ``agent`` under ``swarm run``, or of its world (None: the
    ``swarm run`` process itself, which also runs the embedded router)."""
    if agent is None:
        return swarm.pid
    for pid in children(swarm.pid):
        try:
            args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"agents.follower" in args and args[args.index(b"--id") + 1] == str(agent).encode():
            return pid
    raise AssertionError(f"no process of follower {agent} under swarm run")


class SwarmRun:
    """``swarm run --processes`` in the background; killed at the end if still running."""

    def __init__(self, out: Path, *flags: str) -> None:
        self.out = out
        self.proc = subprocess.Popen([sys.executable, "-m", "swarm", "run", "--processes",
                                      "--followers", "2", *flags, "--out", str(out)], cwd=ROOT,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def finish(self, timeout: float) -> tuple[int, str]:
        _, err = self.proc.communicate(timeout=timeout)
        return self.proc.returncode, err

    def close(self) -> None:
        if self.proc.poll() is None:
            for pid in children(self.proc.pid):
                os.kill(pid, signal.SIGCONT)  # nobody stays stopped after a failed test
            self.proc.kill()
            self.proc.communicate(timeout=10)


@pytest.fixture
def runs():
    started: list[SwarmRun] = []
    yield lambda *args: started.append(SwarmRun(*args)) or started[-1]
    for run in started:
        run.close()


def _pause(run: SwarmRun, agent: int | None, after: int, seconds: float) -> None:
    """SIGSTOP follower ``agent`` (the world: None) once the run has recorded ``after`` ticks,
    SIGCONT it ``seconds`` later."""
    wait_for(lambda: ticks_done(run.out) >= after, 120, f"tick {after}")
    pid = _pid(run.proc, agent)
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)


def _draw(kind: str, who: str = "follower 1") -> tuple[int, float]:
    rng = random.Random(f"{SEED}-{kind}")
    after, seconds = rng.randrange(5, 40), rng.uniform(LEASE_S + 2.0, LEASE_S + 8.0)
    print(f"FAULT_SEED={SEED}: {who} paused after tick {after} for {seconds:.1f} s")
    return after, seconds


@pytest.mark.slow
def test_a_paused_follower_rejoins_and_lockstep_numbers_do_not_change(tmp_path, runs):
    after, seconds = _draw("lockstep")
    run = runs(tmp_path / "run", "--ticks", "2000", "--agent-timeout", "40",
               "--noise-range", "0.01", "--seed", "7")
    _pause(run, 1, after, seconds)
    code, err = run.finish(timeout=600)
    assert code == 0, err
    assert REJOINED in (run.out / "logs" / "agent-1.log").read_text()  # the stall cut it
    reference = tmp_path / "reference"
    run_local(load_config(run.out / "config.toml"), reference)
    for name in ("ticks.csv", "observations.csv"):
        assert (run.out / name).read_bytes() == (reference / name).read_bytes(), name


@pytest.mark.slow
@pytest.mark.timeout(700)  # the run (up to 600 s) and its reference; under load 50-130 s
def test_a_paused_world_is_waited_for_and_lockstep_numbers_do_not_change(tmp_path, runs):
    """The world (the run's router too) paused beyond the lease: every agent's session is cut,
    the agents wait for the world (their start timeout) instead of concluding it died, and join
    it again once it runs."""
    after, seconds = _draw("world", "the world")
    run = runs(tmp_path / "run", "--ticks", "2000", "--agent-timeout", "40",
               "--noise-range", "0.01", "--seed", "7")
    _pause(run, None, after, seconds)
    code, err = run.finish(timeout=600)
    assert code == 0, err
    for agent in (0, 1, 2):
        assert REJOINED in (run.out / "logs" / f"agent-{agent}.log").read_text(), agent
    reference = tmp_path / "reference"
    run_local(load_config(run.out / "config.toml"), reference)
    for name in ("ticks.csv", "observations.csv"):
        assert (run.out / name).read_bytes() == (reference / name).read_bytes(), name


def _missed(out: Path) -> dict[int, set[int]]:
    rows = read_ticks(out / "ticks.csv")
    return {k: {r["tick"] for r in rows if r["agent"] == k and r["missed"]} for k in (1, 2)}


@pytest.mark.slow
def test_a_paused_follower_never_makes_its_successor_miss_in_realtime(tmp_path, runs):
    after, seconds = _draw("realtime")
    ticks = after + int(seconds / 0.256) + 30
    run = runs(tmp_path / "run", "--mode", "realtime", "--time-scale", "0.2", "--ticks",
               str(ticks))
    _pause(run, 1, after, seconds)
    code, err = run.finish(timeout=600)
    _assert_formation_broke(run.out, code, err)  # it stood still while the column moved on
    assert REJOINED in (run.out / "logs" / "agent-1.log").read_text()
    missed = _missed(run.out)
    assert len(missed[1]) >= int(LEASE_S / 0.256)  # it did miss while it was paused
    assert not missed[1] & missed[2], f"follower 2 missed {sorted(missed[1] & missed[2])}"
    assert max(missed[1]) < ticks - 5  # and it was back, settling, before the end


@pytest.mark.slow  # 60 realtime ticks; fast tier: test_attacks' dead follower (realtime)
def test_a_killed_follower_is_recorded_and_a_realtime_run_goes_on(tmp_path, runs):
    kill_after = random.Random(f"{SEED}-kill").randrange(5, 20)
    print(f"FAULT_SEED={SEED}: follower 1 killed after tick {kill_after}")
    run = runs(tmp_path / "run", "--mode", "realtime", "--time-scale", "0.2", "--ticks", "60")
    wait_for(lambda: ticks_done(run.out) >= kill_after, 120, f"tick {kill_after}")
    os.kill(_pid(run.proc, 1), signal.SIGKILL)
    code, err = run.finish(timeout=300)
    _assert_formation_broke(run.out, code, err)  # the run went on, and says the column broke
    assert "agent 1 exited with status -9" in err and "the run goes on without it" in err
    summary = json.loads((run.out / "summary.json").read_text())
    assert summary["complete"] and summary["ticks_completed"] == 60
    missed = _missed(run.out)
    assert set(range(kill_after + 3, 60)) <= missed[1]  # recorded from its death on
    assert not missed[1] & missed[2], f"follower 2 missed {sorted(missed[1] & missed[2])}"


def _assert_formation_broke(out: Path, code: int, err: str) -> dict:
    """The run in ``out`` completed, its stalled follower 1 missed ticks standing out of
    formation, and the launcher exited 1 with :func:`world.results.run_failure`'s line last."""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["formation_broken"], summary
    stalled = summary["followers"]["1"]
    assert stalled["missed_ticks"] > 0 and stalled["broken_ticks"] > 0, stalled
    line = run_failure(summary)
    assert line.startswith("the formation broke:") and "follower-ticks missed" in line, line
    assert code == 1, err
    assert err.strip().splitlines()[-1] == f"error: {line}", err
    return summary


@pytest.mark.parametrize("launcher", ["swarm run", "python -m world"])
def test_a_stalled_follower_is_no_success_in_realtime(tmp_path, runs, launcher):
    """Design §7: follower 1 stopped (SIGSTOP, shorter than Zenoh's lease) misses ticks while
    the column moves on; its formation error is measured where it stands, so the run is
    complete but its formation broke: ``swarm run`` and a hand-started world give the same
    verdict, last line and status 1."""
    rng = random.Random(f"{SEED}-stalled-{launcher}")
    after, seconds = rng.randrange(3, 10), rng.uniform(2.0, 4.0)
    print(f"FAULT_SEED={SEED}: follower 1 stopped after tick {after} for {seconds:.1f} s")
    flags = dict(followers=2, ticks=50, mode="realtime", time_scale=0.1, agent_timeout=2.0,
                 start_timeout=30.0)
    if launcher == "swarm run":
        run = runs(tmp_path / "run", *[f"--{k.replace('_', '-')}={v}" for k, v in flags.items()
                                       if k != "followers"])
        out, proc, pid = run.out, run.proc, lambda: _pid(run.proc, 1)
    else:
        procs = hand_started(tmp_path, RunConfig(run_id="stalled", **flags))
        out, proc, pid = tmp_path / "out", procs[0], lambda: procs[2].pid  # world, leader, 1
    try:
        wait_for(lambda: ticks_done(out) >= after, 60, f"tick {after}")
        os.kill(pid(), signal.SIGSTOP)
        try:
            time.sleep(seconds)
        finally:
            os.kill(pid(), signal.SIGCONT)
        _, err = proc.communicate(timeout=120)
    finally:
        if launcher == "python -m world":
            for p in procs:
                if p.poll() is None:
                    p.kill()
                p.communicate(timeout=10)
    summary = _assert_formation_broke(out, proc.returncode, err)
    assert summary["followers"]["1"]["missed_ticks"] >= int(seconds / 0.128) - 3
