"""Real terrain: ``python -m swarm experiment terrain --dem PATH`` and the DEM helpers it needs.

The experiment runs the column over a DEM (:mod:`world.dem`) through the paper experiment's
grid runner (:func:`swarm.grid.run_grid`: every run over Zenoh, world as embedded
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
``python -m swarm dem-crop IN OUT.tif`` (:func:`crop_dem`) keeps a rectangle of a DEM without
no-data nodes, which ``dem:`` refuses (design §3).
"""
from __future__ import annotations

import math
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np

from protocol.config import AUTO, CLASSICAL, OWN_MOTION
from protocol.distribution import needs
from protocol.folder import write_atomic
from swarm.experiment import draw_jobs
from swarm.grid import (
    Axis,
    GridRun,
    RunOutcome,
    estimator_axis,
    expand,
    follower_rows,
    is_nan,
    mean_over,
    run_grid,
    write_tables,
)

TERRAIN_ESTIMATORS = ("stay", "persist", "edmd-b", *CLASSICAL, *OWN_MOTION, *AUTO)
"""Estimators the terrain study compares (add classical baselines here by name)."""
COMM_PERIOD_COLUMNS = ("start", "comm_period", "estimator", "mean_required_range", "rmse", "run")
POSITION_COLUMNS = ("start", "comm_period", "follower", "estimator", "mean_required_range",
                    "rmse", "run")
JACKSBORO = "jacksboro_fault_dem.npz"
Start = tuple[float, float, float, float]


@dataclass(frozen=True)
class TerrainSpec:
    """Sizes of the terrain study. Lengths in metres, times in seconds.

    ``leader_starts``, one or more (x, y, vx, vy), are required: a DEM has no preset start.
    Every start runs the whole grid; tables keep each start, figures and the report average
    over them.
    """

    leader_starts: tuple[Start, ...]
    estimators: tuple[str, ...] = TERRAIN_ESTIMATORS
    comm_periods: tuple[float, ...] = (0.32, 0.64, 1.28, 2.56, 5.12)
    position_periods: tuple[float, ...] = (1.28, 5.12)
    followers: int = 10
    spacing: float = 40.0
    ticks: int = 40
    smoothing: float = 0.0

    def __post_init__(self) -> None:
        starts = []
        for start in self.leader_starts:
            values = tuple(float(v) for v in start)
            if len(values) != 4 or not all(math.isfinite(v) for v in values):
                raise ValueError(f"leader_starts must hold four finite numbers X,Y,VX,VY each, "
                                 f"got {start!r}")
            starts.append(values)
        if not starts:
            raise ValueError("leader_starts must hold at least one start: a DEM has no preset "
                             "leader start")
        object.__setattr__(self, "leader_starts", tuple(starts))
        if not self.estimators:
            raise ValueError("estimators must name at least one estimator")
        if not self.comm_periods:
            raise ValueError("comm_periods must hold at least one comm period")
        missing = sorted(set(self.position_periods) - set(self.comm_periods))
        if missing:
            raise ValueError(f"position_periods {missing} must be among comm_periods")


QUICK_TICKS, QUICK_FOLLOWERS = 8, 2


def quick(spec: TerrainSpec) -> TerrainSpec:
    """A reduced study to check the pipeline: the first start, two comm periods, 2 followers,
    8 ticks."""
    periods = spec.comm_periods[:2]
    return TerrainSpec(spec.leader_starts[:1], spec.estimators, periods, periods[:1],
                       QUICK_FOLLOWERS, spec.spacing, QUICK_TICKS, spec.smoothing)


def terrain_grid(dem: str | Path, spec: TerrainSpec) -> list[GridRun]:
    """One run per leader start, comm period and estimator, each with ``spec.followers``
    followers.

    Follower 1 of every run gives the comm-period table; every follower of the runs at
    ``spec.position_periods`` gives the position table (follower ``k`` depends only on the
    agents ahead of it, so one run serves both).
    """
    base = {"surface": f"dem:{Path(dem).resolve()}", "followers": spec.followers,
            "spacing": spec.spacing, "ticks": spec.ticks,
            "surface_params": {"smoothing": spec.smoothing} if spec.smoothing else {}}
    starts = Axis("start",
                  tuple((i, {"leader_start": s}) for i, s in enumerate(spec.leader_starts)),
                  "start{}")
    return expand("terrain", base, [starts, Axis.of_field("comm_period", spec.comm_periods,
                                                          "tc{:g}"),
                                    estimator_axis(spec.estimators)])


def mean_over_starts(rows: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """One row per value of ``keys`` with ``mean_required_range`` averaged over the starts
    (NaN if any start's run failed, so a gap is never hidden by the other starts)."""
    return [{**{k: row[k] for k in keys}, "starts": row["n"],
             "mean_required_range": row["mean_required_range"]}
            for row in mean_over(rows, "start", keys, columns=("mean_required_range",),
                                 skip_failed=False)]


def _validate_starts(dem: str | Path, runs: list[GridRun]) -> None:
    """Fail before any run if the DEM cannot be used or a leader start is not on it."""
    from world.main import resolve_with_surface
    from world.sim import WorldSim

    seen = set()
    for run in runs:
        if run.config.leader_start in seen:
            continue
        seen.add(run.config.leader_start)
        config, surface = resolve_with_surface(run.config)
        try:
            WorldSim(config, surface)
        except ValueError as exc:
            raise ValueError(f"leader start {config.leader_start} on {dem}: {exc}") from None


def run_terrain_experiment(dem: str | Path, out_dir: str | Path, spec: TerrainSpec,
                           workers: int | None = None, progress: bool = True) -> dict:
    """Run the terrain study of ``spec`` on ``dem`` into ``out_dir`` (see the module docstring).

    Raises ValueError before any run if the DEM cannot be used or a leader start is not on
    it. Returns ``tables``, ``figures``, ``figure_problems``, ``report``, ``failed`` and
    ``wall_time`` (s), like :func:`swarm.experiment.run_paper_experiment`.
    """
    out_dir = Path(out_dir)
    runs = terrain_grid(dem, spec)
    _validate_starts(dem, runs)
    start = time.perf_counter()
    outcomes = run_grid(runs, out_dir / "runs", workers=workers, progress=progress)
    wall_time = time.perf_counter() - start
    tables, rows = write_tables(out_dir, {
        "terrain_comm_period": (COMM_PERIOD_COLUMNS, follower_rows(outcomes, False)),
        "terrain_position": (POSITION_COLUMNS, follower_rows(
            [o for o in outcomes if o.run.labels["comm_period"] in spec.position_periods],
            True))}, outcomes)
    means = {"terrain_comm_period": mean_over_starts(rows["terrain_comm_period"],
                                                     ("comm_period", "estimator")),
             "terrain_position": mean_over_starts(rows["terrain_position"],
                                                  ("comm_period", "follower", "estimator"))}
    figures, problems = draw_terrain_figures(out_dir, dem, runs, spec, means)
    report = write_terrain_report(out_dir, dem, spec, rows, means, figures, problems, outcomes,
                                  wall_time)
    return {"tables": tables, "figures": figures, "figure_problems": problems, "report": report,
            "failed": [o for o in outcomes if not o.ok], "wall_time": wall_time}


def trajectory_run(runs: list[GridRun], spec: TerrainSpec) -> GridRun:
    """The run whose column the trajectory figure shows: the first start, EDMD-b (else the
    first estimator), the first position comm period."""
    shown = {"start": 0, "comm_period": (spec.position_periods or spec.comm_periods)[0],
             "estimator": "edmd-b" if "edmd-b" in spec.estimators else spec.estimators[0]}
    return next(run for run in runs if run.labels == shown)


def draw_terrain_figures(out_dir: Path, dem: str | Path, runs: list[GridRun], spec: TerrainSpec,
                         means: dict[str, list[dict]]) -> tuple[dict[str, Path], dict[str, str]]:
    """The study's three figures from the tables' ``means`` over the starts; a figure that
    cannot be drawn is named with the reason."""
    from swarm import plots

    folder = out_dir / "figures"
    label = f"{Path(dem).name}: follower 1,\nmean over {len(spec.leader_starts)} start(s)"
    comm_rows = [{**r, "surface": label} for r in means["terrain_comm_period"]]
    position_rows = means["terrain_position"]
    jobs = {
        "terrain_trajectories": lambda: plots.plot_effectiveness(
            out_dir / "runs" / trajectory_run(runs, spec).folder,
            folder / "terrain_trajectories.png",
            title="Column over real terrain (hillshade and contour lines of the DEM)"),
        "terrain_comm_period": lambda: plots.plot_comm_period(
            comm_rows, folder / "terrain_comm_period.png"),
        "terrain_position": lambda: plots.plot_position(
            position_rows, folder / "terrain_position.png"),
    }
    return draw_jobs(jobs)


def _best(rows: list[dict], **keys: Any) -> str:
    """The estimator with the lowest mean required range among the rows matching ``keys``."""
    mine = [r for r in rows if all(r[k] == v for k, v in keys.items())
            and not is_nan(r["mean_required_range"])]
    return min(mine, key=lambda r: r["mean_required_range"])["estimator"] if mine else "n/a"


def _cell(rows: list[dict], **keys: Any) -> float:
    return next((r["mean_required_range"] for r in rows
                 if all(r[k] == v for k, v in keys.items())), math.nan)


def _fmt(x: float) -> str:
    return "n/a" if is_nan(x) else f"{x:.3g}"


def _markdown_table(head: list[str], rows: list[list[str]]) -> list[str]:
    return (["| " + " | ".join(head) + " |", "| --- " * len(head) + "|"]
            + ["| " + " | ".join(row) + " |" for row in rows] + [""])


def write_terrain_report(out_dir: Path, dem: str | Path, spec: TerrainSpec,
                         rows: dict[str, list[dict]], means: dict[str, list[dict]],
                         figures: dict[str, Path], problems: dict[str, str],
                         outcomes: list[RunOutcome], wall_time: float) -> Path:
    """``out_dir/report.md``: the figures, the tables' ``means`` over the starts as markdown
    and what the ``rows`` (every start) show."""
    comm_all, position_all = rows["terrain_comm_period"], rows["terrain_position"]
    comm, position = means["terrain_comm_period"], means["terrain_position"]
    names = list(spec.estimators)
    starts = "; ".join(f"{i}: {s}" for i, s in enumerate(spec.leader_starts))
    lines = [
        "# Formation keeping on real terrain", "",
        f"DEM `{Path(dem).name}`; leader starts (x, y, vx, vy in m, m/s) {starts}; rod length "
        f"{spec.spacing:g} m; {spec.ticks} ticks (4 initial); {spec.followers} followers; "
        f"smoothing {spec.smoothing:g}. {len(outcomes)} runs over Zenoh in {wall_time:.0f} s. "
        "Numbers: mean required sensing range (m), averaged over the leader starts, read from "
        "`tables/` (which keep every start).", "",
    ]
    if "terrain_trajectories" in figures:
        lines += ["![trajectories](figures/terrain_trajectories.png)", "",
                  "Start 0: the leader's path and the followers' ideal (red) and estimated "
                  "(blue) positions over the hillshaded DEM with contour lines (EDMD-b).", ""]
    lines += ["## Against the comm period (follower 1)", ""]
    if "terrain_comm_period" in figures:
        lines += ["![comm period](figures/terrain_comm_period.png)", ""]
    lines += _markdown_table(
        ["T_c (s)", *names, "best"],
        [[f"{p:g}", *(_fmt(_cell(comm, comm_period=p, estimator=n)) for n in names),
          _best(comm, comm_period=p)] for p in spec.comm_periods])
    for period in spec.position_periods:
        lines += [f"## Along the column at T_c = {period:g} s", ""]
        lines += _markdown_table(
            ["follower", *names, "best"],
            [[str(k), *(_fmt(_cell(position, comm_period=period, follower=k, estimator=n))
                        for n in names), _best(position, comm_period=period, follower=k)]
             for k in range(1, spec.followers + 1)])
    if "terrain_position" in figures:
        lines += ["![position](figures/terrain_position.png)", ""]
    lines += _findings(comm_all, position_all, position, spec)
    retried = [o.run.folder for o in outcomes if o.ok and o.attempts > 1]
    if retried:
        lines += [f"{len(retried)} run(s) completed only at a second attempt (the first ended "
                  "early; see `tables/runs.csv`): " + ", ".join(f"`{r}`" for r in retried)
                  + ". A run's numbers do not depend on the attempt (same config, same seed).",
                  ""]
    failed = [o for o in outcomes if not o.ok]
    if failed or problems:
        lines += ["## Problems", ""]
        lines += [f"- run `{o.run.folder}` failed: {o.error}" for o in failed]
        lines += [f"- figure `{name}` not drawn: {why}" for name, why in problems.items()]
        lines.append("")
    path = out_dir / "report.md"
    write_atomic(path, "\n".join(lines))
    return path


def _findings(comm_all: list[dict], position_all: list[dict], position: list[dict],
              spec: TerrainSpec) -> list[str]:
    """Sentences computed from the tables: who wins where (per start and comm period, and per
    position), and how the required range changes down the column."""
    out = ["## What the numbers say", ""]
    cells = [(i, p) for i in range(len(spec.leader_starts)) for p in spec.comm_periods]
    wins: dict[str, int] = {}
    for i, p in cells:
        best = _best(comm_all, start=i, comm_period=p)
        wins[best] = wins.get(best, 0) + 1
    out.append(f"- Lowest required range for follower 1, over {len(cells)} (start, comm period) "
               "cells: " + ", ".join(f"{name} in {count}" for name, count in
                                     sorted(wins.items(), key=lambda kv: -kv[1])) + ".")
    if {"edmd-b", "persist"} <= set(spec.estimators):
        for p in spec.comm_periods:
            ratios = [_cell(comm_all, start=i, comm_period=p, estimator="edmd-b")
                      / _cell(comm_all, start=i, comm_period=p, estimator="persist")
                      for i in range(len(spec.leader_starts))]
            out.append(f"- T_c = {p:g} s: EDMD-b / persist for follower 1 per start: "
                       + ", ".join(_fmt(r) for r in ratios)
                       + f" (EDMD-b better in {sum(r < 1 for r in ratios)} of {len(ratios)}).")
    for period in spec.position_periods:
        growth = [f"{n} {_fmt(_cell(position, comm_period=period, follower=1, estimator=n))} → "
                  + _fmt(_cell(position, comm_period=period, follower=spec.followers,
                               estimator=n))
                  for n in spec.estimators]
        winners: dict[str, int] = {}
        for i in range(len(spec.leader_starts)):
            for k in range(1, spec.followers + 1):
                best = _best(position_all, start=i, comm_period=period, follower=k)
                winners[best] = winners.get(best, 0) + 1
        total = len(spec.leader_starts) * spec.followers
        out.append(f"- At T_c = {period:g} s, follower 1 → follower {spec.followers} (mean over "
                   "starts): " + "; ".join(growth) + ". Best per (start, position): "
                   + ", ".join(f"{n} {c}/{total}" for n, c in winners.items()) + ".")
    out.append("")
    return out


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
    with needs("dem"):
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


def check_tif_out(out: Path, force: bool) -> None:
    """ValueError unless ``out`` is a GeoTIFF path (``.tif``) that does not exist yet, or
    ``force`` (replace it)."""
    if out.exists() and not force:
        raise ValueError(f"out {str(out)!r} exists; choose another path or replace it (--force)")
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"out {str(out)!r} must be a GeoTIFF path (.tif)")


NPZ_KEYS = ("elevation", "xmin", "xmax", "ymin", "ymax", "dx", "dy")


def dem_from_npz(out: str | Path, npz: str | Path | None = None, force: bool = False) -> Path:
    """Write matplotlib's Jacksboro sample DEM (or ``npz`` in the same layout) as a GeoTIFF.

    The archive holds ``elevation`` (rows, cols; north row first; metres) and the grid's outer
    edges in degrees (``xmin``, ``xmax``; ``ymin`` is its **northern** edge, ``ymax`` the
    southern one) with cell sizes ``dx``, ``dy``; the GeoTIFF is EPSG:4326. ValueError (one
    line) if ``out`` exists (unless ``force``) or is not a ``.tif``, or ``npz`` is not such an
    archive.
    """
    import matplotlib.cbook

    check_tif_out(Path(out), force)
    try:
        archive = (np.load(npz, allow_pickle=False) if npz is not None
                   else matplotlib.cbook.get_sample_data(JACKSBORO))
        data = {key: np.asarray(archive[key], dtype=float) for key in NPZ_KEYS}
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        problem = exc.strerror if isinstance(exc, OSError) and exc.strerror else \
            "not an .npz of numbers " + ", ".join(NPZ_KEYS)
        raise ValueError(f"npz {str(npz)!r}: {problem}") from None
    elevation = data["elevation"]
    north, south = max(data["ymin"], data["ymax"]), min(data["ymin"], data["ymax"])
    if elevation.ndim != 2 or not all(data[k].ndim == 0 for k in NPZ_KEYS[1:]):
        raise ValueError(f"npz {str(npz)!r}: elevation must be a 2-D grid and its edges numbers")
    rows, cols = elevation.shape
    if not (math.isclose(north - south, rows * data["dy"], rel_tol=1e-6)
            and math.isclose(data["xmax"] - data["xmin"], cols * data["dx"], rel_tol=1e-6)):
        raise ValueError("npz: the grid's edges do not match its size and cell size")
    return write_geotiff(out, elevation[::-1], west=float(data["xmin"]), south=float(south),
                         cell_x=float(data["dx"]), cell_y=float(data["dy"]), crs="EPSG:4326")


@dataclass(frozen=True)
class Crop:
    """What :func:`crop_dem` wrote. Indices count nodes of the source from the south-west
    (columns east, rows north), inclusive; ``origin`` is the crop's south-west node in the
    source's design frame (m), so a point ``p`` of the source is ``p - origin`` in the crop's."""

    path: Path
    columns: tuple[int, int]
    rows: tuple[int, int]
    origin: tuple[float, float]
    size: tuple[float, float]  # the crop's extent in its own frame (m), x then y
    dropped: int  # no-data nodes of the source left out


CROP_MAX_CELLS = 2 * 4096 * 4096
"""Most cells of a raster ``dem-crop`` reads (``--max-cells`` raises it): it holds the whole
raster's heights and no-data mask, 36 bytes per cell at peak on a 3000 × 3000 GeoTIFF
(bench/bench_dem_limit.py), so about 1.1 GiB at this limit; twice what a run loads
(:data:`world.dem.MAX_CELLS`), since cutting a large raster down is what it is for."""


def crop_dem(source: str | Path, out: str | Path,
             bounds: tuple[float, float, float, float] | None = None,
             force: bool = False, max_cells: int | None = None) -> Crop:
    """Write a rectangle of the DEM at ``source`` without any no-data node as the GeoTIFF
    ``out`` (same CRS, cell size, data type and no-data value; a geo-referenced window).
    A raster over ``max_cells`` cells (default :data:`CROP_MAX_CELLS`) is refused
    (:class:`world.dem.RasterTooLarge`) before its data is read.

    Parameters
    ----------
    bounds : (xmin, ymin, xmax, ymax), optional
        The nodes to keep, in the source's design frame (m, origin at its south-west node). By
        default the largest rectangle (most nodes) of at least 4 × 4 nodes holding data.
    force : bool
        Replace ``out`` if it exists (default: refuse).

    Raises
    ------
    ValueError
        ``out`` is the source, exists (without ``force``) or is not a ``.tif``; the source
        cannot be read (:func:`world.dem.read_grid`); ``bounds`` hold no-data nodes or fewer
        than 4 × 4 nodes; or no rectangle of 4 × 4 nodes holds data.
    """
    with needs("dem"):
        import rasterio
        from rasterio.transform import Affine
        from rasterio.windows import Window

    from world.dem import MIN_NODES, read_dem, read_grid

    source, out = Path(source), Path(out)
    if out.resolve() == source.resolve():  # what can be refused before reading the raster
        raise ValueError(f"out {str(out)!r} is the source DEM; write the crop elsewhere")
    check_tif_out(out, force)
    if bounds is not None and not (bounds[0] < bounds[2] and bounds[1] < bounds[3]):
        raise ValueError(f"bounds must be xmin,ymin,xmax,ymax with xmin < xmax and "
                         f"ymin < ymax, got {bounds}")
    max_cells = CROP_MAX_CELLS if max_cells is None else max_cells
    if isinstance(max_cells, bool) or not isinstance(max_cells, int) or max_cells < 1:
        raise ValueError(f"max_cells must be a whole number >= 1, got {max_cells!r}")
    x, y, z = read_grid(source, max_cells, limit="dem-crop --max-cells")
    valid = np.isfinite(z)
    if bounds is None:
        j0, j1, i0, i1 = largest_rectangle(valid, MIN_NODES)
        if j1 == j0:
            raise ValueError(f"path {str(source)!r}: no rectangle of {MIN_NODES} × {MIN_NODES} "
                             "nodes holds data")
    else:
        xmin, ymin, xmax, ymax = bounds
        cols = np.flatnonzero((x >= xmin) & (x <= xmax))
        rows = np.flatnonzero((y >= ymin) & (y <= ymax))
        if cols.size < MIN_NODES or rows.size < MIN_NODES:
            raise ValueError(f"bounds {bounds} hold {cols.size} × {rows.size} nodes of "
                             f"{str(source)!r}; a bicubic spline needs at least {MIN_NODES} × "
                             f"{MIN_NODES} (its nodes: x ∈ [0, {x[-1]:.6g}], "
                             f"y ∈ [0, {y[-1]:.6g}] m)")
        i0, i1, j0, j1 = int(cols[0]), int(cols[-1]) + 1, int(rows[0]), int(rows[-1]) + 1
        holes = int((~valid[j0:j1, i0:i1]).sum())
        if holes:
            raise ValueError(f"bounds {bounds} hold {holes} no-data node(s) of "
                             f"{str(source)!r}; choose others, or leave --bounds out for the "
                             "largest rectangle with data")
    out.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(source) as src:
        north_up = src.transform.e < 0
        row_off = z.shape[0] - j1 if north_up else j0  # rasterio counts rows from the top
        window = Window(i0, row_off, i1 - i0, j1 - j0)
        heights = src.read(1, window=window)
        profile = dict(driver="GTiff", width=i1 - i0, height=j1 - j0, count=1,
                       dtype=src.dtypes[0], crs=src.crs, nodata=src.nodata,
                       transform=src.transform @ Affine.translation(i0, row_off))
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(heights, 1)
    cx, cy, _ = read_dem(out)  # the crop loads as a surface
    return Crop(out, (i0, i1 - 1), (j0, j1 - 1), (float(x[i0]), float(y[j0])),
                (float(cx[-1]), float(cy[-1])), int((~valid).sum()))


def largest_rectangle(valid: np.ndarray, min_side: int = 1) -> tuple[int, int, int, int]:
    """The axis-aligned rectangle of ``valid`` (2-D bool) with the most True cells among those
    at least ``min_side`` cells along both axes: ``(row0, row1, col0, col1)``, ends exclusive;
    all zero if there is none. Ties go to the first found (rows ending lowest, then columns
    farthest left).

    Examples
    --------
    >>> valid = np.array([[1, 1, 0, 1], [1, 1, 1, 1], [0, 1, 1, 1]], dtype=bool)
    >>> largest_rectangle(valid)
    (1, 3, 1, 4)
    """
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    if valid.ndim != 2:
        raise ValueError(f"valid must be 2-D, got shape {valid.shape}")
    return tuple(int(v) for v in _largest_rectangle(valid, int(min_side)))


@numba.njit(cache=True)
def _largest_rectangle(valid, min_side):
    """For each row as the bottom, the largest rectangle under the histogram of valid runs
    ending there (a stack of rising bars): O(rows × cols)."""
    rows, cols = valid.shape
    heights = np.zeros(cols + 1, dtype=np.int64)  # a zero bar past the end empties the stack
    stack = np.empty(cols + 1, dtype=np.int64)
    best = np.zeros(5, dtype=np.int64)  # area, row0, row1, col0, col1
    for j in range(rows):
        for i in range(cols):
            heights[i] = heights[i] + 1 if valid[j, i] else 0
        top = 0
        for i in range(cols + 1):
            while top > 0 and heights[stack[top - 1]] >= heights[i]:
                top -= 1
                height = heights[stack[top]]
                left = stack[top - 1] + 1 if top > 0 else 0
                width = i - left
                if height >= min_side and width >= min_side and height * width > best[0]:
                    best[0], best[1], best[2] = height * width, j + 1 - height, j + 1
                    best[3], best[4] = left, i
            stack[top] = i
            top += 1
    return best[1], best[2], best[3], best[4]
