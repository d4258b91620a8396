"""Faults: realtime misses, a killed follower rejoining from its checkpoint, duplicate ids,
a vanishing world, ``--resume``, Ctrl-C. Every process is ended and every wait bounded."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from protocol import keys
from protocol.config import RunConfig, dump_config
from protocol.record import read_ticks
from protocol.session import free_tcp_endpoint, zenoh_config
from swarm.launch import agent_commands, launch, write_briefs
from swarm.local import run_local
from tests.waiting import Procs, children, identified, running, signalled, ticks_done, wait_for

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def procs():
    p = Procs()
    yield p
    p.close()


def _world_cmd(config: Path, endpoint: str, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "world", "--config", str(config), "--listen", endpoint,
            "--out", str(out), *extra]


def test_realtime_without_pressure_matches_lockstep(tmp_path):
    cfg = dict(run_id="rt", followers=2, ticks=12)
    lock = launch(RunConfig(**cfg), tmp_path / "lock", in_process=True)
    real = launch(RunConfig(mode="realtime", time_scale=0.3, **cfg), tmp_path / "real",
                  in_process=True)
    assert real["complete"]
    assert all(f["missed_ticks"] == 0 for f in real["followers"].values())
    assert ((tmp_path / "lock" / "ticks.csv").read_text()
            == (tmp_path / "real" / "ticks.csv").read_text())
    assert lock["followers"] == real["followers"]


def test_realtime_misses_are_recorded_and_the_chain_goes_on(tmp_path):
    """An agent timeout far below one tick's work: agents miss ticks, the run still ends."""
    summary = launch(RunConfig(run_id="rtmiss", followers=2, ticks=10, mode="realtime",
                               time_scale=0.05, agent_timeout=0.0005), tmp_path / "o",
                     in_process=True)
    assert summary["complete"] and summary["ticks_completed"] == 10
    missed = [f["missed_ticks"] for f in summary["followers"].values()]
    assert sum(missed) > 0
    rows = read_ticks(tmp_path / "o" / "ticks.csv")
    assert len(rows) == 3 * 10  # every agent has a row for every tick, missed or not


def test_second_process_with_a_live_id_refuses(tmp_path, procs):
    cfg = RunConfig(run_id="dup", followers=1, start_timeout=5.0)
    out, endpoint = tmp_path / "run", free_tcp_endpoint()
    out.mkdir()
    dump_config(cfg, out / "config.toml")
    world = procs.start(_world_cmd(out / "config.toml", endpoint, out))
    briefs = write_briefs(cfg, out)
    first = procs.start(agent_commands(briefs, endpoint, 1)[1])
    with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        def first_is_live() -> bool:
            replies = session.liveliness().get(keys.alive("dup", 1), timeout=1.0)
            return any(r.ok is not None for r in replies)

        wait_for(first_is_live, 60, "the first follower's liveliness token")
    second = subprocess.run(agent_commands(briefs, endpoint, 1)[1], cwd=ROOT,
                            capture_output=True, text=True, timeout=30)
    assert second.returncode == 1
    assert "agent id 1 is already live" in second.stderr
    for proc in (world, first):
        proc.kill()


@pytest.mark.slow  # fast tier: test_link.py (an agent whose world vanishes) and test_integrity.py
# (a resume after the world was killed gives the numbers of an undisturbed run)
def test_agents_exit_when_the_world_vanishes_and_resume_continues(tmp_path, procs):
    """World SIGKILLed once 10 ticks are done and not back within the agents' start timeout:
    agents exit with a clear error and keep their state; ``--resume`` plus restarted agents
    finish the run with exactly the numbers of an uninterrupted one (tests/test_recovery.py
    draws the moments at random, and restarts the world while its agents still wait)."""
    # long enough that the world cannot finish between the poll and the kill (a loaded machine)
    cfg = RunConfig(run_id="resume", surface="wavy", followers=2, ticks=300, agent_timeout=10.0,
                    start_timeout=10.0)
    reference = tmp_path / "ref"  # in memory: every layout gives the same numbers
    run_local(cfg, reference)
    out, endpoint = tmp_path / "run", free_tcp_endpoint()
    out.mkdir()
    dump_config(cfg, out / "config.toml")
    world = procs.start(_world_cmd(out / "config.toml", endpoint, out))
    briefs = write_briefs(cfg, out)  # and the followers' state beside them, in out/state
    agents = [procs.start(cmd) for cmd in agent_commands(briefs, endpoint, 2)]
    wait_for(lambda: ticks_done(out) >= 10, 60, "tick 10")
    world.send_signal(signal.SIGKILL)
    assert world.wait(timeout=10) == -signal.SIGKILL
    for proc in agents:
        assert proc.wait(timeout=30) == 1
        assert "the world process disappeared" in proc.stderr.read()
    assert json.loads((out / "summary.json").read_text())["complete"] is False
    assert sorted(p.name for p in (out / "state").iterdir()) == [
        "agent-1.state", "agent-2.state"]  # kept: the run is not complete
    endpoint = free_tcp_endpoint()
    world = procs.start([sys.executable, "-m", "world", "--resume", str(out), "--listen", endpoint])
    agents = [procs.start(cmd) for cmd in agent_commands(briefs, endpoint, 2)]
    assert world.wait(timeout=60) == 0, world.stderr.read()
    for proc in agents:
        assert proc.wait(timeout=30) == 0
    for name in ("ticks.csv", "observations.csv"):
        assert (out / name).read_text() == (reference / name).read_text()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"]
    assert summary["followers"] == json.loads((reference / "summary.json").read_text())["followers"]


@pytest.mark.skipif(os.name != "posix", reason="signals")
@pytest.mark.parametrize("stop", [  # SIGTERM's 143, fast: the cleanup test below, test_grid_workers
    pytest.param(signal.SIGINT, id="ctrl-c"),
    pytest.param(signal.SIGTERM, id="sigterm", marks=pytest.mark.slow)])
def test_ctrl_c_stops_everything_and_leaves_a_partial_result(tmp_path, stop):
    """Ctrl-C, or a supervisor's SIGTERM, to ``swarm run`` alone: every agent process ends, the
    partial result stays, the run's temporary credentials are removed, status 128 + signal."""
    out, scratch = tmp_path / "run", tmp_path / "tmp"
    scratch.mkdir()
    # paced at 0.3 × 1.28 s a tick: two ticks come soon, the end (200 ticks) never before the stop
    proc = subprocess.Popen([sys.executable, "-m", "swarm", "run", "--followers", "2",
                             "--mode", "realtime", "--time-scale", "0.3", "--ticks", "200",
                             "--out", str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "TMPDIR": str(scratch)})
    try:
        wait_for(lambda: ticks_done(out) >= 2, 60, "two ticks")
        agents = identified(children(proc.pid))
        assert len(agents) == 3
        assert len(_credentials(scratch)) == 1
    finally:
        code, _, err = signalled(proc, stop, 20)
    assert code == 128 + stop, err
    wait_for(lambda: not any(running(pid, started) for pid, started in agents.items()), 10,
             "agent processes to end")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is False and summary["ticks_completed"] >= 2
    assert read_ticks(out / "ticks.csv")  # readable
    assert not _credentials(scratch)  # the passwords did not outlive the run


def _credentials(folder: Path) -> list[Path]:
    """The temporary credential folders of ``swarm run`` in ``folder``."""
    return [p for p in folder.iterdir() if p.name.startswith("swarm-credentials-")]


WEDGED_CLEANUP = """
import sys, threading
from protocol.cli import bounded_interrupt
with bounded_interrupt(grace=float(sys.argv[1])):
    try:
        print("ready", flush=True)
        threading.Event().wait(60)
    except KeyboardInterrupt:
        print("cleaning up", flush=True)
        if sys.argv[2] == "wedged":  # a teardown that never returns
            threading.Event().wait(60)
sys.exit(7)  # cleanup finished in time: the program's own status
"""


@pytest.mark.skipif(os.name != "posix", reason="signals")
@pytest.mark.parametrize("cleanup, stop", [  # each cleanup and each signal once in the fast tier
    pytest.param("wedged", signal.SIGINT, id="wedged-ctrl-c"),
    pytest.param("wedged", signal.SIGTERM, id="wedged-sigterm", marks=pytest.mark.slow),
    pytest.param("prompt", signal.SIGINT, id="prompt-ctrl-c", marks=pytest.mark.slow),
    pytest.param("prompt", signal.SIGTERM, id="prompt-sigterm")])
def test_ctrl_c_ends_a_process_whose_cleanup_wedges(cleanup, stop):
    """After Ctrl-C or SIGTERM the cleanup runs; if it is still running after the grace period
    the process exits with 128 + signal anyway (a Zenoh teardown can wedge); if it finishes,
    the program decides its status after Ctrl-C, and it is 143 after SIGTERM."""
    proc = subprocess.Popen([sys.executable, "-c", WEDGED_CLEANUP, "1.0", cleanup], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        code, out, err = signalled(proc, stop, 20)
    assert "cleaning up" in out
    if cleanup == "wedged":
        assert code == 128 + stop and "cleanup still running after 1 s" in err
    else:
        assert code == (7 if stop == signal.SIGINT else 143) and "still running" not in err


def test_bounded_interrupt_restores_the_signal_handler():
    from protocol.cli import bounded_interrupt

    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    with bounded_interrupt(grace=1.0):
        for sig, handler in before.items():
            assert signal.getsignal(sig) is not handler
    for sig, handler in before.items():
        assert signal.getsignal(sig) is handler
