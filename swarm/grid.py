"""Grids of runs (the types, the one runner and the table I/O) shared by ``swarm experiment``,
``swarm compare`` and ``swarm sweep``.

A :class:`GridRun` is a ``RunConfig`` with a table, a folder name and the key columns it fills;
:func:`run_grid` runs a list of them (each one :func:`swarm.launch.launch` over Zenoh, in a
local process pool or as tasks on a dask cluster) and returns one :class:`RunOutcome` per run;
runs already finished in the folder (an interrupted grid run again) are not run again, and a
dead local worker costs only the run it had. :func:`write_table` / :func:`read_table` write
and read the CSV tables.
"""
from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import multiprocessing
import os
import re
import shutil
import statistics
import tempfile
import time
from collections.abc import Iterable, Mapping
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.config import (
    DEFAULTS,
    OPTIONS,
    RunConfig,
    estimator_options,
    given_options,
    idle_reason,
    load_config,
)
from protocol.distribution import needs
from protocol.folder import LOCK_FILE, FolderLock, write_atomic
from protocol.limits import MAX_RUN_ID

RUN_ATTEMPTS = 2


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


# --- running -----------------------------------------------------------------------------------

def execute(run: GridRun, runs_dir: Path, attempts: int = RUN_ATTEMPTS,
            credentials_in: Path | None = None) -> RunOutcome:
    """Run one grid entry over Zenoh (in-process agents); a worker task of :func:`run_grid`.

    A run that raises or ends incomplete is tried again up to ``attempts`` times in all (a
    transient cause such as a port taken between choosing and binding it goes away; a
    deterministic one fails again and is reported). Each attempt's credentials go to a new
    folder in ``credentials_in`` (default: the temporary directory), removed after the
    attempt; :func:`run_grid` removes ``credentials_in`` too, so a worker killed mid-run
    leaves no password behind.
    """
    from swarm.launch import launch

    start = time.perf_counter()
    error = ""
    folder = runs_dir / run.folder
    for attempt in range(1, attempts + 1):
        try:
            _clear_unfinished(run, folder)
            with tempfile.TemporaryDirectory(prefix="swarm-credentials-",
                                             dir=credentials_in) as scratch:
                summary = launch(run.config, folder, in_process=True,
                                 credentials_dir=Path(scratch) / "run")
        except (ValueError, RuntimeError, OSError) as exc:
            error = f"{type(exc).__name__}: {exc}"
            continue
        if summary["complete"]:
            return RunOutcome(run, summary, "", attempt, time.perf_counter() - start)
        error = f"incomplete: {summary['reason']}"
    return RunOutcome(run, None, error, attempts, time.perf_counter() - start)


def finished_summary(run: GridRun, folder: Path) -> dict | None:
    """The summary of ``run`` if ``folder`` holds it complete (same run id and options), else
    None: how an interrupted grid resumes without running finished runs again."""
    try:
        summary = json.loads((folder / "summary.json").read_text())
        written = load_config(folder / "config.toml")
    except (OSError, ValueError):
        return None
    if not (isinstance(summary, dict) and summary.get("complete") is True):
        return None
    wanted = run.config.to_dict()
    if run.config.leader_start is None:  # the world writes the surface's default start
        wanted.pop("leader_start", None)
    have = written.to_dict()
    return summary if all(have.get(k) == v for k, v in wanted.items()) else None


def _clear_unfinished(run: GridRun, folder: Path) -> None:
    """Remove what an interrupted attempt of ``run`` left in its folder (the world never
    writes into a folder holding results); a folder of another run is refused."""
    if not folder.exists():
        return
    try:
        written = load_config(folder / "config.toml").run_id
    except (OSError, ValueError):
        written = None
    nothing = not {p.name for p in folder.iterdir()} - {LOCK_FILE}  # an attempt that wrote none
    if written != run.config.run_id and not nothing:
        raise ValueError(f"{folder} holds something other than run {run.config.run_id}: "
                         "remove it or choose another output folder")
    with FolderLock(folder, run.config.run_id):  # never from under a live writer
        shutil.rmtree(folder)


def run_grid(runs: list[GridRun], runs_dir: Path, workers: int | None = None,
             progress: bool = True, scheduler: str | None = None) -> list[RunOutcome]:
    """Run ``runs``; return one outcome per run, in the order of ``runs``.

    Runs whose folder already holds their complete results are not run again (their outcome
    has ``attempts`` 0), so an interrupted grid run again with the same folder resumes.

    Parameters
    ----------
    runs : list of GridRun
    runs_dir : Path
        Each run writes ``runs_dir / run.folder`` (on a cluster: a path every worker can
        write, e.g. a shared file system; the summaries come back here either way).
    workers : int, optional
        Local pool size; default ``min(2, os.cpu_count())``. Ignored with ``scheduler``.
    progress : bool
        Show a tqdm bar over completed runs (on a terminal).
    scheduler : str, optional
        Address of a dask ``distributed`` scheduler (``tcp://host:8786``): each run is one
        task, a whole run over Zenoh on the worker that takes it.

    Raises
    ------
    protocol.distribution.MissingExtra
        Before any run: a run's surface is a DEM without the ``[dem]`` extra, or
        ``scheduler`` is given without the ``[cluster]`` extra.
    """
    from tqdm import tqdm

    from world.surfaces import require_surface_extra

    for surface in {run.config.surface for run in runs}:
        require_surface_extra(surface)  # refused here, not once per run in the workers
    outcomes: dict[str, RunOutcome] = {}
    todo = []
    for run in runs:
        summary = finished_summary(run, runs_dir / run.folder)
        if summary is None:
            todo.append(run)
        else:
            outcomes[run.folder] = RunOutcome(run, summary, "", attempts=0)
    bar = tqdm(total=len(runs), initial=len(runs) - len(todo), unit="run", desc="experiment",
               disable=None if progress else True)

    def record(run: GridRun, future) -> None:
        try:
            outcome = future.result()
        except Exception as exc:  # a dead worker or an unexpected error: keep the rest
            outcome = RunOutcome(run, None, f"{type(exc).__name__}: {exc}")
        outcomes[run.folder] = outcome
        bar.update(1)
        failed = sum(not o.ok for o in outcomes.values())
        if failed:
            bar.set_postfix(failed=failed)

    with bar:
        if scheduler is not None:
            _run_on_cluster(todo, runs_dir, scheduler, record)
        elif todo:  # the runs' credentials in one folder this process removes at the end
            with tempfile.TemporaryDirectory(prefix="swarm-grid-credentials-") as scratch:
                _run_in_pool(todo, runs_dir, workers or min(2, os.cpu_count() or 1), record,
                             Path(scratch))
    return [outcomes[run.folder] for run in runs]


def _run_in_pool(runs: list[GridRun], runs_dir: Path, workers: int, record,
                 credentials_in: Path) -> None:
    """Run ``runs`` in local worker processes; ``record(run, future)`` each finished one.

    A worker that dies (killed, out of memory) breaks the whole pool: every run not finished
    then fails with ``BrokenProcessPool``. The runs that were still queued go to a new pool.
    Those that were under way (they had written their ``config.toml`` since the pool started)
    are run again one at a time, each in a worker of its own, so the one whose worker dies
    again is known: it is reported, the others are not charged for it. Ctrl-C or SIGTERM
    cancels the queued runs and ends those under way (:func:`_pool`). Each run's credentials
    go to ``credentials_in`` (see :func:`execute`).
    """
    while runs:
        started, again, suspects = time.time(), [], []
        for run, future in _pool(runs, runs_dir, workers, credentials_in):
            if not isinstance(future.exception(), BrokenProcessPool):
                record(run, future)
            elif _under_way(runs_dir / run.folder, started):
                suspects.append(run)
            else:
                again.append(run)
        for run in suspects:  # alone: a second death is its own
            for _, future in _pool([run], runs_dir, 1, credentials_in):
                if isinstance(future.exception(), BrokenProcessPool):
                    future = _failed("its worker process died (killed, or out of memory), "
                                     "twice")
                record(run, future)
        runs = again


def _pool(runs: list[GridRun], runs_dir: Path, workers: int, credentials_in: Path):
    """Yield ``(run, future)`` as each of ``runs`` finishes in a new pool of ``workers``
    processes (spawned: they start clean instead of inheriting this process's threads and
    sockets)."""
    context = multiprocessing.get_context("spawn")
    others = set(multiprocessing.active_children())  # not the pool's: never stopped here
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        futures = {pool.submit(execute, run, runs_dir, credentials_in=credentials_in): run
                   for run in runs}
        try:
            for future in as_completed(futures):
                yield futures[future], future
        except BaseException:  # Ctrl-C or SIGTERM, here or in the caller (which closes this
            # generator): cancel the queued runs while the pool is still referenced (a pool
            # collected before its manager thread sees the request would go on running them
            # all), and stop the runs under way (a rerun does them again, as after any crash)
            # instead of waiting for them, whose workers would outlive this process.
            pool.shutdown(wait=False, cancel_futures=True)
            for worker in set(multiprocessing.active_children()) - others:
                worker.terminate()
            raise


def _under_way(folder: Path, since: float) -> bool:
    """Whether a run wrote its ``config.toml`` (as its world starts) at or after ``since``."""
    try:
        return (folder / "config.toml").stat().st_mtime >= since
    except OSError:
        return False


def _failed(reason: str) -> Future:
    """A finished future whose result is a ``RuntimeError(reason)``."""
    future: Future = Future()
    future.set_exception(RuntimeError(reason))
    return future


def _run_on_cluster(runs: list[GridRun], runs_dir: Path, scheduler: str, record) -> None:
    """Submit each run as one task to the dask scheduler at ``scheduler``; ``record`` each
    finished one. Ctrl-C cancels the tasks not yet finished. How long connecting may take is
    dask's own option ``distributed.comm.timeouts.connect`` (30 s unless configured, e.g.
    ``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT=5s``)."""
    with needs("cluster"):
        from distributed import Client
        from distributed import as_completed as completed

    try:
        client = Client(scheduler)
    except (OSError, TimeoutError) as exc:
        raise RuntimeError(f"cannot reach the dask scheduler at {scheduler}: {exc}") from None
    with client:
        futures = {client.submit(execute, run, runs_dir, pure=False): run for run in runs}
        try:
            for future in completed(futures):
                record(futures[future], future)
        except KeyboardInterrupt:
            client.cancel(list(futures))
            raise


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


def number(value: Any) -> float:
    return math.nan if value is None else float(value)


def is_nan(value: Any) -> bool:
    return isinstance(value, float) and math.isnan(value)


def table_number(x: float | None, digits: int = 4) -> str:
    """``x`` for a printed table: ``digits`` decimals, or three significant digits in
    e-notation when it is too small for them (a noise-free range of 2.4e-08 is not 0.0000);
    ``-`` when missing or not finite.

    >>> table_number(0.01941), table_number(2.4e-8), table_number(0.0), table_number(None)
    ('0.0194', '2.40e-08', '0.0000', '-')
    """
    if x is None or not math.isfinite(x):
        return "-"
    if 0 < abs(x) < 10.0 ** -digits:
        return f"{x:.2e}"
    return f"{x:.{digits}f}"


# --- grids as axes -----------------------------------------------------------------------------

@dataclass(frozen=True)
class Axis:
    """One dimension of a grid: labelled option sets for ``RunConfig``.

    ``values`` pairs each label (the table cell, e.g. ``1.28`` or ``"auto"``) with the options
    it sets; ``fragment`` formats the label into the run's folder name (``"tc{:g}"``).
    """

    name: str
    values: tuple[tuple[Any, dict[str, Any]], ...]
    fragment: str = "{}"

    @classmethod
    def of_field(cls, name: str, values, fragment: str = "{}") -> Axis:
        """An axis over one ``RunConfig`` field, labelled by its values."""
        return cls(name, tuple((v, {name: v}) for v in values), fragment)


def expand(table: str, base: Mapping[str, Any], axes: list[Axis],
           labels: dict[str, Any] | None = None) -> list[GridRun]:
    """Every combination of the axes' values, in order (the last axis varies fastest).

    Each run is the options ``base`` (any run option; a ``RunConfig``'s ``to_dict()`` too)
    with the options of its values applied, ``run_id`` ``<table>-<name>``, where ``name``
    joins the axes' fragments with ``-``; its labels are ``labels`` plus one per axis. An
    option ``base`` sets that does nothing in a run (:func:`protocol.config.idle_reason`, e.g.
    a dictionary in a persist run of a ``compare``) keeps its default there. Raises
    ValueError (naming the option) for an invalid combination, for a ``base`` option that
    does nothing in any run or that an axis sets in every run, and for a value listed twice
    or two combinations sharing a folder name (each run is run once and counted once in a
    mean).
    """
    given = {k: v for k, v in base.items() if k != "run_id" and DEFAULTS.get(k, v) != v}
    combos: list[tuple[list[str], dict[str, Any], dict[str, Any]]] = [([], dict(labels or {}), {})]
    for axis in axes:
        if not axis.values:
            raise ValueError(f"axis {axis.name!r} has no values")
        seen: list[Any] = []
        for label, _ in axis.values:
            if label in seen:
                raise ValueError(f"axis {axis.name!r} lists {label!r} more than once")
            seen.append(label)
        for key in set(given).intersection(*(options for _, options in axis.values)):
            raise ValueError(f"{key} = {OPTIONS[key].show(given[key])} does nothing: axis "
                             f"{axis.name!r} sets it in every run")
        combos = [(parts + [axis.fragment.format(label)], {**lab, axis.name: label},
                   {**opts, **options})
                  for parts, lab, opts in combos for label, options in axis.values]
    runs: dict[str, GridRun] = {}  # by folder name
    used: set[str] = set()  # the base options that do something in some run
    idle_why: dict[str, str] = {}  # why a base option does nothing in a run
    for parts, lab, opts in combos:
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", "-".join(parts))
        if name in runs:
            raise ValueError(f"{runs[name].labels} and {lab} would share the run folder "
                             f"'{table}/{name}': make the labels differ in letters, digits, "
                             "'_', '.' or '-'")
        run_id = f"{table}-{name}"
        if len(run_id) > MAX_RUN_ID:  # keep the run ids unique within their limit
            run_id = f"{run_id[:MAX_RUN_ID - 13]}-{hashlib.sha1(run_id.encode()).hexdigest()[:12]}"
        options = given_options({**base, **opts, "run_id": run_id})
        values = {**DEFAULTS, **options}
        idle = {k: why for k in given.keys() - opts.keys()
                if k in OPTIONS and (why := idle_reason(k, values)) is not None}
        idle_why.update(idle)
        used |= given.keys() - idle.keys()
        config = RunConfig(**{k: v for k, v in options.items() if k not in idle})
        runs[name] = GridRun(table, name, config, lab)
    for key in given.keys() - used:
        raise ValueError(f"{key} = {OPTIONS[key].show(given[key])} does nothing in any run "
                         f"{idle_why[key]}: leave it out")
    return list(runs.values())


def estimator_axis(labels) -> Axis:
    """The ``estimator`` axis over estimator labels
    (:func:`protocol.config.estimator_options`)."""
    return Axis("estimator", tuple((label, estimator_options(label)) for label in labels))


SUMMARY_COLUMNS = ("mean_required_range", "mean_persist_range", "ratio_to_persist",
                   "mean_persist_range_noise_free", "mean_stay_range", "rmse", "fallback_ticks",
                   "estimated_ticks")


def write_tables(out_dir: Path, tables: dict[str, tuple[tuple[str, ...], list[dict]]],
                 outcomes: list[RunOutcome]) -> tuple[dict[str, Path], dict[str, list[dict]]]:
    """Write each table ``name -> (columns, rows)`` as ``out_dir/tables/<name>.csv`` and the
    run index ``runs.csv``; return the paths and the rows read back, as a report cites them."""
    paths = {name: out_dir / "tables" / f"{name}.csv" for name in tables}
    for name, (columns, rows) in tables.items():
        write_table(paths[name], columns, rows)
    write_run_index(out_dir / "tables" / "runs.csv", outcomes)
    return paths, {name: read_table(path) for name, path in paths.items()}


def follower_rows(outcomes: Iterable[RunOutcome], per_follower: bool) -> list[dict]:
    """One row per run (follower 1) or per run and follower, with the run's key columns
    (:func:`summary_row`; a failed run's metrics are NaN, so the table shows the gap)."""
    return [{**summary_row(outcome, k), **({"follower": k} if per_follower else {})}
            for outcome in outcomes
            for k in (range(1, outcome.run.config.followers + 1) if per_follower else (1,))]


def summary_row(outcome: RunOutcome, follower: int = 1) -> dict[str, Any]:
    """The run's labels and follower ``follower``'s metrics, with its required range over the
    persist baseline of the same run (same noisy readings); NaN where the run failed."""
    stats = outcome.summary["followers"][str(follower)] if outcome.ok else {}
    row = dict(outcome.run.labels)
    for column in SUMMARY_COLUMNS:
        if column != "ratio_to_persist":
            row[column] = number(stats.get(column))
    persist = row["mean_persist_range"]
    row["ratio_to_persist"] = row["mean_required_range"] / persist if persist else math.nan
    row["run"] = outcome.run.folder
    return row


def mean_over(rows: list[dict], over: str, keys: tuple[str, ...],
              columns: tuple[str, ...] = SUMMARY_COLUMNS, spread: tuple[str, ...] = (),
              skip_failed: bool = True) -> list[dict]:
    """Rows averaged over the values of column ``over`` (e.g. the seed), grouped by ``keys``.

    A run failed where its first column (``mean_required_range`` by default) is NaN. Each of
    ``columns`` is the mean of its non-NaN values over the runs that succeeded; with
    ``skip_failed`` False a failed run makes its group's means NaN instead (a gap is never
    hidden by the other runs). The ratio to persist, when among ``columns``, is the ratio of
    the means. Each column ``c`` of ``spread`` also gets ``c_std``, the sample standard
    deviation of the same values (NaN under two). ``n`` counts the runs averaged (those that
    succeeded; every run with ``skip_failed`` False); ``over`` joins every run's value.
    """
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault(tuple(row[k] for k in keys), []).append(row)
    out = []
    for key, members in groups.items():
        ok = [m for m in members if not is_nan(m[columns[0]])]
        gap = not skip_failed and len(ok) < len(members)
        row = dict(zip(keys, key))
        for column in columns:
            values = [] if gap else [m[column] for m in ok if not is_nan(m[column])]
            row[column] = math.fsum(values) / len(values) if values else math.nan
            if column in spread:
                row[f"{column}_std"] = statistics.stdev(values) if len(values) > 1 else math.nan
        if "ratio_to_persist" in columns:
            persist = row["mean_persist_range"]
            row["ratio_to_persist"] = (row["mean_required_range"] / persist
                                       if persist and not is_nan(persist) else math.nan)
        row["n"] = len(ok) if skip_failed else len(members)
        row[over] = " ".join(str(m[over]) for m in members)
        out.append(row)
    return out
