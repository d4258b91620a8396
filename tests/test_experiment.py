"""The paper experiment end to end on the reduced grid (same code path as the full one, over
Zenoh), plus the pieces with a known answer: the grid, the tables, the leader's relative
position behind the effectiveness figure, and the PNG files."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from protocol.config import RunConfig
from swarm import experiment
from swarm.cli import main
from swarm.experiment import (
    FULL,
    QUICK,
    TABLE_COLUMNS,
    GridRun,
    RunOutcome,
    paper_grid,
    practical_rows,
    read_table,
    run_grid,
    write_table,
)
from swarm.plots import leader_relative
from swarm.report import paper_report, write_report

ROOT = Path(__file__).resolve().parents[1]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
BROKEN = "dictionaries/elliptic-broken"


def assert_png(path: Path) -> None:
    """A real PNG: the signature, and matplotlib reads back an RGB(A) image of plausible size."""
    assert path.read_bytes()[:8] == PNG_SIGNATURE, path
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[2] in (3, 4), (path, image.shape)
    assert 300 <= image.shape[0] <= 4000 and 400 <= image.shape[1] <= 4000, (path, image.shape)
    assert image[..., :3].std() > 0.05, f"{path} is blank"


def test_grid_shape():
    full, quick = paper_grid(FULL), paper_grid(QUICK)
    assert set(full) == set(quick) == set(TABLE_COLUMNS) - {"effectiveness"}  # from sensing_range
    n_surfaces = len(FULL.surfaces)
    assert len(full["sensing_range"]) == n_surfaces * 4
    assert len(full["dictionaries"]) == n_surfaces * (7 + 2)
    assert len(full["practical"]) == n_surfaces * 5 * len(FULL.noise_velocities) * len(FULL.seeds)
    assert len(full["comm_period"]) == n_surfaces * len(FULL.comm_periods) * 4
    runs = [run for table in full.values() for run in table]
    assert len({run.folder for run in runs}) == len(runs)
    assert len({run.config.run_id for run in runs}) == len(runs)
    assert {r.config.followers for r in full["sensing_range"]} == {3}
    assert {r.config.followers for t in ("dictionaries", "practical", "comm_period")
            for r in full[t]} == {1}
    idealised = {r.labels["dictionary"]: r.config for r in full["dictionaries"]}
    assert idealised["c"].velocity == "oracle"
    assert all(idealised[d].gps for d in "defg")
    assert {r.config.surface for r in quick["sensing_range"]} == {"elliptic"}
    assert {r.config.ticks for t in quick.values() for r in t} == {QUICK.ticks}


def test_leader_relative_known_geometry():
    """Leader straight above the ideal position, bearing crossing ±pi: r, theta, unwrap."""
    rows = []
    for tick, angle in enumerate((3.0, 3.1, -3.1, -3.0)):  # crosses +pi between ticks 1 and 2
        lead = np.array([10.0, 5.0])
        ideal = lead - 2.0 * np.array([math.cos(angle), math.sin(angle)])
        est = ideal + (np.array([0.0, 0.1]) if tick >= 2 else np.array([np.nan, np.nan]))
        rows.append({"tick": tick, "agent": 0, "pos_x": lead[0], "pos_y": lead[1]})
        rows.append({"tick": tick, "agent": 1, "ideal_x": ideal[0], "ideal_y": ideal[1],
                     "est_x": None if tick < 2 else est[0], "est_y": None if tick < 2 else est[1]})
    rel = leader_relative(rows, 1)
    np.testing.assert_allclose(rel["r_ideal"], 2.0, rtol=1e-12)
    np.testing.assert_allclose(rel["theta_ideal"], [3.0, 3.1, 2 * math.pi - 3.1,
                                                    2 * math.pi - 3.0], rtol=1e-12)
    assert np.isnan(rel["r_est"][:2]).all()
    assert np.all(np.abs(rel["theta_est"][2:] - rel["theta_ideal"][2:]) < 0.1)
    with pytest.raises(ValueError, match="follower"):
        leader_relative(rows, 0)


def test_tables_round_trip_and_seed_average(tmp_path):
    config = RunConfig()
    outcomes = [RunOutcome(GridRun("practical", f"p{seed}", config,
                                   {"surface": "elliptic", "variant": "b", "noise_velocity": 0.05,
                                    "noise_move": 0.01}),
                           {"followers": {"1": {"rmse": rmse}}})
                for seed, rmse in enumerate((1.0, 2.0, 4.0))]
    outcomes.append(RunOutcome(outcomes[0].run, None, "ValueError: boom"))
    (row,) = practical_rows(outcomes)
    assert row["rmse"] == pytest.approx(7 / 3) and row["seeds"] == 3
    assert row["rmse_std"] == pytest.approx(np.std([1.0, 2.0, 4.0], ddof=1))
    row["rmse_std"] = math.nan
    path = tmp_path / "t.csv"
    write_table(path, TABLE_COLUMNS["practical"], [row])
    (back,) = read_table(path)
    assert math.isnan(back["rmse_std"]) and back["seeds"] == 3 and back["variant"] == "b"
    assert back["rmse"] == row["rmse"]  # floats are written with repr: exact round trip


def test_failed_run_does_not_lose_the_others(tmp_path):
    good = GridRun("comm_period", "good", RunConfig(run_id="good", ticks=6), {})
    bad = GridRun("comm_period", "bad", RunConfig(run_id="bad", surface="no_such_module:s",
                                                 ticks=6), {})
    outcomes = run_grid([bad, good], tmp_path, workers=2, progress=False)
    assert [o.run.name for o in outcomes] == ["bad", "good"]
    assert not outcomes[0].ok and "no_such_module" in outcomes[0].error
    assert outcomes[0].attempts == experiment.RUN_ATTEMPTS
    assert outcomes[1].ok and outcomes[1].summary["complete"]
    assert (tmp_path / "comm_period" / "good" / "summary.json").is_file()


@pytest.fixture(scope="module")
def quick_experiment(tmp_path_factory):
    """``swarm experiment paper --quick`` with one extra run that fails on purpose."""
    out = tmp_path_factory.mktemp("paper")
    original = experiment.paper_grid

    def grid_with_a_broken_run(spec):
        grid = original(spec)
        grid["dictionaries"].append(GridRun(
            "dictionaries", "elliptic-broken",
            RunConfig(run_id="broken", surface="no_such_module:s", ticks=spec.ticks),
            {"surface": "elliptic", "dictionary": "broken"}))
        return grid

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(experiment, "paper_grid", grid_with_a_broken_run)
        code = main(["experiment", "paper", "--quick", "--out", str(out)])
    return out, code


@pytest.mark.slow  # the paper's quick grid, 31 runs; fast tier: every run failed still gives
# tables and report (the paper's grid), a failed run does not lose the others, and the terrain
# and drive experiments (test_dem.py, test_drive.py) run quick grids to their reports
def test_quick_experiment_tables(quick_experiment):
    out, code = quick_experiment
    assert code == 1  # the broken run is reported through the exit status ...
    quick = paper_grid(QUICK)
    for table, columns in TABLE_COLUMNS.items():
        path = out / "tables" / f"{table}.csv"
        assert tuple(path.read_text().splitlines()[0].split(",")) == columns
        rows = read_table(path)
        metric = {"practical": "rmse", "effectiveness": "r_error"}.get(table,
                                                                        "mean_required_range")
        good = [r for r in rows if r.get("run") != BROKEN]
        assert good and all(r[metric] >= 0 for r in good), table  # NaN fails >= 0
        for row in rows:  # every row names existing run folders
            for name in str(row.get("run", row.get("runs"))).split():
                assert (out / "runs" / name).is_dir() or name == BROKEN
    sensing = read_table(out / "tables" / "sensing_range.csv")
    assert {(r["follower"], r["estimator"]) for r in sensing} == {
        (k, e) for k in (1, 2, 3) for e in ("stay", "persist", "edmd-b", "auto")}
    dictionaries = read_table(out / "tables" / "dictionaries.csv")
    assert {r["dictionary"] for r in dictionaries} == set("abcdefg") | {"stay", "persist", "broken"}
    broken = next(r for r in dictionaries if r["dictionary"] == "broken")
    assert math.isnan(broken["rmse"]) and math.isnan(broken["mean_required_range"])
    practical = read_table(out / "tables" / "practical.csv")
    assert {r["variant"] for r in practical} >= {"b", "c-lagged", "c-estimated"}
    assert {r["noise_velocity"] for r in practical} == set(QUICK.noise_velocities)
    periods = {r["comm_period"] for r in read_table(out / "tables" / "comm_period.csv")}
    assert periods == set(QUICK.comm_periods)
    index = read_table(out / "tables" / "runs.csv")
    assert len(index) == sum(map(len, quick.values())) + 1
    assert [r["run"] for r in index if r["status"] != "ok"] == [BROKEN]


@pytest.mark.slow  # the quick grid, as above
def test_quick_experiment_figures_and_report(quick_experiment):
    out, _ = quick_experiment
    figures = sorted((out / "figures").glob("*.png"))
    names = {p.stem for p in figures}
    assert names == {"effectiveness_elliptic", "sensing_range", "dictionaries_elliptic",
                     "practical", "comm_period"}
    for path in figures:
        assert_png(path)
    assert not list(out.rglob(".*.tmp"))  # atomic writes leave no temporaries
    report = (out / "report.md").read_text()
    for path in figures:
        assert f"](figures/{path.name})" in report
    assert BROKEN in report and "failed" in report  # ... and named in the report
    sensing = read_table(out / "tables" / "sensing_range.csv")
    edmd = next(r for r in sensing if r["estimator"] == "edmd-b" and r["follower"] == 1)
    assert f"{edmd['mean_required_range']:.3g}" in report  # numbers come from the tables
    assert "n/a" not in report
    assert paper_report(out / "tables") == report  # ... and from nothing else


def test_committed_report_is_what_the_committed_tables_give(tmp_path):
    """``docs/paper-report.md`` is regenerated from a copy of ``docs/tables`` alone (no run,
    no figure drawn) and compared byte for byte: the committed report and tables come from
    the same experiment, and the report depends on nothing else (not the machine, the clock,
    the runs' folders or today's defaults)."""
    shutil.copytree(ROOT / "docs" / "tables", tmp_path / "tables")
    written = write_report(tmp_path)
    assert written.read_bytes() == (ROOT / "docs" / "paper-report.md").read_bytes()
    for name in ("effectiveness", "experiment"):  # a table the report needs is named if absent
        (tmp_path / "tables" / f"{name}.csv").unlink()
    with pytest.raises(ValueError, match="no effectiveness.csv, experiment.csv"):
        paper_report(tmp_path / "tables")


@pytest.mark.slow  # the quick grid, as above; fast tier: test_options.py plots a run
def test_plot_command_on_a_run(quick_experiment, capsys):
    out, _ = quick_experiment
    run_dir = out / "runs" / "sensing_range" / "elliptic-auto"
    assert main(["plot", str(run_dir)]) == 0
    printed = capsys.readouterr().out
    for name in ("effectiveness.png", "required_range.png"):
        assert_png(run_dir / "figures" / name)
        assert name in printed
    assert main(["plot", str(out / "tables")]) == 2  # refused: not a results folder


def test_every_run_failed_still_gives_tables_and_report(tmp_path):
    """No run output at all: empty cells, figures drawn or named as missing, a report."""
    runs = [run for table in paper_grid(QUICK).values() for run in table]
    outcomes = [RunOutcome(run, None, "RuntimeError: world did not start") for run in runs]
    result = experiment.write_results(tmp_path, QUICK, outcomes, workers=1, run_time=0.0)
    assert len(result["failed"]) == len(runs)
    assert set(result["figure_problems"]) == {"effectiveness_elliptic"}  # no ticks.csv
    for path in result["figures"].values():
        assert_png(path)
    sensing = read_table(result["tables"]["sensing_range"])
    assert len(sensing) == 12 and all(math.isnan(r["rmse"]) for r in sensing)
    report = result["report"].read_text()
    assert f"**{len(runs)} run(s) failed**" in report
    assert "effectiveness_elliptic` could not be drawn" in report


def test_every_estimator_of_a_figure_gets_its_own_style():
    """The terrain figures once drew six estimators as identical black curves."""
    from swarm.plots import estimator_styles
    from swarm.terrain import TERRAIN_ESTIMATORS

    names = [*TERRAIN_ESTIMATORS, "edmd-c", "edmd-g", "tests.example_estimator:MeanStep"]
    styles = estimator_styles(names)
    assert set(styles) == set(names) and len(set(styles.values())) == len(names)


@pytest.mark.parametrize("surfaces", [  # the three-surface layout: the slow tier
    ("elliptic",), pytest.param(("elliptic", "hyperbolic", "wavy"), marks=pytest.mark.slow)])
def test_figure_legends_and_titles_lie_inside_their_figures(surfaces, tmp_path, monkeypatch):
    """Every table figure drawn from the committed tables, for one surface (as ``--quick``
    draws them) and for three: each figure's and each panel's legend and title lie inside
    the figure (the practical figure's legend and title once ran off a one-panel figure)."""
    from swarm import plots

    drawn = []
    save = plots._save
    monkeypatch.setattr(plots, "_save", lambda fig, path: drawn.append(fig) or save(fig, path))
    tables = {name: [r for r in read_table(ROOT / "docs" / "tables" / f"{name}.csv")
                     if r["surface"] in surfaces]
              for name in ("sensing_range", "dictionaries", "practical", "comm_period")}
    plots.plot_sensing_range(tables["sensing_range"], tmp_path / "s.png")
    plots.plot_dictionaries(tables["dictionaries"], surfaces[0], tmp_path / "d.png")
    plots.plot_practical(tables["practical"], tmp_path / "p.png")
    plots.plot_comm_period(tables["comm_period"], tmp_path / "c.png")
    position = [{**r, "follower": r["follower"], "comm_period": 1.28}
                for r in tables["sensing_range"] if r["surface"] == surfaces[0]]
    plots.plot_position(position, tmp_path / "pos.png")
    assert len(drawn) == 5
    for fig in drawn:
        renderer = fig.canvas.get_renderer()
        fig.canvas.draw()
        inner = fig.bbox.padded(1.0)  # a pixel of rounding
        texts = [*fig.legends, *[ax.get_legend() for ax in fig.axes if ax.get_legend()],
                 *[ax.title for ax in fig.axes if ax.get_title()]]
        texts += [fig._suptitle] if fig._suptitle is not None else []
        assert texts
        for artist in texts:
            box = artist.get_window_extent(renderer)
            assert (inner.x0 <= box.x0 and box.x1 <= inner.x1 and inner.y0 <= box.y0
                    and box.y1 <= inner.y1), (fig.get_suptitle(), artist, box, fig.bbox)
