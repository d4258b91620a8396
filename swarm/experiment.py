"""``python -m swarm experiment paper``: the paper's Section 4 over Zenoh, as tables, figures,
report.

The grid is data: :func:`paper_grid` returns, per table, the named :class:`GridRun` s (a
``RunConfig`` plus the table columns it fills), built by :func:`swarm.grid.expand` from axes as
any ``swarm sweep`` grid is. :func:`swarm.grid.run_grid` runs them in a process pool,
each task one :func:`swarm.launch.launch` (world as embedded router, every agent its own Zenoh
session) into ``D/runs/<table>/<name>/``; a failed run is recorded and the others go on.
:func:`run_paper_experiment` then writes ``D/tables/*.csv`` from the runs' summaries, draws
``D/figures/*.png`` (:mod:`swarm.plots`) and writes ``D/report.md``, whose numbers are read
back from the tables.

Tables (key columns first, then the metrics, then the run folders behind each row):

- ``sensing_range``: surface, follower (1–3), estimator (stay, persist, edmd-b, auto);
- ``dictionaries``: surface, dictionary a–g in the paper's idealised case (oracle velocity for
  c, GPS for d–g), plus the two baselines as rows ``stay`` and ``persist`` (design §6);
- ``practical``: surface, variant (b, c-lagged, c-estimated, and the baselines), noise on the
  velocity with a fixed actuation noise, mean RMSE over the seeds;
- ``comm_period``: surface, T_c, estimator;
- ``effectiveness``: surface, and what the report cites from its edmd-b run's ticks
  (:func:`effectiveness_numbers`).

With ``runs.csv``, ``figures.csv`` and ``experiment.csv`` (:mod:`swarm.report`) the tables are
all the report reads.
"""
from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.config import GPS_DICTIONARIES, RunConfig
from protocol.record import TICKS_FILE, read_ticks
from swarm.grid import (
    RUN_ATTEMPTS,
    Axis,
    GridRun,
    RunOutcome,
    execute,
    expand,
    follower_rows,
    is_nan,
    mean_over,
    read_table,
    run_grid,
    summary_row,
    write_table,
    write_tables,
)
from swarm.report import (
    FIGURE_COLUMNS,
    SETTINGS,
    write_report,
)

__all__ = ["FULL", "QUICK", "RUN_ATTEMPTS", "TABLE_COLUMNS", "GridRun", "GridSpec", "RunOutcome",
           "execute", "is_nan", "paper_grid", "practical_rows", "read_table", "run_grid",
           "run_paper_experiment", "write_results", "write_table"]

SURFACES = ("elliptic", "hyperbolic", "wavy")
BASELINES = {"stay": {"estimator": "stay"}, "persist": {"estimator": "persist"}}
ESTIMATORS = {**BASELINES, "edmd-b": {"estimator": "edmd", "dictionary": "b"},
              "auto": {"estimator": "auto"}}
DICTIONARIES = {
    "a": {"dictionary": "a"},
    "b": {"dictionary": "b"},
    "c": {"dictionary": "c", "velocity": "oracle"},
    **{d: {"dictionary": d, "gps": True} for d in GPS_DICTIONARIES},
}
PRACTICAL_VARIANTS = {
    "b": {"estimator": "edmd", "dictionary": "b"},
    "c-lagged": {"estimator": "edmd", "dictionary": "c", "velocity": "lagged"},
    "c-estimated": {"estimator": "edmd", "dictionary": "c", "velocity": "estimated"},
    **BASELINES,
}

EFFECTIVENESS_NUMBERS = ("r_error", "r_follower", "theta_error", "theta_follower",
                         "theta_tick", "turn", "turn_tick")
"""What :func:`effectiveness_numbers` returns, the columns of ``effectiveness.csv``."""

TABLE_COLUMNS = {
    "sensing_range": ("surface", "follower", "estimator", "mean_required_range", "rmse", "run"),
    "dictionaries": ("surface", "dictionary", "rmse", "mean_required_range", "run"),
    "practical": ("surface", "variant", "noise_velocity", "rmse", "noise_move", "rmse_std",
                  "seeds", "runs"),
    "comm_period": ("surface", "comm_period", "estimator", "mean_required_range", "run"),
    "effectiveness": ("surface", *EFFECTIVENESS_NUMBERS, "run"),
}

@dataclass(frozen=True)
class GridSpec:
    """The sizes of the paper grid; :data:`FULL` is the experiment, :data:`QUICK` the test's."""

    surfaces: tuple[str, ...] = SURFACES
    ticks: int = 40
    comm_periods: tuple[float, ...] = (0.08, 0.16, 0.32, 0.64, 1.28, 2.56, 5.12, 10.24)
    noise_velocities: tuple[float, ...] = (0.0, 0.01, 0.05, 0.1)
    noise_move: float = 0.01
    seeds: tuple[int, ...] = (0, 1, 2)


FULL = GridSpec()
QUICK = GridSpec(surfaces=("elliptic",), ticks=10, comm_periods=(0.64, 1.28),
                 noise_velocities=(0.0, 0.05), seeds=(0,))


# --- the grid ----------------------------------------------------------------------------------

def grid_base(spec: GridSpec) -> dict:
    """The options every run of the grid starts from (the report cites their settings)."""
    return {"ticks": spec.ticks}


def paper_grid(spec: GridSpec = FULL) -> dict[str, list[GridRun]]:
    """Every run of the paper experiment, per table (keys of :data:`TABLE_COLUMNS`).

    Seeds are fixed (``spec.seeds``; seed 0 where a table has no seed column), so the grid is
    reproducible. Dictionary, practical and comm-period runs have one follower; the
    sensing-range runs have three.
    """
    base = grid_base(spec)
    surface = Axis.of_field("surface", spec.surfaces)
    estimator = Axis("estimator", tuple(ESTIMATORS.items()))
    return {
        "sensing_range": expand("sensing_range", {**base, "followers": 3}, [surface, estimator]),
        "dictionaries": expand("dictionaries", base, [surface, Axis(
            "dictionary", tuple({**DICTIONARIES, **BASELINES}.items()))]),
        "practical": expand("practical", {**base, "noise_move": spec.noise_move}, [
            surface, Axis("variant", tuple(PRACTICAL_VARIANTS.items())),
            Axis.of_field("noise_velocity", spec.noise_velocities, "nv{:g}"),
            Axis.of_field("seed", spec.seeds, "s{}")], {"noise_move": spec.noise_move}),
        "comm_period": expand("comm_period", base, [
            surface, Axis.of_field("comm_period", spec.comm_periods, "tc{:g}"), estimator]),
    }


# --- tables ------------------------------------------------------------------------------------

def practical_rows(outcomes: Iterable[RunOutcome]) -> list[dict]:
    """Mean (and sample standard deviation) of follower 1's RMSE over the seeds of each cell
    (:func:`swarm.grid.mean_over`); ``seeds`` counts the runs that succeeded, ``runs`` names
    them all."""
    means = mean_over([summary_row(o) for o in outcomes], "run",
                      ("surface", "variant", "noise_velocity", "noise_move"),
                      columns=("rmse",), spread=("rmse",))
    return [{**row, "seeds": row["n"], "runs": row["run"]} for row in means]


def effectiveness_numbers(run_dir: Path, followers: Iterable[int]) -> dict[str, float]:
    """What the effectiveness paragraph cites from one run's ``ticks.csv``
    (:data:`EFFECTIVENESS_NUMBERS`): the largest error of the predicted distance to the leader
    (``r_error``, of follower ``r_follower``) and of the predicted bearing (``theta_error`` in
    degrees, follower ``theta_follower`` at ``theta_tick``) over ``followers``, and the fastest
    change of a measured bearing (``turn`` degrees per tick, at ``turn_tick``)."""
    from swarm.plots import leader_relative

    ticks = read_ticks(run_dir / TICKS_FILE)
    worst = {"r": (0.0, 0, 0), "theta": (0.0, 0, 0)}  # error, follower, tick
    turn = (0.0, 0)  # fastest bearing change per tick, at which tick
    for k in followers:
        rel = leader_relative(ticks, k)
        seen = ~np.isnan(rel["r_est"])
        for key, scale in (("r", 1.0), ("theta", 180 / math.pi)):
            err = np.abs(rel[f"{key}_est"] - rel[f"{key}_ideal"])[seen] * scale
            i = int(np.argmax(err))
            if err[i] > worst[key][0]:
                worst[key] = (float(err[i]), k, int(rel["tick"][seen][i]))
        steps = np.degrees(np.abs(np.diff(rel["theta_ideal"])))
        if steps.max() > turn[0]:
            turn = (float(steps.max()), int(rel["tick"][int(np.argmax(steps)) + 1]))
    (err_r, k_r, _), (err_t, k_t, tick_t) = worst["r"], worst["theta"]
    return dict(zip(EFFECTIVENESS_NUMBERS, (err_r, k_r, err_t, k_t, tick_t, *turn), strict=True))


def effectiveness_rows(outcomes: Iterable[RunOutcome], runs_dir: Path) -> list[dict]:
    """Per surface, what the report cites from the ticks of its edmd-b sensing-range run
    (the run the effectiveness figure draws); NaN where that run failed."""
    rows = []
    for outcome in outcomes:
        if outcome.run.labels["estimator"] != "edmd-b":
            continue
        surface = outcome.run.labels["surface"]
        numbers = (effectiveness_numbers(runs_dir / outcome.run.folder,
                                         range(1, outcome.run.config.followers + 1))
                   if outcome.ok else dict.fromkeys(EFFECTIVENESS_NUMBERS, math.nan))
        rows.append({"surface": surface, **numbers, "run": outcome.run.folder})
    return rows


TABLE_BUILDERS: dict[str, Callable[[list[RunOutcome], Path], list[dict]]] = {
    "sensing_range": lambda outcomes, _: follower_rows(outcomes, per_follower=True),
    "dictionaries": lambda outcomes, _: follower_rows(outcomes, per_follower=False),
    "practical": lambda outcomes, _: practical_rows(outcomes),
    "comm_period": lambda outcomes, _: follower_rows(outcomes, per_follower=False),
    "effectiveness": effectiveness_rows,
}
"""Table name -> its rows from the outcomes of its runs and the folder they ran in."""
TABLE_RUNS = {table: table for table in TABLE_COLUMNS} | {"effectiveness": "sensing_range"}
"""Table name -> the grid table whose runs it is built from."""


# --- figures and report ------------------------------------------------------------------------

def draw_figures(out_dir: Path, tables: dict[str, list[dict]]
                 ) -> tuple[dict[str, Path], dict[str, str]]:
    """Draw every experiment figure from the tables (and the edmd-b runs' ticks) into
    ``out_dir/figures``.

    Returns
    -------
    drawn : dict of str to Path
        Figure name -> PNG path.
    problems : dict of str to str
        Figure name -> why it could not be drawn (its run failed, or nothing to draw); the
        other figures are drawn regardless.
    """
    from swarm import plots

    folder = out_dir / "figures"
    surfaces = list(dict.fromkeys(r["surface"] for r in tables["sensing_range"]))
    runs = {r["surface"]: out_dir / "runs" / r["run"] for r in tables["effectiveness"]}
    jobs: dict[str, Callable[[], Path]] = {}
    for surface in surfaces:
        title = (f"{plots.SURFACE_TITLES.get(surface, surface)}: follower trajectory estimation "
                 "by data-streaming EDMD (dictionary b)")
        jobs[f"effectiveness_{surface}"] = lambda s=surface, t=title: plots.plot_effectiveness(
            runs[s], folder / f"effectiveness_{s}.png", title=t)
    jobs["sensing_range"] = lambda: plots.plot_sensing_range(
        tables["sensing_range"], folder / "sensing_range.png")
    for surface in surfaces:
        jobs[f"dictionaries_{surface}"] = lambda s=surface: plots.plot_dictionaries(
            tables["dictionaries"], s, folder / f"dictionaries_{s}.png")
    jobs["practical"] = lambda: plots.plot_practical(tables["practical"], folder / "practical.png")
    jobs["comm_period"] = lambda: plots.plot_comm_period(tables["comm_period"],
                                                         folder / "comm_period.png")
    return draw_jobs(jobs)


def draw_jobs(jobs: dict[str, Callable[[], Path]]) -> tuple[dict[str, Path], dict[str, str]]:
    """Draw every figure it can: (paths by name, why each of the others was not drawn)."""
    drawn, problems = {}, {}
    for name, job in jobs.items():
        try:
            drawn[name] = job()
        except (ValueError, KeyError, IndexError, OSError) as exc:  # e.g. a failed run's files
            problems[name] = f"{type(exc).__name__}: {exc}"
    return drawn, problems


# --- the whole experiment ----------------------------------------------------------------------

def run_paper_experiment(out_dir: str | Path, spec: GridSpec = FULL, workers: int | None = None,
                         progress: bool = True, scheduler: str | None = None) -> dict:
    """Run the grid of ``spec`` into ``out_dir/runs`` (on the dask scheduler at ``scheduler``
    if given; runs already finished there are kept), then :func:`write_results`."""
    start = time.perf_counter()
    workers = workers or min(2, os.cpu_count() or 1)
    grid = paper_grid(spec)
    outcomes = run_grid([run for table in grid.values() for run in table],
                        Path(out_dir) / "runs", workers=workers, progress=progress,
                        scheduler=scheduler)
    return write_results(out_dir, spec, outcomes, workers, time.perf_counter() - start)


def write_results(out_dir: str | Path, spec: GridSpec, outcomes: list[RunOutcome], workers: int,
                  run_time: float) -> dict:
    """Write ``tables/``, ``figures/`` and ``report.md`` in ``out_dir`` from the runs' outcomes.

    Failed runs leave empty cells, figures that cannot be drawn are named in the report, and
    the rest is written regardless. ``tables/experiment.csv`` keeps the grid's settings,
    ``workers``, the machine's CPU count and the wall times (``run_time`` seconds for the
    runs), ``tables/figures.csv`` each figure's file or problem: the report is written from
    the tables alone.

    Returns
    -------
    dict
        ``tables`` (name -> Path), ``figures`` (name -> Path), ``figure_problems`` (name ->
        reason), ``report`` (Path), ``failed`` (list of RunOutcome), ``timing`` (seconds:
        ``runs``, ``figures``, ``total``).
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    runs_dir = out_dir / "runs"
    tables, rows = write_tables(out_dir, {
        table: (columns, TABLE_BUILDERS[table](
            [o for o in outcomes if o.run.table == TABLE_RUNS[table]], runs_dir))
        for table, columns in TABLE_COLUMNS.items()}, outcomes)
    figures, problems = draw_figures(out_dir, rows)
    drawn = time.perf_counter() - start
    timing = {"runs": run_time, "figures": drawn, "total": run_time + drawn}
    tables["figures"] = out_dir / "tables" / "figures.csv"
    write_table(tables["figures"], FIGURE_COLUMNS, [
        {"figure": name, "file": figures[name].relative_to(out_dir).as_posix()
         if name in figures else math.nan, "problem": problems.get(name, math.nan)}
        for name in [*figures, *problems]])
    base = RunConfig(**grid_base(spec))
    tables["experiment"] = out_dir / "tables" / "experiment.csv"
    write_table(tables["experiment"], SETTINGS, [{
        "ticks": base.ticks, "init_ticks": base.init_ticks, "spacing": base.spacing,
        "comm_period": base.comm_period, "workers": workers, "cpus": os.cpu_count() or 1,
        "run_time": run_time, "figure_time": drawn}])
    report = write_report(out_dir)
    return {"tables": tables, "figures": figures, "figure_problems": problems, "report": report,
            "failed": [o for o in outcomes if not o.ok], "timing": timing}
