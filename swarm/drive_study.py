"""``python -m swarm experiment drive``: what driving robots cost the column (docs/drive.md).

The paper names its second practical difficulty (§4.3: a robot reaches its estimate by
iterating on its own odometry, and the discrepancy accumulates) and never measures it. This
study does, with followers that drive (``--motion drive``): the required sensing range and the
formation error against

- the **control steps** per comm interval (2 … 64, the correction window's default 4 steps:
  issue #30's axis), and again with the window's steps scaled with them (``snap_steps =
  control_steps / 2``, block ``window``); either way the window keeps its share of the comm
  period (``protocol.config.CORRECTION_SHARE``), so only the granularity of control changes,
- the **top speed**, as a multiple of the leader's speed (from just above it to unbounded),
- the **comm period**, crossed with the top speed (the minimum top speed per surface and
  comm period comes from this block),

on the paper's three surfaces and a DEM, for ``persist``, EDMD on dictionary b and ``auto``,
with the teleporting column of the same setup as the reference. Those runs are noise-free:
the shortfalls measured are those of driving, not of sensing. A **noise** block adds the
default robot under sensor noise (none, low, mid, high: σ_r/σ_θ 0, 0.01/0.005, 0.02/0.01,
0.05/0.03) with 3 and 5 followers, each beside the same column teleporting, with every
follower's mean formation error and the worst tick (issue #30). Every run is the in-memory layout
(:mod:`swarm.local`, the same code and numbers as a Zenoh run), in a process pool.

The **minimum top speed** of a column (surface, comm period, estimator) is the smallest top
speed tried whose mean formation error is within :data:`TOLERANCE` (10 %) of the best top speed
tried, the unbounded robot included (same control steps and comm period). The best is not
always the unbounded robot: one that follows a wild estimate all the way can break the column
where a slower one only lags.
"""
from __future__ import annotations

import math
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from protocol.config import CORRECTION_SHARE, RunConfig, estimator_options
from protocol.folder import write_atomic
from swarm.grid import number, table_number, write_table

TOLERANCE = 0.10
"""A top speed suffices when the formation error is within this fraction of the best top
speed's."""
REPO_DEM = Path(__file__).resolve().parents[1] / "tests" / "data" / "hills.tif"
REPO_DEM_START = (6.0, 8.0, 1.0, 0.0)  # the test terrain's leader start (tests/make_dem_data.py)
COLUMNS = ("surface", "estimator", "block", "motion", "comm_period", "control_steps",
           "snap_steps", "speed_factor", "max_speed", "ticks", "mean_required_range",
           "mean_formation_error", "last_formation_error", "mean_reach_error",
           "mean_snap_error", "saturated_steps", "path_length", "complete", "noise",
           "followers", "formation_errors", "worst_formation_error", "broken_ticks")
NOISE_LEVELS = {"none": (0.0, 0.0), "low": (0.01, 0.005), "mid": (0.02, 0.01),
                "high": (0.05, 0.03)}
"""The noise block's sensor noise, σ_r (m) and σ_θ (rad)."""
MIN_SPEED_COLUMNS = ("surface", "comm_period", "estimator", "min_speed_factor", "min_speed",
                     "formation_at_min", "best_speed_factor", "formation_best",
                     "formation_unbounded")


@dataclass(frozen=True)
class DriveStudySpec:
    """The study's grid (defaults: the full study)."""

    surfaces: tuple[str, ...] = ("elliptic", "hyperbolic", "wavy", "dem")
    estimators: tuple[str, ...] = ("persist", "edmd-b", "auto")
    control_steps: tuple[int, ...] = (2, 4, 8, 16, 32, 64)
    speed_factors: tuple[float, ...] = (1.02, 1.05, 1.1, 1.25, 1.5, 2.0, 3.0, math.inf)
    comm_periods: tuple[float, ...] = (0.64, 1.28, 2.56)
    base_steps: int = 8  # the defaults: 8 control steps, twice the leader's speed, T_c 1.28
    base_factor: float = 2.0
    base_period: float = 1.28
    followers: int = 3
    noise_levels: tuple[str, ...] = tuple(NOISE_LEVELS)
    noise_followers: tuple[int, ...] = (3, 5)
    duration: float = 51.2  # time units per run on a preset (the paper's 40 ticks of 1.28)
    dem: str = str(REPO_DEM)
    dem_start: tuple[float, float, float, float] = REPO_DEM_START
    dem_duration: float = 30.0  # the leader's 30 m stay inside the test terrain


QUICK = DriveStudySpec(surfaces=("wavy", "dem"), estimators=("persist",),
                       control_steps=(2, 8), speed_factors=(1.25, math.inf),
                       comm_periods=(1.28,), followers=2, duration=12.8, dem_duration=12.8,
                       noise_levels=("none", "high"), noise_followers=(2,))
"""A reduced grid to check the pipeline (``--quick``)."""


@dataclass(frozen=True)
class StudyRun:
    """One run of the study and the labels of its table row."""

    surface: str
    estimator: str
    block: str  # "steps", "window", "speed", "teleport" or "noise"
    config: RunConfig
    speed_factor: float
    noise: str = "none"


def _surface_options(surface: str, spec: DriveStudySpec) -> tuple[dict, float]:
    if surface == "dem":
        return {"surface": f"dem:{spec.dem}", "leader_start": spec.dem_start}, spec.dem_duration
    return {"surface": surface}, spec.duration


def _leader_speed(options: dict) -> float:
    from world.main import resolve_with_surface
    from world.sim import leader_speed

    config, surface = resolve_with_surface(RunConfig(**options))
    return leader_speed(config, surface)


def _drive(steps: int, max_speed: float, window: int | None = None) -> dict:
    """A driving robot's options: ``steps`` control steps, ``window`` correction steps (default:
    the run's, :class:`RunConfig`'s ``snap_steps``), at the top speed ``max_speed`` (the default
    robot has ``spec.base_steps``)."""
    return {"control_steps": steps, "max_speed": max_speed,
            **({} if window is None else {"snap_steps": window})}


def study_runs(spec: DriveStudySpec) -> list[StudyRun]:
    """Every run of the study (no duplicates)."""
    runs: dict[tuple, StudyRun] = {}
    for surface in spec.surfaces:
        options, duration = _surface_options(surface, spec)
        speed = _leader_speed(options)
        cases = [("teleport", period, {}) for period in spec.comm_periods]
        cases += [("steps", spec.base_period, _drive(steps, spec.base_factor * speed))
                  for steps in spec.control_steps]
        cases += [("window", spec.base_period, _drive(steps, spec.base_factor * speed,
                                                      max(1, steps // 2)))
                  for steps in spec.control_steps]
        cases += [("speed", period, _drive(spec.base_steps, factor * speed))
                  for period in spec.comm_periods for factor in spec.speed_factors]
        for label in spec.estimators:
            for block, period, drive in cases:
                config = RunConfig(run_id="drive-study", followers=spec.followers,
                                   ticks=max(int(round(duration / period)), 6),
                                   comm_period=period, **options, **estimator_options(label),
                                   **({"motion": "drive", **drive} if drive else {}))
                factor = drive["max_speed"] / speed if drive else math.nan
                key = (surface, label, block, period, config.motion, config.control_steps,
                       config.snap_steps, config.max_speed)
                runs.setdefault(key, StudyRun(surface, label, block, config, factor))
            for level in spec.noise_levels:
                sigma_r, sigma_t = NOISE_LEVELS[level]
                for n in spec.noise_followers:
                    for motion in ("drive", "teleport"):
                        drive = (_drive(spec.base_steps, spec.base_factor * speed)
                                 if motion == "drive" else {})
                        config = RunConfig(
                            run_id="drive-study", followers=n, motion=motion,
                            ticks=max(int(round(duration / spec.base_period)), 6),
                            comm_period=spec.base_period, noise_range=sigma_r,
                            noise_bearing=sigma_t, **options, **estimator_options(label),
                            **drive)
                        runs[(surface, label, "noise", level, n, motion)] = StudyRun(
                            surface, label, "noise", config,
                            spec.base_factor if motion == "drive" else math.nan, level)
    return list(runs.values())


def _simulate(config: RunConfig) -> dict:
    """Run ``config`` in memory (:func:`swarm.local.run_local`); its summary."""
    from swarm.local import run_local

    return run_local(config)[0]


def _row(run: StudyRun, summary: dict) -> dict:
    """The table row of ``run``, whose run gave ``summary``."""
    from world.results import broken_ticks  # the world's one count (imported with a run)

    followers = [summary["followers"][str(k)] for k in range(1, run.config.followers + 1)]

    def mean(key: str) -> float:
        values = [f[key] for f in followers if f.get(key) is not None]
        return float(np.mean(values)) if values else math.nan

    cfg = run.config
    return {
        "surface": run.surface, "estimator": run.estimator, "block": run.block,
        "motion": cfg.motion, "comm_period": cfg.comm_period,
        "control_steps": cfg.control_steps if cfg.drives else math.nan,
        "snap_steps": cfg.snap_steps if cfg.drives else math.nan,
        "speed_factor": run.speed_factor,
        "max_speed": cfg.max_speed if cfg.max_speed is not None else math.nan,
        "ticks": summary["ticks_completed"],
        "mean_required_range": mean("mean_required_range"),
        "mean_formation_error": mean("mean_formation_error"),
        "last_formation_error": number(followers[-1].get("mean_formation_error")),
        "mean_reach_error": mean("mean_reach_error"),
        "mean_snap_error": mean("mean_snap_error"),
        "saturated_steps": sum(f.get("saturated_steps", 0) for f in followers),
        "path_length": mean("path_length"),
        "complete": int(summary["complete"]),
        "noise": run.noise, "followers": cfg.followers,
        "formation_errors": " ".join(table_number(f.get("mean_formation_error"))
                                     for f in followers),
        "worst_formation_error": max((f.get("worst_formation_error") or 0.0)
                                     for f in followers),
        "broken_ticks": broken_ticks(summary),
    }


def run_study(spec: DriveStudySpec, workers: int | None = None,
              on_run: Callable[[int, int], None] | None = None) -> list[dict]:
    """Every run's table row, in the order of :func:`study_runs` (a pool of ``workers``
    processes, default ``min(2, CPU count)``). A configuration several blocks share is run
    once: the default robot at the base comm period is a cell of the steps, the speed and the
    noise block (noise-free, base length), and that column teleporting is the teleport
    reference and a noise cell; ``on_run`` counts the configurations run."""
    runs = study_runs(spec)
    configs = list({repr(run.config): run.config for run in runs}.items())
    workers = workers or min(2, os.cpu_count() or 1)
    summaries: dict[str, dict] = {}
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        done = pool.map(_simulate, [config for _, config in configs], chunksize=1)
        for count, ((key, _), summary) in enumerate(zip(configs, done), start=1):
            summaries[key] = summary
            if on_run is not None:
                on_run(count, len(configs))
    return [_row(run, summaries[repr(run.config)]) for run in runs]


def minimum_speeds(rows: list[dict], spec: DriveStudySpec) -> list[dict]:
    """Per surface, comm period and estimator: the smallest top speed tried whose mean
    formation error is within :data:`TOLERANCE` of the best top speed tried."""
    out = []
    for surface in spec.surfaces:
        for period in spec.comm_periods:
            for label in spec.estimators:
                tried = sorted((r for r in rows if r["block"] == "speed"
                                and r["surface"] == surface and r["estimator"] == label
                                and r["comm_period"] == period), key=lambda r: r["speed_factor"])
                if not tried:
                    continue
                best = min(tried, key=lambda r: r["mean_formation_error"])
                limit = (1.0 + TOLERANCE) * best["mean_formation_error"]
                enough = next(r for r in tried if r["mean_formation_error"] <= limit)
                unbounded = [r["mean_formation_error"] for r in tried
                             if math.isinf(r["speed_factor"])]
                out.append({"surface": surface, "comm_period": period, "estimator": label,
                            "min_speed_factor": enough["speed_factor"],
                            "min_speed": enough["max_speed"],
                            "formation_at_min": enough["mean_formation_error"],
                            "best_speed_factor": best["speed_factor"],
                            "formation_best": best["mean_formation_error"],
                            "formation_unbounded": unbounded[0] if unbounded else math.nan})
    return out


def draw_study(rows: list[dict], spec: DriveStudySpec, path: Path) -> Path:
    """The study's figure (:func:`swarm.plots.plot_drive_study`)."""
    from swarm.plots import plot_drive_study

    return plot_drive_study(rows, spec, path)


def write_report(out_dir: Path, rows: list[dict], minimum: list[dict], spec: DriveStudySpec,
                 wall_time: float) -> Path:
    """``report.md``: the headline numbers of the study."""
    lines = ["# Driving followers: the study", "",
             f"`python -m swarm experiment drive`; {len(rows)} runs, {wall_time:.0f} s wall "
             f"time. Noise-free but for the noise block; {spec.followers} followers but in it; "
             "table `tables/drive.csv`, figure "
             "`figures/drive.png`.", "",
             "## Minimum top speed (multiple of the leader's speed)", "",
             f"The smallest top speed tried ({', '.join(_factor(f) for f in spec.speed_factors)}"
             f" × the leader's) whose mean formation error is within {TOLERANCE:.0%} of the "
             f"best top speed's ({spec.base_steps} control steps); in brackets the best when "
             "it is not the unbounded robot.", ""]
    head = ["surface", "T_c", *spec.estimators]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for surface in spec.surfaces:
        for period in spec.comm_periods:
            cells = []
            for label in spec.estimators:
                match = [m for m in minimum if m["surface"] == surface
                         and m["comm_period"] == period and m["estimator"] == label]
                if not match:
                    cells.append("-")
                    continue
                best = match[0]["best_speed_factor"]
                cells.append(_factor(match[0]["min_speed_factor"])
                             + ("" if math.isinf(best) else f" ({_factor(best)})"))
            lines.append(f"| {surface} | {period:g} | " + " | ".join(cells) + " |")
    lines += _steps_table(rows, spec, "steps", "## Formation error against control steps",
                          f"the correction window's {RunConfig().snap_steps} steps "
                          "(the default)")
    lines += _steps_table(rows, spec, "window", "## The same, the window's steps scaled too",
                          "as many correction steps as half the control steps (docs/drive.md "
                          "says why a finer window lands worse)")
    lines += _noise_table(rows, spec)
    incomplete = [r for r in rows if not r["complete"]]
    lines += ["", f"Runs that ended early: {len(incomplete)}."]
    path = out_dir / "report.md"
    write_atomic(path, "\n".join(lines) + "\n")
    return path


def _steps_table(rows: list[dict], spec: DriveStudySpec, block: str, title: str,
                 window: str) -> list[str]:
    """The report's table of the mean formation error against the control steps (``block``
    ``steps`` or ``window``), beside the same column teleporting."""
    lines = ["", title, "",
             f"T_c = {spec.base_period:g}, top speed {spec.base_factor:g}× the leader's, "
             f"{window}, the window taking {CORRECTION_SHARE:.0%} of the comm period; teleport: "
             "the same column teleporting.", ""]
    head = ["surface", "estimator", *[str(n) for n in spec.control_steps], "teleport"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for surface in spec.surfaces:
        for label in spec.estimators:
            cells = []
            for steps in spec.control_steps:
                match = [r for r in rows if r["block"] == block and r["surface"] == surface
                         and r["estimator"] == label and r["control_steps"] == steps]
                cells.append(table_number(match[0]["mean_formation_error"]) if match else "-")
            tele = [r for r in rows if r["block"] == "teleport" and r["surface"] == surface
                    and r["estimator"] == label and r["comm_period"] == spec.base_period]
            cells.append(table_number(tele[0]["mean_formation_error"]) if tele else "-")
            lines.append(f"| {surface} | {label} | " + " | ".join(cells) + " |")
    return lines


WORST_TICK = 1.0
"""Issue #30's bound on the worst tick of any follower of a driving column (m)."""


def drive_bound(teleport: float) -> float:
    """Issue #30's bound on a driving column's last follower's mean formation error: twice
    the same column's teleporting, ``teleport``, plus 0.05 m."""
    return 2 * teleport + 0.05


def within_bound(drive: float, teleport: float) -> bool:
    """Whether a driving column's last follower's mean formation error ``drive`` is within
    :func:`drive_bound` of the teleporting column's ``teleport``."""
    return drive <= drive_bound(teleport)


def _noise_table(rows: list[dict], spec: DriveStudySpec) -> list[str]:
    """The report's noise block: per surface, estimator, noise level and column length, the
    required range and every follower's mean formation error (follower 1 first) driving and
    teleporting, the worst tick driving, and issue #30's bound on the last follower
    (drive ≤ 2 × teleport + 0.05 m)."""
    noisy = [r for r in rows if r["block"] == "noise"]
    if not noisy:
        return []
    levels = ", ".join(f"{name} {r:g}/{t:g}" for name, (r, t) in NOISE_LEVELS.items())
    lines = ["", "## Under sensor noise", "",
             f"The default robot ({spec.base_steps} control steps, top speed "
             f"{spec.base_factor:g}× the leader's, T_c = {spec.base_period:g}) under sensor "
             f"noise σ_r/σ_θ ({levels}), beside the same column teleporting. Formation error "
             "per follower (mean over the run, follower 1 first); worst: the largest any "
             "follower settled with; bound: the last follower's mean driving is within 2 × "
             "teleport's + 0.05 m.", "",
             "| surface | estimator | noise | N | required, drive | required, teleport | "
             "formation per follower, drive | formation per follower, teleport | worst, "
             "drive | bound |", "|" + "---|" * 10]
    for surface in spec.surfaces:
        for label in spec.estimators:
            for level in spec.noise_levels:
                for n in spec.noise_followers:
                    cell = {r["motion"]: r for r in noisy if r["surface"] == surface
                            and r["estimator"] == label and r["noise"] == level
                            and r["followers"] == n}
                    if len(cell) < 2:
                        continue
                    d, t = cell["drive"], cell["teleport"]
                    ok = within_bound(d["last_formation_error"], t["last_formation_error"])
                    lines.append(
                        f"| {surface} | {label} | {level} | {n} | "
                        f"{table_number(d['mean_required_range'])} | "
                        f"{table_number(t['mean_required_range'])} | {d['formation_errors']} | "
                        f"{t['formation_errors']} | "
                        f"{table_number(d['worst_formation_error'])} | "
                        f"{'yes' if ok else 'NO'} |")
    return lines


def _factor(x: float) -> str:
    return "unbounded" if math.isinf(x) else f"{x:g}"


def run_drive_study(out_dir: str | Path, spec: DriveStudySpec = DriveStudySpec(),
                    workers: int | None = None,
                    on_run: Callable[[int, int], None] | None = None) -> dict:
    """Run the study and write ``tables/drive.csv``, ``tables/drive_min_speed.csv``,
    ``figures/drive.png`` and ``report.md`` into ``out_dir``; return their paths and the
    wall time."""
    out = Path(out_dir)
    start = time.monotonic()
    rows = run_study(spec, workers, on_run)
    runs_time = time.monotonic() - start
    minimum = minimum_speeds(rows, spec)
    tables = {"drive": out / "tables" / "drive.csv",
              "drive_min_speed": out / "tables" / "drive_min_speed.csv"}
    write_table(tables["drive"], COLUMNS, rows)
    write_table(tables["drive_min_speed"], MIN_SPEED_COLUMNS, minimum)
    figure = draw_study(rows, spec, out / "figures" / "drive.png")
    wall = time.monotonic() - start
    report = write_report(out, rows, minimum, spec, wall)
    return {"tables": tables, "figures": {"drive": figure}, "report": report,
            "runs": len(rows), "runs_time": runs_time, "wall_time": wall,
            "incomplete": sum(1 for r in rows if not r["complete"])}


def quick(spec: DriveStudySpec) -> DriveStudySpec:
    """The reduced grid keeping ``spec``'s DEM."""
    return replace(QUICK, dem=spec.dem, dem_start=spec.dem_start)
