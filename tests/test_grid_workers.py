"""A grid's local worker processes dying (killed from outside, or by the run itself): the runs
that were queued still run, the one under way runs again, and only a run whose worker dies
again is reported failed. The kill moment is drawn from a printed seed (``FAULT_SEED``)."""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from swarm.grid import Axis, estimator_axis, expand, run_grid
from swarm.local import run_local
from tests.waiting import children, identified, running, signalled, wait_for

ROOT = Path(__file__).resolve().parents[1]

SEED = int(os.environ.get("FAULT_SEED", str(int(time.time()) % 100_000)))
KILLS = "tests.example_estimator:KillsItsProcess"


def _workers(parent: int | None = None) -> list[int]:
    """The pool workers of ``parent`` (default this process): its spawned children running
    ``spawn_main`` (not the resource tracker, also a spawned child)."""
    found = []
    for pid in children(os.getpid() if parent is None else parent):
        try:
            if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes():
                found.append(pid)
        except OSError:
            continue
    return found


def _started(runs_dir: Path) -> list[Path]:
    return sorted(runs_dir.glob("*/*/config.toml"))


@pytest.fixture()
def scratch(tmp_path, monkeypatch) -> Path:
    """The temporary folder of this process and of the workers it spawns: the runs'
    credentials, even a killed worker's, must not remain there."""
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setenv("TMPDIR", str(folder))
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


@pytest.mark.slow  # fast tier: a run that kills its own worker is run again, then reported
@pytest.mark.timeout(300)
def test_a_worker_killed_mid_run_costs_nothing(tmp_path, scratch):
    print(f"FAULT_SEED={SEED} (rerun with this environment variable to replay)")
    delay = random.Random(SEED).uniform(0.0, 0.5)
    base = {"ticks": 300}
    runs = expand("killed", base, [estimator_axis(["persist", "kalman"]),
                                   Axis.of_field("seed", [0, 1], "s{}")])
    result: dict = {}
    grid = threading.Thread(target=lambda: result.update(
        outcomes=run_grid(runs, tmp_path, workers=2, progress=False)))
    grid.start()
    try:
        wait_for(lambda: _started(tmp_path) and _workers(), 60, "a run under way")
        time.sleep(delay)
        victims, killed_at = _workers(), time.time()
        assert victims, "no worker left to kill: the grid ended first"
        os.kill(victims[0], signal.SIGKILL)
        under_way = [path for path in _started(tmp_path)
                     if not (path.parent / "summary.json").exists()
                     or '"complete": true' not in (path.parent / "summary.json").read_text()]
    finally:
        grid.join(240)
    assert not grid.is_alive(), "the grid did not finish"
    # the killed worker's run was run again from its start
    assert any(path.stat().st_mtime > killed_at for path in under_way), under_way
    outcomes = result["outcomes"]
    assert [o.run for o in outcomes] == runs
    assert all(o.ok for o in outcomes), [o.error for o in outcomes if not o.ok]
    assert not list(scratch.iterdir())  # no password outlived its run
    for outcome in outcomes:  # the same numbers as an undisturbed run
        own = run_local(outcome.run.config)[0]
        assert outcome.summary["followers"] == own["followers"]


@pytest.mark.timeout(300)
def test_a_run_that_kills_its_worker_is_reported_and_the_others_finish(tmp_path, scratch):
    base = {"ticks": 8}
    runs = expand("dies", base, [estimator_axis(["persist", KILLS, "kalman"])])
    # one worker: each pool the grid starts costs a process start (a pool of two with a
    # worker killed from outside: the slow test above)
    outcomes = run_grid(runs, tmp_path, workers=1, progress=False)
    assert [o.run for o in outcomes] == runs
    persist, kills, kalman = outcomes
    assert persist.ok and kalman.ok
    assert not kills.ok
    assert kills.error == ("RuntimeError: its worker process died (killed, or out of memory), "
                           "twice")
    assert not list(scratch.iterdir())  # not even the killed runs' passwords


@pytest.mark.skipif(os.name != "posix", reason="signals")
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
@pytest.mark.timeout(300)
def test_a_stopped_grid_stops_its_workers(tmp_path, scratch, stop):
    """Ctrl-C or SIGTERM to a grid's own process alone (not its workers): the runs under way
    stop with it instead of running on in orphaned workers, within the grace period, and no
    run's credentials remain."""
    out = tmp_path / "cmp"
    proc = subprocess.Popen([sys.executable, "-m", "swarm", "compare", "--estimators",
                             "persist,kalman", "--seeds", "0,1", "--ticks", "5000", "--workers",
                             "2", "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: _started(out / "runs") and len(_workers(proc.pid)) == 2, 120,
                 "runs under way")
        workers = identified(_workers(proc.pid))
    finally:
        code, _, err = signalled(proc, stop, 30)
    assert code == 128 + stop, err
    assert "interrupted: finished runs are in" in err and "cleanup still running" not in err
    wait_for(lambda: not any(running(pid, started) for pid, started in workers.items()), 10,
             "the workers to end")
    assert not list(scratch.iterdir())
    assert not any((path.parent / "summary.json").exists()
                   and '"complete": true' in (path.parent / "summary.json").read_text()
                   for path in _started(out / "runs"))  # stopped, not finished: rerun them
