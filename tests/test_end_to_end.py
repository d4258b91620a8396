"""End to end over Zenoh: in-process sessions, separate processes, and a hand-assembled run
give identical numbers, and the numbers match the geometry's ground truth."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.config import AgentBrief, RunConfig, load_config
from protocol.record import TICK_COLUMNS, read_ticks
from protocol.session import free_tcp_endpoint
from swarm.launch import agent_commands, launch, write_briefs
from tests.boundaries import check_imports
from world import ideal_formation
from world.surfaces import make_surface

ROOT = Path(__file__).resolve().parents[1]
SUMMARY_KEYS = {"mean_required_range", "rmse", "mean_stay_range", "mean_persist_range",
                "mean_persist_range_noise_free", "mean_floor_range", "lost_ticks", "missed_ticks",
                "estimated_ticks", "fallback_ticks", "followed", "mean_formation_error",
                "worst_formation_error", "broken_ticks"}


def _numbers(run_dir: Path) -> tuple[str, dict]:
    summary = json.loads((run_dir / "summary.json").read_text())
    return (run_dir / "ticks.csv").read_text(), summary["followers"]


@pytest.fixture(scope="module")
def chain_config() -> RunConfig:
    """Two followers with every kind of noise and an estimator that uses velocities."""
    return RunConfig(run_id="e2e", surface="wavy", followers=2, ticks=14, agent_timeout=20.0,
                     dictionary="c", velocity="estimated", noise_range=0.01,
                     noise_bearing=0.005, noise_velocity=0.02, noise_move=0.01, seed=11)


@pytest.fixture(scope="module")
def in_process_run(tmp_path_factory, chain_config):
    out = tmp_path_factory.mktemp("inproc")
    summary = launch(chain_config, out, in_process=True)
    return out, summary


def test_results_folder(in_process_run, chain_config):
    out, summary = in_process_run
    assert summary["complete"] and summary["ticks_completed"] == chain_config.ticks
    header = (out / "ticks.csv").read_text().splitlines()[0].split(",")
    assert tuple(header) == TICK_COLUMNS
    on_disk = json.loads((out / "summary.json").read_text())
    assert set(on_disk["followers"]) == {"1", "2"}
    for stats in on_disk["followers"].values():
        assert set(stats) == SUMMARY_KEYS
        assert stats["estimated_ticks"] == chain_config.ticks - chain_config.init_ticks
    resolved = load_config(out / "config.toml")
    assert resolved.leader_start == (30.0, 5.0, 1.0, 0.0) and resolved.run_id == "e2e"
    assert not list(out.glob(".*.tmp"))  # atomic writes leave no temporaries


def test_ground_truth(in_process_run, chain_config):
    """The leader drives the ideal formation's geodesic exactly; a follower settles near its
    place in the ideal formation (under noise a snap is a move by the sensed offset, design §4),
    and every range is measured from where it really is."""
    out, _ = in_process_run
    rows = read_ticks(out / "ticks.csv")
    cfg = load_config(out / "config.toml")
    truth = ideal_formation(make_surface(cfg.surface), cfg.leader_start, cfg.followers,
                            cfg.spacing, cfg.comm_period, cfg.ticks)
    for row in rows:
        pos = np.array([row["pos_x"], row["pos_y"]])
        if row["agent"] == 0:
            np.testing.assert_allclose(pos, truth[0, row["tick"]], atol=1e-9)
            continue
        error = np.hypot(*(pos - truth[row["agent"], row["tick"]]))
        assert row["formation_error"] == pytest.approx(error, abs=1e-12)
        assert 0 < row["formation_error"] < 0.2
        ideal = np.array([row["ideal_x"], row["ideal_y"]])
        if row["tick"] >= cfg.init_ticks:
            est = np.array([row["est_x"], row["est_y"]])
            assert row["required_range"] == pytest.approx(np.hypot(*(est - ideal)), abs=1e-12)
        else:
            assert row["est_x"] is None and row["required_range"] is None


def test_processes_match_in_process(tmp_path, in_process_run, chain_config):
    out, _ = in_process_run
    summary = launch(chain_config, tmp_path / "procs", in_process=False)
    assert summary["complete"]
    assert _numbers(tmp_path / "procs") == _numbers(out)


def test_in_memory_layout_matches(tmp_path, in_process_run, chain_config):
    """``swarm.local`` (no network; used for estimator studies) gives the same numbers."""
    from swarm.local import run_local

    out, _ = in_process_run
    run_local(chain_config, tmp_path / "local")
    assert _numbers(tmp_path / "local") == _numbers(out)


def test_hand_assembled_run_matches(tmp_path, in_process_run):
    """``python -m world`` from the written config.toml + ``python -m agents.*`` from their
    briefs: same numbers."""
    out, _ = in_process_run
    endpoint = free_tcp_endpoint()
    config = out / "config.toml"
    procs = [subprocess.Popen([sys.executable, "-m", "world", "--config", str(config),
                               "--listen", endpoint, "--out", str(tmp_path / "hand")], cwd=ROOT)]
    try:
        briefs = write_briefs(load_config(config), tmp_path / "agents")
        procs += [subprocess.Popen(cmd, cwd=ROOT) for cmd in agent_commands(briefs, endpoint, 2)]
        codes = [p.wait(timeout=90) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert codes == [0, 0, 0, 0]
    assert _numbers(tmp_path / "hand") == _numbers(out)


def test_world_start_timeout(tmp_path):
    """A world whose agents never come fails with a clear message, not a hang."""
    from protocol.config import dump_config

    dump_config(RunConfig(run_id="lonely", start_timeout=1.0), tmp_path / "c.toml")
    endpoint = free_tcp_endpoint()
    proc = subprocess.run([sys.executable, "-m", "world", "--config", str(tmp_path / "c.toml"),
                           "--listen", endpoint, "--out", str(tmp_path / "o")],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "agents 0, 1 (2 of 2) did not come up within 1 s" in proc.stderr
    # a hand-started world says where it listens and whom it waits for, once
    assert proc.stdout.splitlines() == [
        f"world: run lonely listening on {endpoint}; waiting up to 1 s for the leader and 1 "
        f"follower; results into {tmp_path / 'o'}"]


def test_an_in_process_agent_whose_session_fails_is_named(tmp_path):
    """The router refuses follower 1 (its line in the router's password dictionary was changed
    from outside): the run stops before tick 0 naming that agent's Zenoh session, not with
    another agent's later timeout, and lists who had not come up."""
    from swarm.launch import RunCredentials

    config = RunConfig(run_id="refused", followers=2, ticks=6, start_timeout=6.0)
    credentials = RunCredentials.create(tmp_path / "credentials", config.followers)
    lines = credentials.dictionary.read_text().splitlines()
    credentials.dictionary.write_text("\n".join(
        "follower-1:not-its-password" if line.startswith("follower-1:") else line
        for line in lines) + "\n")
    with pytest.raises(RuntimeError, match=r"run aborted before it started: agent 1's Zenoh "
                                           r"session failed: .*\(agent 1 had not come up\)"):
        launch(config, tmp_path / "run", in_process=True, credentials=credentials)


def test_agent_without_world_exits(tmp_path):
    brief = AgentBrief.of(RunConfig(run_id="orphan", start_timeout=1.0), 0)
    proc = subprocess.run([sys.executable, "-m", "agents.leader", "--config",
                           str(brief.write(tmp_path / "leader.toml")), "--session-mode", "peer"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "is the world running?" in proc.stderr


def test_agents_never_import_world():
    """Static check of every module in agents/, and a live import check in a fresh interpreter."""
    check_imports(ROOT / "agents", ("agents.leader", "agents.follower", "agents.policies",
                                    "agents.estimators"), ("world", "scipy", "swarm"))


def test_leaving_the_domain_ends_the_run_cleanly(tmp_path):
    """A leader driving off a hemisphere: partial result marked incomplete, clear reason."""
    summary = launch(RunConfig(run_id="rim", surface="hemisphere", followers=1, ticks=40),
                     tmp_path / "rim", in_process=True)
    assert summary["complete"] is False
    assert "domain" in summary["reason"]
    on_disk = json.loads((tmp_path / "rim" / "summary.json").read_text())
    assert on_disk["complete"] is False and 4 < on_disk["ticks_completed"] < 40
    assert len(read_ticks(tmp_path / "rim" / "ticks.csv")) == 2 * on_disk["ticks_completed"]


def test_cli_repeats_a_run_from_its_config_and_never_overwrites(tmp_path, in_process_run):
    from swarm.cli import main

    out, _ = in_process_run
    again = tmp_path / "again"
    assert main(["run", "--config", str(out / "config.toml"), "--in-process",
                 "--out", str(again)]) == 0
    assert _numbers(again) == _numbers(out)
    before = (again / "ticks.csv").read_text()
    assert main(["run", "--config", str(out / "config.toml"), "--in-process",
                 "--out", str(again)]) == 2
    assert (again / "ticks.csv").read_text() == before


def test_cli_rejects_bad_flags(capsys):
    from swarm.cli import main

    assert main(["run", "--followers", "0"]) == 2
    assert "followers must be an integer" in capsys.readouterr().err
    assert main(["run", "--leader-start", "1,2,x,4"]) == 2
    assert "--leader-start must be X,Y,VX,VY" in capsys.readouterr().err
    assert main(["run", "--surface", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
