"""Hostile peers with real router sessions (issue: runs survive any hostile peer).

A peer holding a run's credentials (the worst case: a stolen password) floods observations and
publishes rods for far-future ticks; a second world tries to serve a live run id; a realtime
run loses a follower for good. The run's numbers do not change, files stay bounded, the second
world is refused, and the dead follower's successors keep their own time budget.
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from protocol import keys
from protocol.config import RunConfig, dump_config
from protocol.messages import Observation, Rod, encode
from protocol.record import read_observations, read_ticks
from protocol.session import free_tcp_endpoint, zenoh_config
from swarm.launch import RunCredentials, launch
from tests.attacking import run_under_attack, same_results, wait_for_world
from tests.deployment import hand_started
from tests.waiting import ticks_done, wait_for

ROOT = Path(__file__).resolve().parents[1]


def _flood(endpoint: str, run_id: str, credentials: RunCredentials, stop: threading.Event,
           sent: dict) -> None:
    """As the leader: rods for tick 10,000,000; as follower 1: observations for ticks that are
    never in progress, 2,000 of them."""
    sessions = [zenoh.open(zenoh_config("client", connect=[endpoint], user=user,
                                        password=credentials.passwords[user]))
                for user in ("leader", "follower-1")]
    try:
        wait_for_world(sessions[0], run_id, stop)
        far = encode(Rod(tick=10_000_000, length=3.57, side=1))
        for i in range(2000):
            if stop.is_set():
                break
            sessions[0].put(keys.rod(run_id, 0), far)
            obs = Observation(tick=10_000 + i, estimator="edmd-b", measurement=(1.0, 2.0))
            sessions[1].put(keys.obs(run_id, 1), encode(obs))
            sent["n"] += 1
            if i % 50 == 0:
                time.sleep(0.005)  # spread over the run
    finally:
        for session in sessions:
            session.close()


def test_observation_flood_and_far_future_rods_change_nothing(tmp_path, caplog):
    caplog.set_level("WARNING")
    cfg = RunConfig(run_id="flood", surface="wavy", followers=2, ticks=40)
    sent = {"n": 0}
    clean, attacked = run_under_attack(
        cfg, tmp_path, lambda endpoint, credentials, stop: _flood(endpoint, cfg.run_id,
                                                                  credentials, stop, sent))
    assert sent["n"] > 0 and same_results(tmp_path)
    obs = read_observations(tmp_path / "attacked" / "observations.csv")
    assert len(obs) == cfg.ticks * cfg.followers  # one per follower and tick, nothing more
    assert attacked["followers"] == clean["followers"]
    text = caplog.text
    assert "dropped observation" in text  # the world's one-per-tick rule
    assert "for tick 10000000" in text  # follower 1 did not believe the far-future rod


def test_a_second_world_with_a_live_run_id_refuses(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    cfg = RunConfig(run_id="twice", followers=1, ticks=10, start_timeout=30.0)
    dump_config(cfg, folder / "config.toml")
    endpoint = free_tcp_endpoint()
    first = subprocess.Popen([sys.executable, "-m", "world",
                              "--config", str(folder / "config.toml"), "--listen", endpoint,
                              "--out", str(folder / "first")], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as watcher:
            up = threading.Event()
            watch = watcher.liveliness().declare_subscriber(keys.alive("twice", "world"),
                                                            lambda _: up.set(), history=True)
            assert up.wait(30), "the first world never came up"
            watch.undeclare()
        second = subprocess.run(
            [sys.executable, "-m", "world", "--config", str(folder / "config.toml"),
             "--connect", endpoint, "--out", str(folder / "second")],
            cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert second.returncode == 1
        assert second.stderr.count("error:") == 1 and "'twice' is already live" in second.stderr
        assert first.poll() is None  # the live run is untouched
        assert not (folder / "second" / "ticks.csv").exists()
    finally:
        first.kill()
        first.communicate(timeout=10)


def test_world_refuses_a_finished_runs_folder(tmp_path):
    cfg = RunConfig(run_id="done-once", followers=1, ticks=6)
    launch(cfg, tmp_path / "run")
    before = (tmp_path / "run" / "ticks.csv").read_bytes()
    dump_config(cfg, tmp_path / "config.toml")
    again = subprocess.run([sys.executable, "-m", "world",
                            "--config", str(tmp_path / "config.toml"),
                            "--listen", free_tcp_endpoint(), "--out", str(tmp_path / "run")],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert again.returncode == 2  # refused before anything ran
    assert "already holds results of run 'done-once'" in again.stderr
    assert (tmp_path / "run" / "ticks.csv").read_bytes() == before


def test_a_dead_follower_never_makes_its_successors_miss(tmp_path):
    """Realtime: follower 1 is SIGKILLed for good after tick 3. It misses every later tick;
    followers 2 and 3 go on from where it stands (at most the tick in progress is lost)."""
    folder = tmp_path / "run"
    folder.mkdir()
    cfg = RunConfig(run_id="cascade", followers=3, ticks=30, mode="realtime", time_scale=0.08,
                    agent_timeout=2.0, start_timeout=30.0)
    out = folder / "out"
    procs = hand_started(folder, cfg)
    try:
        wait_for(lambda: ticks_done(out) >= 4, 60, "tick 4")
        procs[2].send_signal(signal.SIGKILL)  # follower 1
        procs[2].wait(timeout=10)
        procs[0].wait(timeout=120)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=10)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ticks_completed"] == cfg.ticks
    missed = {k: summary["followers"][str(k)]["missed_ticks"] for k in (1, 2, 3)}
    assert missed[1] >= cfg.ticks - 6  # dead from tick ~4 on
    assert missed[2] <= 2 and missed[3] <= 2, missed
    rows = read_ticks(out / "ticks.csv")
    assert {r["missed"] for r in rows if r["agent"] == 1 and r["tick"] > 8} == {1}
