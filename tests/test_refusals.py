"""A refused command (design §9: status 2) says why in one line and leaves nothing: every
check of the command line, the configuration, the surface, the raster, the start and a plug-in
comes before a results folder is made."""
from __future__ import annotations

from pathlib import Path

import pytest

import world.main
from protocol.config import RunConfig, dump_config
from swarm.cli import main

ROOT = Path(__file__).resolve().parents[1]
HILLS = ROOT / "tests" / "data" / "hills.tif"
README = ROOT / "README.md"


def _refused_in_one_line(capsys, command, *args: str) -> str:
    """Run ``command(args)`` (status returned, or raised by argparse); it must be 2 with one
    line on stderr, which is returned."""
    try:
        status = command(list(args))
    except SystemExit as exc:
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2, err
    assert len(err.splitlines()) == 1, err
    return err


@pytest.mark.parametrize("args, fragment", [
    (["--surface", "ellipic"], "name 'ellipic' is not a preset"),
    (["--surface", "dem:missing.tif"], "no such DEM file"),
    (["--surface", f"dem:{README}"], "is not a raster rasterio can read"),
    (["--surface", f"dem:{HILLS}"], "has no default leader start: give leader_start"),
    (["--surface", f"dem:{HILLS}", "--leader-start", "1e6,0,1,0"], "lies outside the DEM grid"),
    (["--surface", f"dem:{HILLS}", "--leader-start", "49.9,8,0,1", "--followers", "3",
      "--spacing", "20"], "rod leaves the surface's domain"),
    (["--estimator", "nosuch.module:Mine"], "no module 'nosuch.module' is importable here"),
    (["--seed", "abc"], "argument --seed: invalid int value: 'abc'"),
], ids=["surface-typo", "dem-missing", "dem-not-a-raster", "dem-no-start", "start-off-grid",
        "column-off-grid", "plugin-missing", "seed-not-a-number"])
@pytest.mark.parametrize("layout", ["--processes", "--in-process"])
def test_a_refused_run_leaves_nothing(tmp_path, monkeypatch, capsys, args, fragment, layout):
    monkeypatch.chdir(tmp_path)  # the default results folder is runs/<id> here
    err = _refused_in_one_line(capsys, main, "run", layout, "--ticks", "6", *args)
    assert fragment in err
    assert not err.startswith("usage")
    assert list(tmp_path.iterdir()) == []


def test_a_refused_run_into_a_given_folder_leaves_nothing(tmp_path, capsys):
    out = tmp_path / "deep" / "er" / "run"
    err = _refused_in_one_line(capsys, main, "run", "--surface", "ellipic", "--out", str(out))
    assert "not a preset" in err
    assert list(tmp_path.iterdir()) == []


def test_a_hand_started_world_refuses_a_start_off_its_dem_before_making_a_folder(tmp_path,
                                                                                 capsys):
    dump_config(RunConfig(run_id="off", surface=f"dem:{HILLS}",
                          leader_start=(80.0, 8.0, 1.0, 0.0)), tmp_path / "run.toml")
    err = _refused_in_one_line(capsys, world.main.main, "--config", str(tmp_path / "run.toml"),
                               "--out", str(tmp_path / "out"))
    assert "lies outside the DEM grid" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


@pytest.mark.parametrize("args, fragment", [
    (["--dem", "missing.tif", "--leader-start", "0,0,1,0"], "no such DEM file"),
    (["--dem", str(HILLS), "--leader-start", "90,8,1,0"], "lies outside the DEM grid"),
], ids=["dem-missing", "start-off-grid"])
def test_a_refused_terrain_experiment_leaves_no_folder(tmp_path, monkeypatch, capsys, args,
                                                       fragment):
    monkeypatch.chdir(tmp_path)  # its default folder is runs/experiment-terrain here
    err = _refused_in_one_line(capsys, main, "experiment", "terrain", "--quick", *args)
    assert fragment in err
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_before_the_first_tick_says_so_and_keeps_nothing(tmp_path):
    """The follower's plug-in takes its time at import (it is only found, never run, by
    `swarm run`), so tick 0 cannot complete; Ctrl-C once the run's folder is made: status 130,
    one line saying nothing was kept, no folder, no warning about vanished agents, and no
    agent left running."""
    import signal
    import subprocess
    import sys

    from tests.waiting import children, identified, running, signalled, wait_for

    (tmp_path / "slow_plugin.py").write_text("import time\ntime.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-m", "swarm", "run", "--followers", "2",
                             "--estimator", "slow_plugin:Never", "--out", "run"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        wait_for(lambda: len(children(proc.pid)) == 3, 60, "the three agent processes")
        agents = identified(children(proc.pid))
        assert (tmp_path / "run" / "config.toml").exists()
    finally:
        code, _, err = signalled(proc, signal.SIGINT, timeout=30)
    assert code == 130, err
    assert err.splitlines() == ["interrupted before the first tick: nothing kept (run removed)"]
    assert list(tmp_path.iterdir()) == [tmp_path / "slow_plugin.py"]
    assert not any(running(pid, started) for pid, started in agents.items())


def test_a_discarded_folder_takes_nothing_that_is_not_its_own(tmp_path):
    """A refused run removes the folder it made and the parents it made if they are empty;
    not a run folder made beside it meanwhile, nor one another writer holds."""
    from protocol.cli import NewFolder
    from protocol.folder import FolderLock

    mine = NewFolder(tmp_path / "runs" / "a", "a")
    (tmp_path / "runs" / "a").mkdir(parents=True)
    (tmp_path / "runs" / "a" / "config.toml").write_text("x")
    (tmp_path / "runs" / "b").mkdir()  # another run's, made meanwhile
    mine.discard()
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["b"]
    held = NewFolder(tmp_path / "new" / "c", "c")
    with FolderLock(tmp_path / "new" / "c", "someone-else"):
        held.discard()
        assert (tmp_path / "new" / "c" / ".swarm.lock").exists()
    found = NewFolder(tmp_path / "runs", None)  # it was there: nothing is made, nothing goes
    found.discard()
    assert (tmp_path / "runs" / "b").is_dir() and not found.made


def test_a_stop_during_a_step_that_must_finish_waits_for_it():
    """``protocol.cli.stops_deferred``: Ctrl-C arriving while ``swarm run`` spawns its agents
    waits until every agent it started is held (one was left running once the launcher had
    exited); then it acts as it would have, a ``KeyboardInterrupt`` after the block."""
    import subprocess
    import sys

    script = (
        "import os, signal\n"
        "from protocol.cli import stops_deferred\n"
        "done = []\n"
        "try:\n"
        "    with stops_deferred():\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        done.append('finished')\n"
        "    print('not interrupted')\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted after', done)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60, cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == "interrupted after ['finished']", out
