"""Benchmark rod ends on DEM surfaces: compiled vs plain Python, and accuracy across knots.

For each DEM case (matplotlib's Jacksboro sample DEM as GeoTIFF, 74 m × 93 m cells, rods of
3.57 m and 40 m; the committed test DEM ``tests/data/hills.tif``, 2 m cells, rods of 3.57 m)
``rod_end`` is timed call by call (median after a warm-up, cycling through random rods:
uniform points at least one rod length inside the grid, random headings). The same DEM wrapped
as a plain-Python custom surface (scipy's spline evaluated per call, the Python integrator) is
timed on the first few of those rods, and the speed-up is the ratio of the medians over those
same rods. Errors are the largest xy distance to :func:`reference_rod_end`: scipy's
``solve_ivp`` DOP853 at ``rtol = atol = 1e-13``, restarted at every knot line it crosses (an
event), so that no step of the reference straddles the spline's C² seams. The column
``python err`` is the plain-Python path, which has no knot handling; ``DOP853 no-restart err``
is the same reference without the restarts.

Run ``python bench/bench_dem.py``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from swarm.terrain import dem_from_npz  # noqa: E402  (after the path set-up)
from tests.dem_reference import REFERENCE_TOLERANCE, Case, make_cases, reference_rod_end  # noqa: E402
from world.dem import DemSurface, load_dem  # noqa: E402
from world.geometry import rod_end  # noqa: E402

TARGET_MS, TARGET_ERROR, TARGET_SPEEDUP = 0.1, 1e-6, 1000.0


class PlainPythonDem:
    """A DEM as a user's custom surface would be: only height, gradient, hessian, contains."""

    def __init__(self, dem: DemSurface) -> None:
        self.dem = dem

    def contains(self, p: ArrayLike) -> bool:
        return self.dem.contains(p)

    def height(self, p: ArrayLike) -> float:
        return self.dem.height(p)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        return self.dem.gradient(p)

    def hessian(self, p: ArrayLike) -> np.ndarray:
        return self.dem.hessian(p)


def median_ms(call: Callable[[Case], object], cases: Sequence[Case], calls: int) -> float:
    """Median wall time of one call in ms, cycling through ``cases`` after one warm-up call."""
    call(cases[0])
    times = []
    for i in range(calls):
        start = time.perf_counter_ns()
        call(cases[i % len(cases)])
        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1e6


def bench_case(dem: DemSurface, length: float, calls: int, python_calls: int,
               accuracy_cases: int, seed: int) -> dict[str, float]:
    """Timings (ms), errors (m) and knot crossings of one DEM and rod length."""
    cases = make_cases(dem, accuracy_cases, length, seed)
    plain = PlainPythonDem(dem)
    references, crossings, naive = [], [], []
    for p, _, n in cases:
        end, crossed = reference_rod_end(dem, p, n, length)
        references.append(end)
        crossings.append(crossed)
        naive.append(reference_rod_end(dem, p, n, length, restart=False)[0])
    ours = [rod_end(dem, p, h, length)[0] for p, h, _ in cases]
    python_cases = cases[:python_calls]
    python_ends = [rod_end(plain, p, h, length)[0] for p, h, _ in python_cases]
    compiled_ms = median_ms(lambda c: rod_end(dem, c[0], c[1], length), cases, calls)
    # The speed-up compares the same rods: the plain-Python ones, each timed once per pass.
    python_ms = median_ms(lambda c: rod_end(plain, c[0], c[1], length), python_cases,
                          len(python_cases))
    same_rods_ms = median_ms(lambda c: rod_end(dem, c[0], c[1], length), python_cases,
                             calls // 10 * len(python_cases) or len(python_cases))

    def worst(ends: Sequence[np.ndarray]) -> float:
        return max(float(np.max(np.abs(e - r))) for e, r in zip(ends, references))

    return {"rod_end_ms": compiled_ms, "python_ms": python_ms,
            "speedup": python_ms / same_rods_ms, "max_error": worst(ours),
            "python_max_error": worst(python_ends), "no_restart_max_error": worst(naive),
            "mean_crossings": float(np.mean(crossings)), "max_crossings": int(max(crossings))}


def run(calls: int = 2000, python_calls: int = 10, accuracy_cases: int = 40,
        seed: int = 0) -> dict[str, dict[str, float]]:
    """Every case of the module docstring; keys ``"<dem> <rod length>"``."""
    with tempfile.TemporaryDirectory() as folder:
        jacksboro = load_dem(dem_from_npz(Path(folder) / "jacksboro.tif"))
    hills = load_dem(REPO_ROOT / "tests" / "data" / "hills.tif")
    results = {}
    for name, dem, length in (("jacksboro", jacksboro, 3.57), ("jacksboro", jacksboro, 40.0),
                              ("hills", hills, 3.57)):
        results[f"{name} {length:g} m"] = bench_case(dem, length, calls, python_calls,
                                                     accuracy_cases, seed)
    return results


def format_table(results: dict[str, dict[str, float]]) -> str:
    lines = [f"rod_end on DEMs; errors (m, max norm) vs DOP853 at {REFERENCE_TOLERANCE:g} "
             "restarted at knot lines; targets: <= "
             f"{TARGET_MS} ms, <= {TARGET_ERROR:g} m, >= {TARGET_SPEEDUP:,.0f}x",
             f"{'case':<18} {'ms':>7} {'max err':>8} {'python ms':>10} {'speed-up':>9} "
             f"{'python err':>10} {'DOP853 no-restart err':>21} {'knots/rod':>9}"]
    for name, row in results.items():
        lines.append(f"{name:<18} {row['rod_end_ms']:>7.4f} {row['max_error']:>8.1e} "
                     f"{row['python_ms']:>10.1f} {row['speedup']:>8.0f}x "
                     f"{row['python_max_error']:>10.1e} {row['no_restart_max_error']:>21.1e} "
                     f"{row['mean_crossings']:>5.2f} (max {row['max_crossings']})")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--python-calls", type=int, default=10,
                        help="rods timed (once each) as a plain-Python custom surface")
    parser.add_argument("--accuracy-cases", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(format_table(run(args.calls, args.python_calls, args.accuracy_cases, args.seed)))
