"""``python -m swarm experiment paper``: the paper's Section 4 over Zenoh, as tables, figures, report.

The grid is data: :func:`paper_grid` returns, per table, the named :class:`GridRun` s (a
``RunConfig`` plus the table columns it fills). :func:`run_grid` runs them in a process pool,
each task one :func:`swarm.launch.launch` (world as embedded router, every agent its own Zenoh
session) into ``D/runs/<table>/<name>/``; a failed run is recorded and the others go on.
:func:`run_paper_experiment` then writes ``D/tables/*.csv`` from the runs' summaries, draws
``D/figures/*.png`` (:mod:`swarm.plots`) and writes ``D/report.md``, whose numbers are read
back from the tables.

Tables (key columns first, then the metrics, then the run folders behind each row):

- ``sensing_range``: surface, follower (1–3), estimator (stay, persist, edmd-b, auto);
- ``dictionaries``: surface, dictionary a–g in the paper's idealised case (oracle velocity for
  c, GPS for d–g), plus the two baselines as rows ``stay`` and ``persist`` (SPEC §6);
- ``practical``: surface, variant (b, c-lagged, c-estimated, and the baselines), noise on the
  velocity with a fixed actuation noise, mean RMSE over the seeds;
- ``comm_period``: surface, T_c, estimator.
"""
from __future__ import annotations

import csv
import io
import math
import multiprocessing
import os
import statistics
import time
from collections import defaultdict
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.config import RunConfig, write_atomic

SURFACES = ("elliptic", "hyperbolic", "wavy")
BASELINES = {"stay": {"estimator": "stay"}, "persist": {"estimator": "persist"}}
ESTIMATORS = {**BASELINES, "edmd-b": {"estimator": "edmd", "dictionary": "b"},
              "auto": {"estimator": "auto"}}
DICTIONARIES = {
    "a": {"dictionary": "a"},
    "b": {"dictionary": "b"},
    "c": {"dictionary": "c", "velocity": "oracle"},
    **{d: {"dictionary": d, "gps": True} for d in "defg"},
}
PRACTICAL_VARIANTS = {
    "b": {"estimator": "edmd", "dictionary": "b"},
    "c-lagged": {"estimator": "edmd", "dictionary": "c", "velocity": "lagged"},
    "c-estimated": {"estimator": "edmd", "dictionary": "c", "velocity": "estimated"},
    **BASELINES,
}
TABLE_COLUMNS = {
    "sensing_range": ("surface", "follower", "estimator", "mean_required_range", "rmse", "run"),
    "dictionaries": ("surface", "dictionary", "rmse", "mean_required_range", "run"),
    "practical": ("surface", "variant", "noise_velocity", "rmse", "noise_move", "rmse_std",
                  "seeds", "runs"),
    "comm_period": ("surface", "comm_period", "estimator", "mean_required_range", "run"),
}
RUN_ATTEMPTS = 2


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


@dataclass(frozen=True)
class GridRun:
    """One run of the grid: its table, its folder name, its config and the key columns it fills."""

    table: str
    name: str
    config: RunConfig
    labels: dict[str, Any] = field(default_factory=dict)

    @property
    def folder(self) -> str:
        """Path of the run's results folder relative to ``D/runs``."""
        return f"{self.table}/{self.name}"


@dataclass(frozen=True)
class RunOutcome:
    """What a worker reports: the run, its summary (None if it failed) and the error if any."""

    run: GridRun
    summary: dict | None
    error: str = ""
    attempts: int = 1
    wall_time: float = 0.0

    @property
    def ok(self) -> bool:
        return self.summary is not None and not self.error


# --- the grid ----------------------------------------------------------------------------------

def paper_grid(spec: GridSpec = FULL) -> dict[str, list[GridRun]]:
    """Every run of the paper experiment, per table (keys of :data:`TABLE_COLUMNS`).

    Seeds are fixed (``spec.seeds``; seed 0 where a table has no seed column), so the grid is
    reproducible. Dictionary, practical and comm-period runs have one follower; the
    sensing-range runs have three.
    """
    grid: dict[str, list[GridRun]] = {table: [] for table in TABLE_COLUMNS}
    base = RunConfig(ticks=spec.ticks)

    def add(table: str, name: str, labels: dict[str, Any], **options: Any) -> None:
        run_id = f"{table}-{name}"
        grid[table].append(GridRun(table, name, base.replace(run_id=run_id, **options), labels))

    for surface in spec.surfaces:
        for est, options in ESTIMATORS.items():
            add("sensing_range", f"{surface}-{est}", {"surface": surface, "estimator": est},
                surface=surface, followers=3, **options)
        for dic, options in {**DICTIONARIES, **BASELINES}.items():
            add("dictionaries", f"{surface}-{dic}", {"surface": surface, "dictionary": dic},
                surface=surface, **options)
        for noise in spec.noise_velocities:
            for variant, options in PRACTICAL_VARIANTS.items():
                for seed in spec.seeds:
                    add("practical", f"{surface}-{variant}-nv{noise:g}-s{seed}",
                        {"surface": surface, "variant": variant, "noise_velocity": noise,
                         "noise_move": spec.noise_move},
                        surface=surface, noise_velocity=noise, noise_move=spec.noise_move,
                        seed=seed, **options)
        for period in spec.comm_periods:
            for est, options in ESTIMATORS.items():
                add("comm_period", f"{surface}-tc{period:g}-{est}",
                    {"surface": surface, "comm_period": period, "estimator": est},
                    surface=surface, comm_period=period, **options)
    return grid


# --- running -----------------------------------------------------------------------------------

def execute(run: GridRun, runs_dir: Path, attempts: int = RUN_ATTEMPTS) -> RunOutcome:
    """Run one grid entry over Zenoh (in-process agents); a worker task of :func:`run_grid`.

    A run that raises or ends incomplete is tried again up to ``attempts`` times in all (a
    transient cause such as a port taken between choosing and binding it goes away; a
    deterministic one fails again and is reported).
    """
    from swarm.launch import launch

    start = time.perf_counter()
    error = ""
    for attempt in range(1, attempts + 1):
        try:
            summary = launch(run.config, runs_dir / run.folder, in_process=True)
        except (ValueError, RuntimeError, OSError) as exc:
            error = f"{type(exc).__name__}: {exc}"
            continue
        if summary["complete"]:
            return RunOutcome(run, summary, "", attempt, time.perf_counter() - start)
        error = f"incomplete: {summary['reason']}"
    return RunOutcome(run, None, error, attempts, time.perf_counter() - start)


def run_grid(runs: list[GridRun], runs_dir: Path, workers: int | None = None,
             progress: bool = True) -> list[RunOutcome]:
    """Run ``runs`` in a process pool; return one outcome per run, in the order of ``runs``.

    Parameters
    ----------
    runs : list of GridRun
    runs_dir : Path
        Each run writes ``runs_dir / run.folder``.
    workers : int, optional
        Pool size; default ``min(2, os.cpu_count())``.
    progress : bool
        Show a tqdm bar over completed runs (on a terminal).
    """
    from tqdm import tqdm

    workers = workers or min(2, os.cpu_count() or 1)
    outcomes: dict[str, RunOutcome] = {}
    # spawn: workers start clean instead of inheriting this process's threads and sockets.
    context = multiprocessing.get_context("spawn")
    bar = tqdm(total=len(runs), unit="run", desc="experiment", disable=None if progress else True)
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool, bar:
        futures = {pool.submit(execute, run, runs_dir): run for run in runs}
        try:
            for future in as_completed(futures):
                run = futures[future]
                try:
                    outcome = future.result()
                except Exception as exc:  # a dead worker or an unexpected error: keep the rest
                    outcome = RunOutcome(run, None, f"{type(exc).__name__}: {exc}")
                outcomes[run.folder] = outcome
                bar.update(1)
                failed = sum(not o.ok for o in outcomes.values())
                if failed:
                    bar.set_postfix(failed=failed)
        except KeyboardInterrupt:
            # Cancel the queued runs while the pool is still referenced (a pool collected
            # before its manager thread sees the request would go on running them all).
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    return [outcomes[run.folder] for run in runs]


# --- tables ------------------------------------------------------------------------------------

def follower_rows(outcomes: Iterable[RunOutcome], per_follower: bool) -> list[dict]:
    """One row per run (follower 1) or per run and follower, with the run's key columns.

    A failed run still gets its rows, with NaN metrics, so the table shows the gap.
    """
    rows = []
    for outcome in outcomes:
        followers = range(1, outcome.run.config.followers + 1) if per_follower else (1,)
        for k in followers:
            stats = outcome.summary["followers"][str(k)] if outcome.ok else {}
            row = dict(outcome.run.labels)
            if per_follower:
                row["follower"] = k
            row.update(mean_required_range=_number(stats.get("mean_required_range")),
                       rmse=_number(stats.get("rmse")), run=outcome.run.folder)
            rows.append(row)
    return rows


def practical_rows(outcomes: Iterable[RunOutcome]) -> list[dict]:
    """Mean (and sample standard deviation) of follower 1's RMSE over the seeds of each cell."""
    cells: dict[tuple, list[RunOutcome]] = defaultdict(list)
    for outcome in outcomes:
        labels = outcome.run.labels
        cells[(labels["surface"], labels["variant"], labels["noise_velocity"])].append(outcome)
    rows = []
    for (surface, variant, noise), members in cells.items():
        values = [o.summary["followers"]["1"]["rmse"] for o in members if o.ok]
        rows.append({
            "surface": surface, "variant": variant, "noise_velocity": noise,
            "rmse": statistics.fmean(values) if values else math.nan,
            "noise_move": members[0].run.labels["noise_move"],
            "rmse_std": statistics.stdev(values) if len(values) > 1 else math.nan,
            "seeds": len(values), "runs": " ".join(o.run.folder for o in members),
        })
    return rows


TABLE_BUILDERS: dict[str, Callable[[list[RunOutcome]], list[dict]]] = {
    "sensing_range": lambda outcomes: follower_rows(outcomes, per_follower=True),
    "dictionaries": lambda outcomes: follower_rows(outcomes, per_follower=False),
    "practical": practical_rows,
    "comm_period": lambda outcomes: follower_rows(outcomes, per_follower=False),
}


def write_table(path: Path, columns: tuple[str, ...], rows: list[dict]) -> None:
    """Write ``rows`` as CSV with ``columns`` (NaN as an empty cell), atomically."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(["" if is_nan(row[c]) else (repr(row[c]) if isinstance(row[c], float)
                                                      else row[c]) for c in columns])
    write_atomic(path, buf.getvalue())


def read_table(path: str | Path) -> list[dict]:
    """Read a table back: numbers as int or float, empty cells as NaN, text as str."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [{key: _parse_cell(value) for key, value in raw.items()}
                for raw in csv.DictReader(fh)]


def write_run_index(path: Path, outcomes: list[RunOutcome]) -> None:
    """``runs.csv``: every run's folder, status, error, attempts and wall time."""
    rows = [{"run": o.run.folder, "status": "ok" if o.ok else "failed", "error": o.error,
             "attempts": o.attempts, "wall_time": round(o.wall_time, 3)} for o in outcomes]
    write_table(path, ("run", "status", "error", "attempts", "wall_time"), rows)


def _parse_cell(value: str) -> Any:
    if value == "":
        return math.nan
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


def is_nan(value: Any) -> bool:
    return isinstance(value, float) and math.isnan(value)


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
    jobs: dict[str, Callable[[], Path]] = {}
    for surface in surfaces:
        title = (f"{plots.SURFACE_TITLES.get(surface, surface)}: follower trajectory estimation "
                 "by data-streaming EDMD (dictionary b)")
        jobs[f"effectiveness_{surface}"] = lambda s=surface, t=title: plots.plot_effectiveness(
            effectiveness_run(out_dir, s), folder / f"effectiveness_{s}.png", title=t)
    jobs["sensing_range"] = lambda: plots.plot_sensing_range(
        tables["sensing_range"], folder / "sensing_range.png")
    for surface in surfaces:
        jobs[f"dictionaries_{surface}"] = lambda s=surface: plots.plot_dictionaries(
            tables["dictionaries"], s, folder / f"dictionaries_{s}.png")
    jobs["practical"] = lambda: plots.plot_practical(tables["practical"], folder / "practical.png")
    jobs["comm_period"] = lambda: plots.plot_comm_period(tables["comm_period"],
                                                         folder / "comm_period.png")
    drawn, problems = {}, {}
    for name, job in jobs.items():
        try:
            drawn[name] = job()
        except (ValueError, KeyError, IndexError, OSError) as exc:  # e.g. a failed run's files
            problems[name] = f"{type(exc).__name__}: {exc}"
    return drawn, problems


def effectiveness_run(out_dir: Path, surface: str) -> Path:
    """The sensing-range run whose trajectories the effectiveness figure of ``surface`` shows."""
    return out_dir / "runs" / "sensing_range" / f"{surface}-edmd-b"


# --- the whole experiment ----------------------------------------------------------------------

def run_paper_experiment(out_dir: str | Path, spec: GridSpec = FULL, workers: int | None = None,
                         progress: bool = True) -> dict:
    """Run the grid of ``spec`` into ``out_dir/runs``, then :func:`write_results`."""
    start = time.perf_counter()
    workers = workers or min(2, os.cpu_count() or 1)
    grid = paper_grid(spec)
    outcomes = run_grid([run for table in TABLE_COLUMNS for run in grid[table]],
                        Path(out_dir) / "runs", workers=workers, progress=progress)
    return write_results(out_dir, spec, outcomes, workers, time.perf_counter() - start)


def write_results(out_dir: str | Path, spec: GridSpec, outcomes: list[RunOutcome], workers: int,
                  run_time: float) -> dict:
    """Write ``tables/``, ``figures/`` and ``report.md`` in ``out_dir`` from the runs' outcomes.

    Failed runs leave empty cells, figures that cannot be drawn are named in the report, and
    the rest is written regardless.

    Returns
    -------
    dict
        ``tables`` (name -> Path), ``figures`` (name -> Path), ``figure_problems`` (name ->
        reason), ``report`` (Path), ``failed`` (list of RunOutcome), ``timing`` (seconds:
        ``runs``, ``figures``, ``total``).
    """
    start = time.perf_counter()
    out_dir = Path(out_dir)
    tables = {}
    for table, columns in TABLE_COLUMNS.items():
        tables[table] = out_dir / "tables" / f"{table}.csv"
        write_table(tables[table], columns,
                    TABLE_BUILDERS[table]([o for o in outcomes if o.run.table == table]))
    write_run_index(out_dir / "tables" / "runs.csv", outcomes)
    figures, problems = draw_figures(out_dir, {t: read_table(p) for t, p in tables.items()})
    drawn = time.perf_counter() - start
    timing = {"runs": run_time, "figures": drawn, "total": run_time + drawn}
    from swarm.report import write_report

    report = write_report(out_dir, spec, outcomes, figures, problems, timing, workers)
    return {"tables": tables, "figures": figures, "figure_problems": problems, "report": report,
            "failed": [o for o in outcomes if not o.ok], "timing": timing}
