"""Agents are told only what a robot knows (design §5, §9): every agent process reads its
brief (:class:`protocol.config.AgentBrief`), never the run's configuration, in every layout."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from protocol.config import AgentBrief, RunConfig, dump_config
from swarm.cli import main
from swarm.launch import launch

ROOT = Path(__file__).resolve().parents[1]
SEED = 987654321  # distinctive: it appears in nothing an agent is given
SECRETS = (str(SEED), "hyperbolic", "leader_start")


def _children_given() -> dict[int, tuple[list[str], str, dict[str, str]]]:
    """What each agent process this process started is given: pid -> (command line,
    environment, {path: text} of every file its arguments name)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            status = (entry / "status").read_text()
            parent = int(next(line.split()[1] for line in status.splitlines()
                              if line.startswith("PPid:")))
            argv = (entry / "cmdline").read_bytes().decode().split("\0")[:-1]
            environ = (entry / "environ").read_bytes().decode("utf-8", "replace")
        except (OSError, StopIteration):  # gone meanwhile, or not ours to read
            continue
        if parent == os.getpid() and any(a.startswith("agents.") for a in argv):
            files = {arg: Path(arg).read_text() for arg in argv[1:] if Path(arg).is_file()}
            found[int(entry.name)] = (argv, environ, files)
    return found


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="needs Linux's /proc")
def test_no_argument_or_file_an_agent_process_is_given_holds_the_worlds_secrets(tmp_path):
    """A processes run with a distinctive seed on the hyperbolic surface with a leader start of
    its own: at the first tick, read from /proc every agent process's command line and
    environment, and every file its arguments name; none holds the seed, the surface or the
    leader start (the world's config.toml does)."""
    config = RunConfig(run_id="secret", surface="hyperbolic", followers=2, ticks=6,
                       seed=SEED, noise_range=0.01, leader_start=(50.0, -20.0, 1.0, 0.0))
    seen: dict[int, tuple[list[str], str, dict[str, str]]] = {}

    def look(tick: int) -> None:  # while the agents run (their files go at the end)
        if tick == 0:
            seen.update(_children_given())

    summary = launch(config, tmp_path / "run", on_tick=look)
    assert summary["complete"]
    assert str(SEED) in (tmp_path / "run" / "config.toml").read_text()  # the world's own
    commands = [argv for argv, _, _ in seen.values()]
    assert sorted(argv[2] for argv in commands) == ["agents.follower", "agents.follower",
                                                    "agents.leader"], commands
    for argv, environ, files in seen.values():
        assert len(files) == 2, argv  # its brief and its password file
        for secret in SECRETS:
            assert secret not in " ".join(argv) and secret not in environ, (secret, argv)
            for path, text in files.items():
                assert secret not in text, (secret, path, text)


def test_an_agent_given_the_runs_configuration_refuses_it_in_one_line(tmp_path):
    """The run's config.toml holds the world's secrets: an agent refuses it (status 2) and
    says how to make its brief; nothing connects."""
    dump_config(RunConfig(run_id="r", seed=SEED), tmp_path / "config.toml")
    proc = subprocess.run([sys.executable, "-m", "agents.follower", "--id", "1", "--config",
                           str(tmp_path / "config.toml")], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert "is a run configuration" in proc.stderr
    assert "python -m swarm agent-config" in proc.stderr and "--id K" in proc.stderr


def test_agent_config_writes_a_brief_without_secrets_that_loads_back(tmp_path, capsys):
    config = RunConfig(run_id="r", surface="wavy", followers=3, seed=SEED, noise_range=0.02,
                       estimator="auto", leader_start=(30.0, 5.0, 1.0, 0.0))
    dump_config(config, tmp_path / "config.toml")
    assert main(["agent-config", str(tmp_path / "config.toml"), "--id", "2"]) == 0
    text = capsys.readouterr().out
    assert str(SEED) not in text and "wavy" not in text
    assert not re.search(r"^(seed|surface|leader_start|sensing_range) ", text, re.MULTILINE)
    (tmp_path / "f2.toml").write_text(text)
    brief = AgentBrief.load(tmp_path / "f2.toml")
    assert brief == AgentBrief.of(config, 2)
    assert brief.settings.noise_range == 0.02 and brief.settings.estimator == "auto"
    assert main(["agent-config", str(tmp_path / "config.toml"), "--all", "--out",
                 str(tmp_path / "agents")]) == 0
    assert sorted(p.name for p in (tmp_path / "agents").iterdir()) == [
        "follower-1.toml", "follower-2.toml", "follower-3.toml", "leader.toml"]
    assert main(["agent-config", str(tmp_path / "config.toml"), "--id", "4"]) == 2
    assert "agent id must be in 0..3" in capsys.readouterr().err


@pytest.mark.parametrize("text, fragment", [
    ('agent = 1\n[settings]\nrun_id = "r"\nseed = 5\n', "seed is not something an agent is told"),
    ('agent = 1\n[settings]\nrun_id = "r"\nsurface = "wavy"\n', "surface is not something"),
    ('agent = 1\nseed = 5\n[settings]\nrun_id = "r"\n', "must hold `agent = K` and a [settings]"),
    ('agent = 1\n[settings]\nrun_id = "r"\nforget = 2.0\n', "forget must be in"),
    ('agent = -1\n[settings]\nrun_id = "r"\n', "agent id must be a non-negative integer"),
])
def test_a_brief_holds_only_what_agents_are_told(tmp_path, text, fragment):
    (tmp_path / "a.toml").write_text(text)
    with pytest.raises(ValueError, match="agent brief .*a.toml") as error:
        AgentBrief.load(tmp_path / "a.toml")
    assert fragment in str(error.value)


def test_an_agent_refuses_another_agents_brief(tmp_path, capsys):
    from agents import follower, leader

    config = RunConfig(run_id="r", followers=2)
    one = AgentBrief.of(config, 1).write(tmp_path / "follower-1.toml")
    assert leader.main(["--config", str(one)]) == 2
    assert "is follower 1's brief, not the leader's" in capsys.readouterr().err
    assert follower.main(["--id", "2", "--config", str(one)]) == 2
    assert "not follower 2's" in capsys.readouterr().err
    chief = AgentBrief.of(config, 0).write(tmp_path / "leader.toml")
    assert follower.main(["--config", str(chief)]) == 2
    assert "is the leader's brief, not a follower's" in capsys.readouterr().err
