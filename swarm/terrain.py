"""Real terrain: ``python -m swarm experiment terrain --dem PATH`` and the DEM helpers it needs.

The experiment runs the column over a DEM (:mod:`world.dem`) through the paper experiment's
grid runner (:func:`swarm.experiment.run_grid`: every run over Zenoh, world as embedded
router) and writes, into ``D``:

- ``tables/terrain_comm_period.csv``: follower 1's mean required sensing range per comm period
  and estimator;
- ``tables/terrain_position.csv``: the same per position in the column (followers 1 … N) at
  the comm periods of :attr:`TerrainSpec.position_periods`;
- ``tables/runs.csv``; ``figures/terrain_comm_period.png``, ``figures/terrain_position.png``,
  ``figures/terrain_trajectories.png`` (the column over the hillshaded relief); ``report.md``,
  whose numbers are read back from the tables.

Estimators are names in :data:`TERRAIN_ESTIMATORS` (``edmd-b`` is the paper's EDMD with
dictionary b; any other name is passed as ``--estimator``), so adding one is one line.

``python -m swarm dem-from-npz OUT.tif`` writes matplotlib's sample DEM (USGS, Jacksboro
fault, Tennessee; public domain) as a GeoTIFF, the DEM of the committed study.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from protocol.config import RunConfig, write_atomic
from swarm.experiment import (GridRun, RunOutcome, is_nan, read_table, run_grid, write_run_index,
                              write_table)

TERRAIN_ESTIMATORS = ("stay", "persist", "edmd-b", "auto")
"""Estimators the terrain study compares (add classical baselines here by name)."""
COMM_PERIOD_COLUMNS = ("comm_period", "estimator", "mean_required_range", "rmse", "run")
POSITION_COLUMNS = ("comm_period", "follower", "estimator", "mean_required_range", "rmse", "run")
JACKSBORO = "jacksboro_fault_dem.npz"
JACKSBORO_START = (15_000.0, 9_000.0, 0.0, 8.0)
"""A leader start on the Jacksboro DEM (m, m/s): heading north across the fault's ridges."""


@dataclass(frozen=True)
class TerrainSpec:
    """Sizes of the terrain study. Lengths in metres, times in seconds.

    ``leader_start`` (x, y, vx, vy) is required: a DEM has no preset start.
    """

    leader_start: tuple[float, float, float, float]
    estimators: tuple[str, ...] = TERRAIN_ESTIMATORS
    comm_periods: tuple[float, ...] = (0.32, 0.64, 1.28, 2.56, 5.12)
    position_periods: tuple[float, ...] = (1.28, 5.12)
    followers: int = 10
    spacing: float = 40.0
    ticks: int = 40
    smoothing: float = 0.0

    def __post_init__(self) -> None:
        start = tuple(float(v) for v in self.leader_start)
        if len(start) != 4 or not all(math.isfinite(v) for v in start):
            raise ValueError(f"leader_start must be four finite numbers X,Y,VX,VY, got "
                             f"{self.leader_start!r}")
        object.__setattr__(self, "leader_start", start)
        if not self.estimators:
            raise ValueError("estimators must name at least one estimator")
        if not self.comm_periods:
            raise ValueError("comm_periods must hold at least one comm period")
        missing = sorted(set(self.position_periods) - set(self.comm_periods))
        if missing:
            raise ValueError(f"position_periods {missing} must be among comm_periods")


QUICK_TICKS, QUICK_FOLLOWERS = 8, 2


def quick(spec: TerrainSpec) -> TerrainSpec:
    """A reduced study to check the pipeline: two comm periods, 2 followers, 8 ticks."""
    periods = spec.comm_periods[:2]
    return TerrainSpec(spec.leader_start, spec.estimators, periods, periods[:1],
                       QUICK_FOLLOWERS, spec.spacing, QUICK_TICKS, spec.smoothing)


def estimator_options(name: str) -> dict[str, Any]:
    """RunConfig options of a study estimator name (``edmd-b``: EDMD, dictionary b)."""
    if name == "edmd-b":
        return {"estimator": "edmd", "dictionary": "b"}
    return {"estimator": name}


def terrain_grid(dem: str | Path, spec: TerrainSpec) -> list[GridRun]:
    """One run per comm period and estimator, each with ``spec.followers`` followers.

    Follower 1 of every run gives the comm-period table; every follower of the runs at
    ``spec.position_periods`` gives the position table (follower ``k`` depends only on the
    agents ahead of it, so one run serves both).
    """
    base = RunConfig(surface=f"dem:{Path(dem).resolve()}", leader_start=spec.leader_start,
                     followers=spec.followers, spacing=spec.spacing, ticks=spec.ticks,
                     surface_params={"smoothing": spec.smoothing} if spec.smoothing else {})
    runs = []
    for period in spec.comm_periods:
        for name in spec.estimators:
            run_name = f"tc{period:g}-{name}"
            runs.append(GridRun("terrain", run_name,
                                base.replace(run_id=f"terrain-{run_name}", comm_period=period,
                                             **estimator_options(name)),
                                {"comm_period": period, "estimator": name}))
    return runs


def table_rows(outcomes: list[RunOutcome], followers: range) -> list[dict]:
    """Rows per run and follower in ``followers`` (NaN metrics for a failed run)."""
    rows = []
    for outcome in outcomes:
        for k in followers:
            stats = outcome.summary["followers"][str(k)] if outcome.ok else {}
            rows.append({**outcome.run.labels, "follower": k,
                         "mean_required_range": _number(stats.get("mean_required_range")),
                         "rmse": _number(stats.get("rmse")), "run": outcome.run.folder})
    return rows


def run_terrain_experiment(dem: str | Path, out_dir: str | Path, spec: TerrainSpec,
                           workers: int | None = None, progress: bool = True) -> dict:
    """Run the terrain study of ``spec`` on ``dem`` into ``out_dir`` (see the module docstring).

    Raises ValueError before any run if the DEM cannot be used or the leader start is not on
    it. Returns ``tables``, ``figures``, ``figure_problems``, ``report``, ``failed`` and
    ``wall_time`` (s), like :func:`swarm.experiment.run_paper_experiment`.
    """
    from world.main import resolve_with_surface
    from world.sim import WorldSim

    out_dir = Path(out_dir)
    runs = terrain_grid(dem, spec)
    config, surface = resolve_with_surface(runs[0].config)
    WorldSim(config, surface)  # a bad leader start fails here, once, with the DEM's extent
    start = time.perf_counter()
    outcomes = run_grid(runs, out_dir / "runs", workers=workers, progress=progress)
    wall_time = time.perf_counter() - start
    tables = {"terrain_comm_period": out_dir / "tables" / "terrain_comm_period.csv",
              "terrain_position": out_dir / "tables" / "terrain_position.csv"}
    write_table(tables["terrain_comm_period"], COMM_PERIOD_COLUMNS,
                table_rows(outcomes, range(1, 2)))
    write_table(tables["terrain_position"], POSITION_COLUMNS,
                table_rows([o for o in outcomes
                            if o.run.labels["comm_period"] in spec.position_periods],
                           range(1, spec.followers + 1)))
    write_run_index(out_dir / "tables" / "runs.csv", outcomes)
    figures, problems = draw_terrain_figures(out_dir, dem, spec, tables)
    report = write_terrain_report(out_dir, dem, spec, tables, figures, problems, outcomes,
                                  wall_time)
    return {"tables": tables, "figures": figures, "figure_problems": problems, "report": report,
            "failed": [o for o in outcomes if not o.ok], "wall_time": wall_time}


def trajectory_run(out_dir: Path, spec: TerrainSpec) -> Path:
    """The run whose column the trajectory figure shows: EDMD-b (else the first estimator)
    at the first position comm period."""
    name = "edmd-b" if "edmd-b" in spec.estimators else spec.estimators[0]
    period = (spec.position_periods or spec.comm_periods)[0]
    return out_dir / "runs" / "terrain" / f"tc{period:g}-{name}"


def draw_terrain_figures(out_dir: Path, dem: str | Path, spec: TerrainSpec,
                         tables: dict[str, Path]) -> tuple[dict[str, Path], dict[str, str]]:
    """The study's three figures; a figure that cannot be drawn is named with the reason."""
    from swarm import plots

    folder = out_dir / "figures"
    comm_rows = [{**r, "surface": f"DEM {Path(dem).name}, follower 1"}
                 for r in read_table(tables["terrain_comm_period"])]
    position_rows = read_table(tables["terrain_position"])
    jobs = {
        "terrain_trajectories": lambda: plots.plot_effectiveness(
            trajectory_run(out_dir, spec), folder / "terrain_trajectories.png",
            title="Column over real terrain (hillshade and contour lines of the DEM)"),
        "terrain_comm_period": lambda: plots.plot_comm_period(
            comm_rows, folder / "terrain_comm_period.png"),
        "terrain_position": lambda: plots.plot_position(
            position_rows, folder / "terrain_position.png"),
    }
    drawn, problems = {}, {}
    for name, job in jobs.items():
        try:
            drawn[name] = job()
        except (ValueError, KeyError, IndexError, OSError) as exc:  # e.g. a failed run's files
            problems[name] = f"{type(exc).__name__}: {exc}"
    return drawn, problems


def _best(rows: list[dict], **keys: Any) -> tuple[str, float]:
    mine = [r for r in rows if all(r[k] == v for k, v in keys.items())
            and not is_nan(r["mean_required_range"])]
    if not mine:
        return "n/a", math.nan
    row = min(mine, key=lambda r: r["mean_required_range"])
    return row["estimator"], row["mean_required_range"]


def _cell(rows: list[dict], **keys: Any) -> float:
    return next((r["mean_required_range"] for r in rows
                 if all(r[k] == v for k, v in keys.items())), math.nan)


def _fmt(x: float) -> str:
    return "n/a" if is_nan(x) else f"{x:.3g}"


def write_terrain_report(out_dir: Path, dem: str | Path, spec: TerrainSpec,
                         tables: dict[str, Path], figures: dict[str, Path],
                         problems: dict[str, str], outcomes: list[RunOutcome],
                         wall_time: float) -> Path:
    """``out_dir/report.md``: the figures, the tables as markdown and what they show."""
    comm = read_table(tables["terrain_comm_period"])
    position = read_table(tables["terrain_position"])
    names = list(spec.estimators)
    lines = [
        "# Formation keeping on real terrain", "",
        f"DEM `{Path(dem).name}`; leader start (x, y, vx, vy) = {spec.leader_start} (m, m/s); "
        f"rod length {spec.spacing:g} m; {spec.ticks} ticks (4 initial); "
        f"{spec.followers} followers; smoothing {spec.smoothing:g}. {len(outcomes)} runs over "
        f"Zenoh in {wall_time:.0f} s. Numbers: mean required sensing range (m), read from "
        "`tables/`.", "",
    ]
    if "terrain_trajectories" in figures:
        lines += ["![trajectories](figures/terrain_trajectories.png)", "",
                  "The leader's path and the followers' ideal (red) and estimated (blue) "
                  "positions over the hillshaded DEM with contour lines (EDMD-b).", ""]
    lines += ["## Against the comm period (follower 1)", ""]
    if "terrain_comm_period" in figures:
        lines += ["![comm period](figures/terrain_comm_period.png)", ""]
    lines += ["| T_c (s) | " + " | ".join(names) + " | best |",
              "| --- " * (len(names) + 2) + "|"]
    for period in spec.comm_periods:
        best, _ = _best(comm, comm_period=period)
        lines.append(f"| {period:g} | " + " | ".join(
            _fmt(_cell(comm, comm_period=period, estimator=n)) for n in names) + f" | {best} |")
    lines.append("")
    for period in spec.position_periods:
        lines += [f"## Along the column at T_c = {period:g} s", ""]
        lines += ["| follower | " + " | ".join(names) + " | best |",
                  "| --- " * (len(names) + 2) + "|"]
        for k in range(1, spec.followers + 1):
            best, _ = _best(position, comm_period=period, follower=k)
            lines.append(f"| {k} | " + " | ".join(
                _fmt(_cell(position, comm_period=period, follower=k, estimator=n))
                for n in names) + f" | {best} |")
        lines.append("")
    if "terrain_position" in figures:
        lines += ["![position](figures/terrain_position.png)", ""]
    lines += _findings(comm, position, spec)
    failed = [o for o in outcomes if not o.ok]
    if failed or problems:
        lines += ["## Problems", ""]
        lines += [f"- run `{o.run.folder}` failed: {o.error}" for o in failed]
        lines += [f"- figure `{name}` not drawn: {why}" for name, why in problems.items()]
        lines.append("")
    path = out_dir / "report.md"
    write_atomic(path, "\n".join(lines))
    return path


def _findings(comm: list[dict], position: list[dict], spec: TerrainSpec) -> list[str]:
    """Sentences computed from the tables: who wins where, and how the error grows down the
    column."""
    out = ["## What the numbers say", ""]
    wins = {}
    for period in spec.comm_periods:
        best, _ = _best(comm, comm_period=period)
        wins[best] = wins.get(best, 0) + 1
    out.append("- Lowest required range for follower 1: " + ", ".join(
        f"{name} at {count} of {len(spec.comm_periods)} comm periods"
        for name, count in sorted(wins.items(), key=lambda kv: -kv[1])) + ".")
    if {"edmd-b", "persist"} <= set(spec.estimators):
        ratios = [(_cell(comm, comm_period=p, estimator="edmd-b")
                   / _cell(comm, comm_period=p, estimator="persist")) for p in spec.comm_periods]
        out.append("- EDMD-b / persist (follower 1) per comm period: " + ", ".join(
            f"{p:g} s: {_fmt(r)}" for p, r in zip(spec.comm_periods, ratios))
            + " (below 1: the paper's estimator beats assuming a constant relative position).")
    for period in spec.position_periods:
        growth = []
        for name in spec.estimators:
            first = _cell(position, comm_period=period, follower=1, estimator=name)
            last = _cell(position, comm_period=period, follower=spec.followers, estimator=name)
            growth.append(f"{name} {_fmt(first)} → {_fmt(last)}")
        winners = {}
        for k in range(1, spec.followers + 1):
            best, _ = _best(position, comm_period=period, follower=k)
            winners[best] = winners.get(best, 0) + 1
        out.append(f"- At T_c = {period:g} s, follower 1 → follower {spec.followers}: "
                   + "; ".join(growth) + ". Best per position: " + ", ".join(
                       f"{n} {c}/{spec.followers}" for n, c in winners.items()) + ".")
    out.append("")
    return out


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


# --- DEM files ---------------------------------------------------------------------------------

def write_geotiff(path: str | Path, heights: np.ndarray, *, west: float, south: float,
                  cell_x: float, cell_y: float, crs: str | None) -> Path:
    """Write ``heights`` (shape (rows, cols), **south row first**) as a one-band GeoTIFF.

    Parameters
    ----------
    west, south : float
        Outer edges of the grid in the CRS's units.
    cell_x, cell_y : float
        Cell size (> 0) in the CRS's units.
    crs : str or None
        E.g. ``"EPSG:4326"``; None writes no CRS.
    """
    import rasterio
    from rasterio.transform import Affine

    z = np.asarray(heights)
    if z.ndim != 2:
        raise ValueError(f"heights must be 2-D (rows, cols), got shape {z.shape}")
    if not (cell_x > 0 and cell_y > 0):
        raise ValueError(f"cell_x and cell_y must be > 0, got {cell_x!r}, {cell_y!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    north = south + cell_y * z.shape[0]
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                       dtype=z.dtype, crs=crs,
                       transform=Affine(cell_x, 0.0, west, 0.0, -cell_y, north)) as dst:
        dst.write(z[::-1], 1)
    return path


def dem_from_npz(out: str | Path, npz: str | Path | None = None) -> Path:
    """Write matplotlib's Jacksboro sample DEM (or ``npz`` in the same layout) as a GeoTIFF.

    The archive holds ``elevation`` (rows, cols; north row first; metres) and the grid's outer
    edges in degrees (``xmin``, ``xmax``; ``ymin`` is its **northern** edge, ``ymax`` the
    southern one) with cell sizes ``dx``, ``dy``; the GeoTIFF is EPSG:4326.
    """
    import matplotlib.cbook

    data = (np.load(npz) if npz is not None
            else matplotlib.cbook.get_sample_data(JACKSBORO))
    elevation = np.asarray(data["elevation"])
    north, south = max(data["ymin"], data["ymax"]), min(data["ymin"], data["ymax"])
    rows, cols = elevation.shape
    if not (math.isclose(north - south, rows * data["dy"], rel_tol=1e-6)
            and math.isclose(data["xmax"] - data["xmin"], cols * data["dx"], rel_tol=1e-6)):
        raise ValueError("npz: the grid's edges do not match its size and cell size")
    return write_geotiff(out, elevation[::-1], west=float(data["xmin"]), south=float(south),
                         cell_x=float(data["dx"]), cell_y=float(data["dy"]), crs="EPSG:4326")
