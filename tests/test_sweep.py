"""``swarm sweep GRID.toml`` and ``swarm compare`` over Zenoh: tables, ratios to the persist
baseline of the same runs, bad grid files, and the experiment/report import order."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from swarm.cli import main
from swarm.grid import read_table

ROOT = Path(__file__).resolve().parents[1]
GRID = """
name = "tiny"
[base]
ticks = 8
surface = "wavy"
[axes]
estimator = ["persist", "auto"]
[axes.noise]
none = {}
middle = { noise_range = 0.02, noise_bearing = 0.01 }
"""


def test_sweep_writes_one_row_per_run_with_ratios(tmp_path, capsys):
    grid = tmp_path / "tiny.toml"
    grid.write_text(GRID)
    assert main(["sweep", str(grid), "--out", str(tmp_path / "out"), "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert "persist (noise-free)" in printed and "tiny-mean.csv" in printed
    rows = read_table(tmp_path / "out" / "tables" / "tiny.csv")
    assert [(r["estimator"], r["noise"]) for r in rows] == [
        ("persist", "none"), ("persist", "middle"), ("auto", "none"), ("auto", "middle")]
    for row in rows:
        assert (tmp_path / "out" / "runs" / row["run"] / "summary.json").is_file()
        assert row["ratio_to_persist"] == pytest.approx(
            row["mean_required_range"] / row["mean_persist_range"])
        if row["estimator"] == "persist":  # the baseline is computed from the same readings
            assert row["ratio_to_persist"] == pytest.approx(1.0, abs=1e-9)
    middle = {r["estimator"]: r for r in rows if r["noise"] == "middle"}
    # persist's counterfactual is what persist itself does, from the same readings
    assert middle["persist"]["mean_persist_range"] == pytest.approx(
        middle["persist"]["mean_required_range"], rel=1e-9)
    assert middle["persist"]["mean_persist_range"] != pytest.approx(
        middle["persist"]["mean_persist_range_noise_free"])


def test_compare_averages_over_seeds(tmp_path, capsys):
    assert main(["compare", "--surface", "elliptic", "--ticks", "8", "--noise-range", "0.01",
                 "--estimators", "persist,kalman", "--seeds", "0,1", "--workers", "1",
                 "--out", str(tmp_path)]) == 0
    assert "kalman" in capsys.readouterr().out
    runs = read_table(tmp_path / "tables" / "compare.csv")
    means = read_table(tmp_path / "tables" / "compare-mean.csv")
    assert len(runs) == 4 and [m["estimator"] for m in means] == ["persist", "kalman"]
    for mean in means:
        mine = [r for r in runs if r["estimator"] == mean["estimator"]]
        assert mean["n"] == 2 and mean["seed"] == "0 1"
        assert mean["mean_required_range"] == pytest.approx(
            sum(r["mean_required_range"] for r in mine) / 2)
    assert runs[0]["mean_persist_range"] != runs[1]["mean_persist_range"]  # seeds differ


@pytest.mark.parametrize("text, message", [
    ("[axes]\nestimator = []\n", "axes.estimator must be a non-empty list"),
    ("colour = 1\n[axes]\nseed = [0]\n", "unknown key(s) ['colour']"),
    ("[axes]\nestimator = ['nope']\n", "estimator must be one of"),
    ("[base]\nticks = 1\n[axes]\nseed = [0]\n", "ticks must be an integer"),
    ("[axes.noise]\nbad = 3\n", "axes.noise.bad must be a table"),
    ("[axes]\ncomm_period = [1.28, 0.64, 1.280]\n", "axis 'comm_period' lists 1.28 more than once"),
    ("[axes.noise]\n'a b' = {}\na_b = { noise_range = 0.01 }\n",
     "{'noise': 'a b'} and {'noise': 'a_b'} would share the run folder 'g/a_b'"),
])
def test_bad_grid_files_are_refused(tmp_path, capsys, text, message):
    grid = tmp_path / "g.toml"
    grid.write_text(text)
    assert main(["sweep", str(grid), "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flags, message", [
    (["--seeds", "0,x"], "--seeds must be comma-separated integers"),
    (["--follower", "2"], "--follower must be in 1..1"),
    (["--estimators", ","], "--estimators must name at least one estimator"),
    (["--estimators", "persist,nope"], "estimator must be one of"),
    (["--workers", "0"], "--workers must be at least 1"),
    (["--seeds", "0,1,0"], "axis 'seed' lists 0 more than once"),
    (["--estimators", "persist,kalman,persist"], "axis 'estimator' lists 'persist' more than once"),
])
def test_bad_compare_flags_are_refused(tmp_path, capsys, flags, message):
    assert main(["compare", "--out", str(tmp_path / "o"), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_report_does_not_import_the_experiment():
    """The experiment <-> report import cycle is gone: report needs only the grid module."""
    code = ("import sys, swarm.report; "
            "sys.exit(1 if 'swarm.experiment' in sys.modules else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
