"""``--estimator package.module:Name`` (design §6): loaded by the follower process only, run over
Zenoh with agents as processes, its name recorded, its not-ready ticks counted as fallbacks."""
from __future__ import annotations

import csv
import json
import re
import sys

import pytest

from agents.policies import load_estimator, make_policy
from protocol.config import AgentSettings, RunConfig
from protocol.limits import MAX_NAME, NAME_RULE
from swarm.launch import launch
from swarm.local import run_local
from world.main import resolve_with_surface

SPEC = "tests.example_estimator:MeanStep"


def test_plugin_runs_over_zenoh_as_processes(tmp_path):
    config = RunConfig(run_id="plugin", surface="elliptic", ticks=12, estimator=SPEC,
                       agent_timeout=20.0)
    sys.modules.pop("tests.example_estimator", None)
    summary = launch(config, tmp_path / "procs", in_process=False)
    # Only the follower process imported it, never the world (this process).
    assert "tests.example_estimator" not in sys.modules
    assert summary["complete"] and summary["estimator"] == SPEC
    s = summary["followers"]["1"]
    assert s["fallback_ticks"] == 1 and s["estimated_ticks"] == 7  # tick 4 needs 5 samples
    assert s["followed"] == pytest.approx({"mean-step": 7 / 8, "persist": 1 / 8})
    with open(tmp_path / "procs" / "observations.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["agent"] == "1"]
    assert {r["estimator"] for r in rows} == {"mean-step"}
    with open(tmp_path / "procs" / "ticks.csv", newline="") as fh:
        assert {r["estimator"] for r in csv.DictReader(fh) if r["agent"] == "1"} == {SPEC}
    # The in-memory layout gives the same numbers.
    run_local(config, tmp_path / "local")
    assert ((tmp_path / "local" / "ticks.csv").read_text()
            == (tmp_path / "procs" / "ticks.csv").read_text())
    on_disk = json.loads((tmp_path / "procs" / "summary.json").read_text())
    follower = on_disk["followers"]["1"]
    assert follower["mean_required_range"] < follower["mean_persist_range"]


def test_a_plugin_name_at_the_limit_runs_over_zenoh(tmp_path):
    """The name limit has one owner (protocol.limits.MAX_NAME) that the follower's loader and
    the world's codec both use: a name of MAX_NAME characters travels in every observation
    (it used to be allowed up to 128 at load and killed the follower at tick 0)."""
    spec = "tests.example_estimator:LongestName"
    summary = launch(RunConfig(run_id="long-name", ticks=6, estimator=spec), tmp_path,
                     in_process=True)
    assert summary["complete"], summary["reason"]
    assert summary["ticks_completed"] == 6
    with open(tmp_path / "observations.csv", newline="") as fh:
        assert {r["estimator"] for r in csv.DictReader(fh)} == {"n" * MAX_NAME}


def test_plugin_errors_name_the_problem():
    settings = AgentSettings.from_config(RunConfig())
    with pytest.raises(ValueError, match="cannot import 'tests.nowhere'"):
        load_estimator("tests.nowhere:X", settings)
    with pytest.raises(ValueError, match="has no class or factory 'Missing'"):
        load_estimator("tests.example_estimator:Missing", settings)
    with pytest.raises(ValueError, match="does not implement propose, record, skip"):
        load_estimator("tests.example_estimator:not_a_policy", settings)
    with pytest.raises(ValueError, match=re.escape(f"name must be {NAME_RULE}")):
        load_estimator("tests.example_estimator:LongName", settings)
    with pytest.raises(ValueError, match="estimator must be one of"):
        RunConfig(estimator="no colon")
    policy = make_policy(AgentSettings.from_config(RunConfig(estimator=SPEC)))
    assert policy.name == "mean-step"


def test_a_plugin_that_fails_in_its_follower_is_reported_by_swarm_run_in_one_line(
        tmp_path, capsys, monkeypatch):
    """Only the follower process imports the estimator (`swarm run` checks only that its
    module is there, running none of it); `swarm run` still says why it stopped (the
    follower's own error line), not just its exit status."""
    from swarm.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty_plugin.py").write_text("")
    assert main(["run", "--estimator", "empty_plugin:X", "--ticks", "6",
                 "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("error: run aborted before it started: agent 1 exited with status 2: "
                             "estimator 'empty_plugin:X': empty_plugin has no class or factory "
                             "'X'")
    assert err[0].endswith(f"(see {tmp_path / 'o' / 'logs' / 'agent-1.log'}) (agent 1 had not "
                           "come up)")


def test_a_plugin_is_not_told_the_top_speed_of_a_drive_run():
    """A drive run's default top speed is twice the leader's speed on the hidden surface: the
    driving controller gets it, an estimator (here a plug-in) does not."""
    from tests import example_estimator

    spec = "tests.example_estimator:NotesItsSettings"
    config = RunConfig(motion="drive", surface="wavy", followers=2, ticks=6, estimator=spec)
    resolved, _ = resolve_with_surface(config)
    assert resolved.max_speed is not None and AgentSettings.from_config(resolved).max_speed
    example_estimator.SETTINGS_SEEN.clear()
    make_policy(AgentSettings.from_config(resolved))
    summary, _ = run_local(config)
    assert summary["complete"]
    seen = example_estimator.SETTINGS_SEEN
    assert len(seen) == 3 and all(s.motion == "drive" for s in seen)
    assert [s.max_speed for s in seen] == [None, None, None]


@pytest.mark.parametrize("command, layout", [
    (["{python}", "-m", "swarm"], "--in-process"),
    (["{bin}/swarm"], "--in-process"),
    (["{python}", "-m", "swarm"], "--processes"),
    (["{bin}/swarm"], "--processes"),
], ids=["python-m-in-process", "console-in-process", "python-m-processes", "console-processes"])
def test_a_plugin_in_the_current_folder_resolves_in_every_entry_point_and_layout(
        tmp_path, command, layout):
    """docs/estimators.md: a plug-in resolves from the current folder, whichever way the tool
    was started (the console script puts no folder on sys.path of its own) and wherever the
    followers run. The module exists only in the current folder."""
    import shutil
    import subprocess
    from pathlib import Path

    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "swarm").exists():
        pytest.skip("the swarm console script is not installed beside this interpreter")
    source = Path(__file__).with_name("example_estimator.py")
    shutil.copy(source, tmp_path / "my_plugin.py")
    argv = [part.format(python=sys.executable, bin=bin_dir) for part in command]
    proc = subprocess.run([*argv, "run", layout, "--ticks", "8", "--estimator",
                           "my_plugin:MeanStep", "--out", "run"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "run" / "observations.csv", newline="") as fh:
        assert {r["estimator"] for r in csv.DictReader(fh) if r["agent"] == "1"} == {"mean-step"}
