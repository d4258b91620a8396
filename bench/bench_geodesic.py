"""Benchmark ``world.geometry.rod_end`` against scipy's DOP853 at equal accuracy.

For each paper preset, ``rod_end`` is timed call by call (median over ``--calls`` calls after a
warm-up, cycling through random start points near the leader's start and random headings);
scipy's ``solve_ivp(method="DOP853")`` integrates the same rods from the same rod normals. All
errors are the largest xy distance (max norm) to a ``solve_ivp`` DOP853 reference at
``rtol = atol = 1e-13``. scipy is timed at two tolerances taken from a ladder
``1e-8 … 1e-12`` (1e-13 is the reference itself): the loosest that meets the design's 1e-8 bound
("contract"), and the loosest that is at least as accurate as ``rod_end`` ("matched"; 1e-12
when none is). The first-call times are measured in
fresh interpreters: with an empty numba cache (compilation) and with the cache just written.

Run ``python bench/bench_geodesic.py``; other scripts call :func:`rod_end_timing`.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from world.geometry import rod_end, rod_normal  # noqa: E402  (after the path set-up)
from world.surfaces import Surface, make_surface, surface_leader_start  # noqa: E402

PAPER_PRESETS = ("elliptic", "hyperbolic", "wavy")
SPACING = 3.57
REFERENCE_TOLERANCE = 1e-13
CONTRACT_ERROR = 1e-8
TOLERANCE_LADDER = (1e-8, 1e-9, 1e-10, 1e-11, 1e-12)
Case = tuple[np.ndarray, np.ndarray, np.ndarray]
"""A rod: holder position, heading and rod normal, each shape (2,)."""

_FIRST_CALL = """
import time
start = time.perf_counter()
from world.geometry import rod_end
from world.surfaces import make_surface
rod_end(make_surface("elliptic"), (50.0, -10.0), (-1.0, 0.1), 3.57)
print(time.perf_counter() - start)
"""


def make_cases(surface: Surface, count: int, seed: int) -> list[Case]:
    """``count`` rods at random points within ~5 units of the leader start, random headings."""
    rng = np.random.default_rng(seed)
    start = np.array(surface_leader_start(surface)[:2])
    cases = []
    for _ in range(count):
        p, heading = start + rng.normal(0.0, 5.0, 2), rng.normal(size=2)
        cases.append((p, heading, rod_normal(surface, p, heading)))
    return cases


def scipy_rod_end(surface: Surface, p: np.ndarray, n: np.ndarray, tolerance: float) -> np.ndarray:
    """The rod end by ``solve_ivp`` DOP853 at ``rtol = atol = tolerance``, shape (2,)."""
    def field(_: float, state: np.ndarray) -> np.ndarray:
        gradient, hessian = surface.gradient(state[:2]), surface.hessian(state[:2])
        velocity = state[2:]
        curvature = velocity @ hessian @ velocity / (1.0 + gradient @ gradient)
        return np.concatenate([velocity, -gradient * curvature])

    solution = solve_ivp(field, (0.0, SPACING), np.concatenate([p, n]), method="DOP853",
                         rtol=tolerance, atol=tolerance)
    if not solution.success:
        raise RuntimeError(f"solve_ivp failed: {solution.message}")
    return solution.y[:2, -1]


def median_ms(call: Callable[[Case], object], cases: Sequence[Case], calls: int) -> float:
    """Median wall time of one call in ms, cycling through ``cases`` after one warm-up pass."""
    for case in cases:
        call(case)
    times = []
    for i in range(calls):
        case = cases[i % len(cases)]
        start = time.perf_counter_ns()
        call(case)
        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1e6


def max_error(ends: Sequence[np.ndarray], references: Sequence[np.ndarray]) -> float:
    return max(float(np.max(np.abs(end - ref))) for end, ref in zip(ends, references, strict=True))


def loosest_tolerance(errors: dict[float, float], bound: float) -> float:
    """The loosest ladder tolerance whose error is within ``bound`` (else the tightest)."""
    for tolerance in TOLERANCE_LADDER:
        if errors[tolerance] <= bound:
            return tolerance
    return TOLERANCE_LADDER[-1]


def time_preset(name: str, calls: int, scipy_calls: int, accuracy_cases: int,
                seed: int) -> dict[str, float]:
    """Timings (ms) and errors of ``rod_end`` and scipy on one preset."""
    surface = make_surface(name)
    cases = make_cases(surface, accuracy_cases, seed)
    references = [scipy_rod_end(surface, p, n, REFERENCE_TOLERANCE) for p, _, n in cases]
    ours = max_error([rod_end(surface, p, h, SPACING)[0] for p, h, _ in cases], references)
    scipy_errors = {
        tolerance: max_error([scipy_rod_end(surface, p, n, tolerance) for p, _, n in cases],
                             references)
        for tolerance in TOLERANCE_LADDER}
    figures = {"rod_end_ms": median_ms(lambda c: rod_end(surface, c[0], c[1], SPACING),
                                       cases, calls),
               "rod_end_max_error": ours}
    for label, bound in (("contract", CONTRACT_ERROR), ("matched", ours)):
        tolerance = loosest_tolerance(scipy_errors, bound)
        elapsed = median_ms(lambda c, tol=tolerance: scipy_rod_end(surface, c[0], c[2], tol),
                            cases, scipy_calls)
        figures |= {f"scipy_{label}_tolerance": tolerance,
                    f"scipy_{label}_max_error": scipy_errors[tolerance],
                    f"scipy_{label}_ms": elapsed,
                    f"speedup_{label}": elapsed / figures["rod_end_ms"]}
    return figures


def first_call_seconds(cache_dir: str) -> float:
    """Import plus first ``rod_end`` in a fresh interpreter using numba cache ``cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir,
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO_ROOT),
                                                        os.environ.get("PYTHONPATH")])))
    result = subprocess.run([sys.executable, "-c", _FIRST_CALL], env=env, capture_output=True,
                            text=True, check=True, cwd=REPO_ROOT)
    return float(result.stdout.strip().splitlines()[-1])


def rod_end_timing(presets: Sequence[str] = PAPER_PRESETS, calls: int = 2000,
                   scipy_calls: int = 200, accuracy_cases: int = 100,
                   seed: int = 0) -> dict[str, object]:
    """Time ``rod_end`` and scipy DOP853 on each preset; see the module docstring.

    Parameters
    ----------
    presets : sequence of str
        Preset names.
    calls : int
        Timed ``rod_end`` calls per preset (the median is reported).
    scipy_calls : int
        Timed ``solve_ivp`` calls per preset and tolerance.
    accuracy_cases : int
        Distinct rods per preset, used both for the errors and, cyclically, for the timing.
    seed : int
        Seed of the random rods.

    Returns
    -------
    dict
        ``"presets"``: per preset, ``rod_end_ms``, ``rod_end_max_error`` and, for
        ``label`` in (``contract``, ``matched``), ``scipy_<label>_tolerance``,
        ``scipy_<label>_max_error``, ``scipy_<label>_ms``, ``speedup_<label>``;
        ``"first_call_cold_s"`` and ``"first_call_cached_s"``: import plus first ``rod_end``
        with an empty and with a warm numba cache; and the settings used.
    """
    with tempfile.TemporaryDirectory() as cache_dir:
        cold = first_call_seconds(cache_dir)
        cached = first_call_seconds(cache_dir)
    return {"presets": {name: time_preset(name, calls, scipy_calls, accuracy_cases, seed)
                        for name in presets},
            "first_call_cold_s": cold, "first_call_cached_s": cached,
            "calls": calls, "scipy_calls": scipy_calls, "accuracy_cases": accuracy_cases,
            "spacing": SPACING, "reference_tolerance": REFERENCE_TOLERANCE}


def format_table(timing: dict[str, object]) -> str:
    """A plain-text table of :func:`rod_end_timing`'s figures."""
    lines = [f"rod_end vs scipy DOP853, rod length {timing['spacing']}, "
             f"errors vs DOP853 at rtol=atol={timing['reference_tolerance']:g} "
             f"({timing['accuracy_cases']} rods per preset); medians over "
             f"{timing['calls']} (rod_end) / {timing['scipy_calls']} (scipy) calls",
             f"{'preset':<13} {'rod_end ms':>10} {'max err':>8} | "
             f"{'scipy tol':>9} {'ms':>7} {'max err':>8} {'speed-up':>8} | "
             f"{'scipy tol':>9} {'ms':>7} {'max err':>8} {'speed-up':>8}",
             f"{'':<33}| {'(contract: error <= 1e-8)':^36} | {'(matched: error <= rod_end)':^36}"]
    for name, row in timing["presets"].items():
        line = f"{name:<13} {row['rod_end_ms']:>10.4f} {row['rod_end_max_error']:>8.1e}"
        for label in ("contract", "matched"):
            line += (f" | {row[f'scipy_{label}_tolerance']:>9.0e} {row[f'scipy_{label}_ms']:>7.3f}"
                     f" {row[f'scipy_{label}_max_error']:>8.1e}"
                     f" {row[f'speedup_{label}']:>7.1f}x")
        lines.append(line)
    lines.append(f"first call (import + compile + run): {timing['first_call_cold_s']:.2f} s "
                 f"with an empty numba cache, {timing['first_call_cached_s']:.2f} s cached")
    return "\n".join(lines)


def main(presets: Sequence[str], calls: int, scipy_calls: int, accuracy_cases: int,
         seed: int) -> None:
    print(format_table(rod_end_timing(presets, calls, scipy_calls, accuracy_cases, seed)))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default=",".join(PAPER_PRESETS),
                        help="comma-separated preset names (default: the paper's three)")
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--scipy-calls", type=int, default=200)
    parser.add_argument("--accuracy-cases", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.presets.split(","), args.calls, args.scipy_calls, args.accuracy_cases, args.seed)
