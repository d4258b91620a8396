"""The reference for rod ends on a DEM: scipy's DOP853 at a tight tolerance, restarted at every
knot line the rod crosses (where the spline is only C²), and random test rods on a DEM. Used
by tests/test_dem.py and bench/bench_dem.py."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import solve_ivp

from world.dem import DemSurface
from world.geometry import rod_normal

REFERENCE_TOLERANCE = 1e-13
Case = tuple[np.ndarray, np.ndarray, np.ndarray]
"""A rod: holder position, heading and rod normal, each shape (2,)."""


def _cell(knots: np.ndarray, u: float, velocity: float) -> tuple[float, float]:
    """Knot cell the path enters from ``u`` moving with ``velocity`` (knots distinct, sorted)."""
    i = int(np.clip(np.searchsorted(knots, u, side="right") - 1, 0, knots.size - 2))
    low, high = knots[i], knots[i + 1]
    tiny = 1e-9 * (high - low)
    if u - low <= tiny and velocity < 0 and i > 0:
        return knots[i - 1], low
    if high - u <= tiny and velocity > 0 and i < knots.size - 2:
        return high, knots[i + 2]
    return low, high


def reference_rod_end(dem: DemSurface, p: ArrayLike, n: ArrayLike, length: float,
                      tolerance: float = REFERENCE_TOLERANCE, restart: bool = True
                      ) -> tuple[np.ndarray, int]:
    """The geodesic from ``(p, n)`` over ``[0, length]`` by DOP853, restarted at knot lines.

    Returns the end xy, shape (2,), and the number of knot lines crossed.
    """
    knots = (np.unique(dem.spline.tck[1]), np.unique(dem.spline.tck[0]))  # x, y

    def field(_: float, state: np.ndarray) -> np.ndarray:
        gradient, hessian = dem.gradient(state[:2]), dem.hessian(state[:2])
        velocity = state[2:]
        curvature = velocity @ hessian @ velocity / (1.0 + gradient @ gradient)
        return np.concatenate([velocity, -gradient * curvature])

    state, t, crossings = np.concatenate([p, n]).astype(float), 0.0, 0
    while t < length:
        events = []
        if restart:
            for axis in range(2):
                low, high = _cell(knots[axis], state[axis], state[axis + 2])
                for line, direction in ((low, -1.0), (high, 1.0)):
                    def event(_: float, s: np.ndarray, a: int = axis, c: float = line) -> float:
                        return s[a] - c
                    event.terminal, event.direction = True, direction
                    events.append(event)
        solution = solve_ivp(field, (t, length), state, method="DOP853", rtol=tolerance,
                             atol=tolerance, events=events or None)
        if not solution.success:
            raise RuntimeError(f"solve_ivp failed: {solution.message}")
        hits = [(times[0], values[0]) for times, values in
                zip(solution.t_events or [], solution.y_events or []) if times.size]
        if hits:
            t, state = min(hits, key=lambda hit: hit[0])
            crossings += 1
        else:
            t, state = length, solution.y[:, -1]
    return np.asarray(state[:2]), crossings


def make_cases(dem: DemSurface, count: int, length: float, seed: int) -> list[Case]:
    """``count`` random rods at least ``length`` inside the grid, random headings."""
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1 = dem.bounds
    cases = []
    for _ in range(count):
        p = np.array([rng.uniform(x0 + length, x1 - length), rng.uniform(y0 + length, y1 - length)])
        heading = rng.normal(size=2)
        cases.append((p, heading, rod_normal(dem, p, heading)))
    return cases
