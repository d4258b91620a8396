"""Riemannian geometry of a graph surface: metric, geodesics, rods and the ideal formation.

All functions are pure and take the surface first (design §3). Points ``p`` and vectors are xy
coordinates, shape (2,). For ``z = F(x, y)`` the metric is
``g = I + ∇F ∇Fᵀ`` and geodesics solve ``ẍ = −∇F (ẋᵀ H ẋ) / (1 + |∇F|²)``.

Integrator
----------
Geodesics are integrated with Gragg–Bulirsch–Stoer extrapolation: each step of size ``H``
runs the modified midpoint rule with ``n = 2, 4, …, 12`` substeps and extrapolates the results
to ``h → 0`` with the Aitken–Neville scheme in ``h²``; the extrapolated value is an explicit
Runge–Kutta method of order 12, and the difference between the last two extrapolants (order
10) is the error estimate that adapts ``H`` (mixed tolerance ``1e-12·(1 + |y|)`` per step,
max norm over ``(x, y, ẋ, ẏ)``). The integrator is written once, as plain Python functions
marked ``register_jitable``: for the preset surfaces it runs compiled by numba (derivatives
from :func:`world.surfaces.preset_derivatives`), and for DEM surfaces too (the B-spline
evaluated by :func:`world.dem.spline_derivatives`); for any other surface the very same
functions run as Python, calling the surface's ``gradient``, ``hessian`` and ``contains``.

A DEM's spline is only C² across its knot lines, where the extrapolation's error estimate
would be misled. The surface may therefore bound each step (:func:`_step_limit`: a step ends
at most just past the next knot line, predicted to second order) and reject a step that ended
too far past one (:func:`_step_shrink`, retried shorter); a step cut short this way keeps the
error-controlled step size for the next one. For other surfaces both are no-ops.

Domain
------
Every evaluation of the right-hand side checks the surface's domain (``contains`` for custom
surfaces, the preset's own test for the hemisphere), that the derivatives are finite and that
the slope ``|∇F|`` is below 1e6 (where the graph is that close to vertical, as at the
hemisphere's rim, the xy chart degenerates and a geodesic could stall there unnoticed). An
evaluation that fails this makes the step fail; the step is shrunk, and the integration stops
with :class:`SurfaceDomainError` when an accepted step ends outside, or when the step size
falls below ``1e-12·t`` because every attempt leaves the domain.
"""
from __future__ import annotations

import math
import numbers
from collections.abc import Callable

import numba
import numpy as np
from numba.extending import overload, register_jitable
from numpy.typing import ArrayLike

from world.dem import (
    DEM_KIND,
    DemSurface,
    describe_domain,
    knot_step_limit,
    knot_step_shrink,
    spline_derivatives,
)
from world.surfaces import PRESETS, Surface, preset_derivatives, surface_leader_start

Context = tuple[int, np.ndarray] | Surface
"""A preset or a DEM as ``(kind, params)`` (compiled path), any other surface (Python path)."""


class SurfaceDomainError(ValueError):
    """A point or a geodesic lies outside the domain where the surface is defined."""


_OK, _LEFT_DOMAIN, _STEP_UNDERFLOW, _STEP_LIMIT = 0, 1, 2, 3
_STEP_COUNTS = (2, 4, 6, 8, 10, 12)
_EARLY_ROW = 2  # a cut-short step may stop after rows n = 2, 4, 6 (order 6)
_TOLERANCE = 1e-12
_SAFETY, _MIN_FACTOR, _MAX_FACTOR, _OUTSIDE_FACTOR = 0.9, 0.2, 4.0, 0.25
_MIN_STEP_FRACTION = 1e-12
_MAX_SLOPE_SQUARED = 1e12
_MAX_STEPS = 100_000
_COMPILED_TYPES = frozenset(PRESETS.values()) | {DemSurface}


def _surface_derivatives(ctx: Context, x: float,
                         y: float) -> tuple[bool, float, float, float, float, float]:
    """``(inside, Fx, Fy, Fxx, Fxy, Fyy)`` at ``(x, y)`` for either kind of context."""
    if isinstance(ctx, tuple):
        if ctx[0] == DEM_KIND:
            return spline_derivatives(ctx[1], x, y)
        return preset_derivatives(ctx[0], ctx[1], x, y)
    nan = math.nan
    p = np.array([x, y])
    contains = getattr(ctx, "contains", None)
    if not np.isfinite(p).all() or (contains is not None and not contains(p)):
        return False, nan, nan, nan, nan, nan
    gradient = np.asarray(ctx.gradient(p), dtype=float)
    hessian = np.asarray(ctx.hessian(p), dtype=float)
    if gradient.shape != (2,) or hessian.shape != (2, 2):
        raise ValueError(f"surface.gradient must return shape (2,) and surface.hessian shape "
                         f"(2, 2), got {gradient.shape} and {hessian.shape}")
    fxy = 0.5 * (float(hessian[0, 1]) + float(hessian[1, 0]))
    return (True, float(gradient[0]), float(gradient[1]), float(hessian[0, 0]), fxy,
            float(hessian[1, 1]))


# Numba wants the typing function and its implementation to have the same parameters,
# annotations included: the former receives numba types, the latter values, hence ``object``.
@overload(_surface_derivatives, jit_options={"cache": True})
def _surface_derivatives_compiled(ctx: object, x: object, y: object) -> Callable[..., tuple]:
    """Numba's version: in compiled code the context is a preset or DEM ``(kind, params)``."""
    def implementation(ctx: object, x: object, y: object) -> tuple:
        if ctx[0] == DEM_KIND:
            return spline_derivatives(ctx[1], x, y)
        return preset_derivatives(ctx[0], ctx[1], x, y)
    return implementation


def _step_limit(ctx: Context, state: np.ndarray, rate: np.ndarray) -> float:
    """Longest step the surface allows from ``state``: a DEM's knot lines, else no limit."""
    if isinstance(ctx, tuple) and ctx[0] == DEM_KIND:
        return knot_step_limit(ctx[1], state, rate)
    return math.inf


def _step_shrink(ctx: Context, state: np.ndarray, end: np.ndarray) -> float:
    """1 if a step from ``state`` to ``end`` is acceptable to the surface, else the fraction to
    retry it with (a DEM's knot lines, see :func:`world.dem.knot_step_shrink`)."""
    if isinstance(ctx, tuple) and ctx[0] == DEM_KIND:
        return knot_step_shrink(ctx[1], state, end)
    return 1.0


@overload(_step_limit, jit_options={"cache": True})
def _step_limit_compiled(ctx: object, state: object, rate: object) -> Callable[..., float]:
    """Numba's version of :func:`_step_limit` (the context is always a tuple there)."""
    def implementation(ctx: object, state: object, rate: object) -> float:
        if ctx[0] == DEM_KIND:
            return knot_step_limit(ctx[1], state, rate)
        return math.inf
    return implementation


@overload(_step_shrink, jit_options={"cache": True})
def _step_shrink_compiled(ctx: object, state: object, end: object) -> Callable[..., float]:
    """Numba's version of :func:`_step_shrink`."""
    def implementation(ctx: object, state: object, end: object) -> float:
        if ctx[0] == DEM_KIND:
            return knot_step_shrink(ctx[1], state, end)
        return 1.0
    return implementation


def _g_norm(fx: float, fy: float, ax: float, ay: float) -> float:
    """Length of the vector ``a`` in the metric with gradient ``(fx, fy)``."""
    slope = fx * ax + fy * ay
    return math.sqrt(ax * ax + ay * ay + slope * slope)


def _rod_direction(fx: float, fy: float, hx: float, hy: float,
                   side: int) -> tuple[float, float]:
    """g-unit rod normal for heading ``h``: ``side·unit_g(w − g(w,h)/g(h,h)·h)``, ``w = Jh``."""
    wx, wy = -hy, hx
    slope_h = fx * hx + fy * hy
    g_wh = (fx * wx + fy * wy) * slope_h
    g_hh = hx * hx + hy * hy + slope_h * slope_h
    mx, my = wx - g_wh / g_hh * hx, wy - g_wh / g_hh * hy
    norm = _g_norm(fx, fy, mx, my)
    return side * mx / norm, side * my / norm


def _heading_direction(fx: float, fy: float, ux: float, uy: float,
                       side: int) -> tuple[float, float]:
    """g-unit heading ``h`` with ``g(h, u) = 0`` whose rod normal on ``side`` is ``u``.

    ``h ∝ −side·J(g u)`` (``J`` the +90° rotation): it is g-orthogonal to ``u`` because
    ``(J a)·a = 0``, and ``g(J h, u) = side·|g u|² / norm > 0`` fixes the sign.
    """
    slope_u = fx * ux + fy * uy
    gux, guy = ux + fx * slope_u, uy + fy * slope_u
    hx, hy = side * guy, -side * gux
    norm = _g_norm(fx, fy, hx, hy)
    return hx / norm, hy / norm


@register_jitable
def _rhs(ctx: Context, state: np.ndarray, out: np.ndarray) -> bool:
    """Geodesic vector field at ``state = (x, y, ẋ, ẏ)`` into ``out``; False if undefined there."""
    inside, fx, fy, fxx, fxy, fyy = _surface_derivatives(ctx, state[0], state[1])
    vx, vy = state[2], state[3]
    curvature = (fxx * vx * vx + 2.0 * fxy * vx * vy + fyy * vy * vy) / (1.0 + fx * fx + fy * fy)
    out[0] = vx
    out[1] = vy
    out[2] = -fx * curvature
    out[3] = -fy * curvature
    return (inside and math.isfinite(out[2]) and math.isfinite(out[3])
            and fx * fx + fy * fy < _MAX_SLOPE_SQUARED)


@register_jitable
def _modified_midpoint(ctx: Context, start: np.ndarray, f_start: np.ndarray, big_h: float,
                       n: int, previous: np.ndarray, current: np.ndarray,
                       slope: np.ndarray) -> bool:
    """Gragg's modified midpoint rule, ``n`` substeps over ``big_h``; the result is ``current``."""
    h = big_h / n
    for i in range(4):
        previous[i] = start[i]
        current[i] = start[i] + h * f_start[i]
    for _ in range(n - 1):
        if not _rhs(ctx, current, slope):
            return False
        for i in range(4):
            following = previous[i] + 2.0 * h * slope[i]
            previous[i] = current[i]
            current[i] = following
    return True


@register_jitable
def _scaled_error(start: np.ndarray, table: np.ndarray, row: int) -> float:
    """Error estimate of extrapolation row ``row``: ``|T[row,row] − T[row,row−1]|`` scaled by
    the mixed tolerance, max over the components."""
    error = 0.0
    for i in range(4):
        scale = _TOLERANCE * (1.0 + max(abs(start[i]), abs(table[row, row, i])))
        error = max(error, abs(table[row, row, i] - table[row, row - 1, i]) / scale)
    return error


@register_jitable
def _extrapolation_step(ctx: Context, start: np.ndarray, f_start: np.ndarray, big_h: float,
                        early: bool, table: np.ndarray, previous: np.ndarray,
                        current: np.ndarray, slope: np.ndarray) -> tuple[bool, float, int]:
    """One GBS step; the result is ``table[row, row]``, shape (4,).

    ``table[j, k]`` is the Aitken–Neville extrapolant from midpoint rows ``j−k … j``. With
    ``early``, the step stops at the first row ``j >= _EARLY_ROW`` whose error estimate is
    within tolerance (used for steps the surface cut short, often tiny); otherwise it uses
    every row. Returns whether every evaluation was defined, the scaled error estimate and
    the row of the result.
    """
    rows = len(_STEP_COUNTS)
    for j in range(rows):
        n_j = _STEP_COUNTS[j]
        if not _modified_midpoint(ctx, start, f_start, big_h, n_j, previous, current, slope):
            return False, math.inf, j
        for i in range(4):
            table[j, 0, i] = current[i]
        for k in range(1, j + 1):
            ratio = n_j / _STEP_COUNTS[j - k]
            denominator = ratio * ratio - 1.0
            for i in range(4):
                table[j, k, i] = (table[j, k - 1, i]
                                  + (table[j, k - 1, i] - table[j - 1, k - 1, i]) / denominator)
        if early and _EARLY_ROW <= j < rows - 1 and _scaled_error(start, table, j) <= 1.0:
            return True, _scaled_error(start, table, j), j
    error = _scaled_error(start, table, rows - 1)
    return math.isfinite(error), error, rows - 1


@register_jitable
def _geodesic_flow(ctx: Context, state: np.ndarray, t: float) -> int:
    """Advance ``state = (x, y, ẋ, ẏ)`` in place along the geodesic over ``[0, t]``.

    Returns a status code; on failure ``state`` is the last accepted state (or, when an
    accurate step ends outside the domain, that end).
    """
    rows = len(_STEP_COUNTS)
    f_start, f_end = np.empty(4), np.empty(4)
    previous, current, slope = np.empty(4), np.empty(4), np.empty(4)
    table = np.empty((rows, rows, 4))
    if not _rhs(ctx, state, f_start):
        return _LEFT_DOMAIN
    if t == 0.0:
        return _OK
    exponent = 1.0 / (2 * rows - 1)
    done, big_h = 0.0, t
    retry = math.inf  # a shorter step the surface asked for after rejecting one
    for _ in range(_MAX_STEPS):
        step = min(big_h, retry, _step_limit(ctx, state, f_start))
        retry = math.inf
        cut = step < big_h  # the surface cut this step short (never for presets)
        last = step >= t - done
        if last:
            step, cut = t - done, False
        inside, error, row = _extrapolation_step(ctx, state, f_start, step, cut, table,
                                                 previous, current, slope)
        if inside and error <= 1.0:
            shrink = _step_shrink(ctx, state, table[row, row])
            if shrink < 1.0:
                retry = step * shrink
                continue
            for i in range(4):
                state[i] = table[row, row, i]
            if not _rhs(ctx, state, f_end):
                return _LEFT_DOMAIN
            if last:
                return _OK
            for i in range(4):
                f_start[i] = f_end[i]
            done += step
            if cut:
                continue  # keep the error-controlled size for the next step
            if error == 0.0:
                big_h = step * _MAX_FACTOR
            else:
                big_h = step * min(_MAX_FACTOR, _SAFETY * error ** -exponent)
        else:
            if inside:
                big_h = step * max(_MIN_FACTOR, _SAFETY * error ** -exponent)
            else:
                big_h = step * _OUTSIDE_FACTOR
            if big_h < _MIN_STEP_FRACTION * t:
                return _STEP_UNDERFLOW if inside else _LEFT_DOMAIN
    return _STEP_LIMIT


@register_jitable
def _integrate_state(ctx: Context, x: float, y: float, vx: float, vy: float,
                     t: float) -> tuple[int, float, float, float, float]:
    """``(status, x, y, ẋ, ẏ)`` after following the geodesic from ``(x, y, ẋ, ẏ)`` for ``t``."""
    state = np.empty(4)
    state[0], state[1], state[2], state[3] = x, y, vx, vy
    status = _geodesic_flow(ctx, state, t)
    return status, state[0], state[1], state[2], state[3]


_integrate_state_compiled = numba.njit(cache=True)(_integrate_state)


def _context(surface: Surface) -> Context:
    """``(kind, params)`` for an exact preset or DEM type, else the surface itself (Python path)."""
    if type(surface) in _COMPILED_TYPES:
        return surface.kind, surface.params
    if isinstance(surface, type) or not isinstance(surface, Surface):
        raise ValueError(f"surface must have height, gradient and hessian methods, "
                         f"got {type(surface).__name__}")
    return surface


def _vector(value: ArrayLike, name: str, size: int = 2) -> np.ndarray:
    vector = np.asarray(value, dtype=float)
    if vector.shape != (size,) or not np.isfinite(vector).all():
        raise ValueError(f"{name} must be {size} finite numbers, got {value!r}")
    return vector


def _heading(value: ArrayLike, name: str = "heading") -> np.ndarray:
    heading = _vector(value, name)
    if not heading.any():
        raise ValueError(f"{name} must be a nonzero vector, got {value!r}")
    return heading


def _real(value: float, name: str, *, strictly_positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if value < 0 or (strictly_positive and value == 0):
        raise ValueError(f"{name} must be {'> 0' if strictly_positive else '>= 0'}, "
                         f"got {value!r}")
    return float(value)


def _count(value: int, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _side(side: int) -> int:
    if isinstance(side, bool) or side not in (1, -1):
        raise ValueError(f"side must be +1 (left) or -1 (right), got {side!r}")
    return int(side)


def _check_status(status: int, x: float, y: float, what: str) -> None:
    """Turn an integrator status into the matching exception."""
    where = f"near (x, y) = ({x:.6g}, {y:.6g})"
    if status == _LEFT_DOMAIN:
        raise SurfaceDomainError(f"{what} leaves the surface's domain {where} (contains() is "
                                 "false, the derivatives are not finite or |∇F| > 1e6)")
    if status == _STEP_UNDERFLOW:
        raise RuntimeError(f"{what}: the geodesic integrator's step size underflowed {where}")
    if status == _STEP_LIMIT:
        raise RuntimeError(f"{what}: the geodesic integrator took more than {_MAX_STEPS} "
                           f"steps, stopping {where}")


def _flow(ctx: Context, p: np.ndarray, v: np.ndarray, t: float,
          what: str) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled or the Python integrator; raise on failure."""
    integrate = _integrate_state_compiled if isinstance(ctx, tuple) else _integrate_state
    status, x, y, vx, vy = integrate(ctx, p[0], p[1], v[0], v[1], t)
    _check_status(status, x, y, what)
    return np.array([x, y]), np.array([vx, vy])


def _gradient_inside(ctx: Context, p: np.ndarray, name: str) -> tuple[float, float]:
    inside, fx, fy, _, _, _ = _surface_derivatives(ctx, float(p[0]), float(p[1]))
    if not inside:
        where = (f"the DEM grid {describe_domain(ctx[1])}"
                 if isinstance(ctx, tuple) and ctx[0] == DEM_KIND else "the surface's domain")
        raise SurfaceDomainError(f"{name} = ({p[0]:.6g}, {p[1]:.6g}) lies outside {where}")
    return fx, fy


def _normal_at(ctx: Context, p: np.ndarray, heading: np.ndarray, side: int) -> np.ndarray:
    fx, fy = _gradient_inside(ctx, p, "p")
    return np.array(_rod_direction(fx, fy, heading[0], heading[1], side))


def metric(surface: Surface, p: ArrayLike) -> np.ndarray:
    """The metric ``g = I + ∇F ∇Fᵀ`` at ``p``.

    Parameters
    ----------
    surface : Surface
    p : array_like, shape (2,)

    Returns
    -------
    ndarray, shape (2, 2)
    """
    gradient = np.asarray(surface.gradient(_vector(p, "p")), dtype=float)
    if gradient.shape != (2,):
        raise ValueError(f"surface.gradient must return shape (2,), got {gradient.shape}")
    return np.eye(2) + np.outer(gradient, gradient)


def integrate_geodesic(surface: Surface, p: ArrayLike, v: ArrayLike,
                       t: float) -> tuple[np.ndarray, np.ndarray]:
    """Follow the geodesic from position ``p`` with coordinate velocity ``v`` for time ``t``.

    The velocity is used as given (not normalised), so the arc length is ``t·|v|_g``.

    Parameters
    ----------
    surface : Surface
    p, v : array_like, shape (2,)
        Start position and coordinate velocity.
    t : float
        Duration, ``t >= 0``.

    Returns
    -------
    p_end, v_end : ndarray, shape (2,)
        Position and coordinate velocity at ``t``.

    Raises
    ------
    SurfaceDomainError
        If the geodesic leaves the surface's domain before ``t``.
    """
    ctx = _context(surface)
    duration = _real(t, "t", strictly_positive=False)
    return _flow(ctx, _vector(p, "p"), _vector(v, "v"), duration, "geodesic")


def geodesic_points(surface: Surface, p: ArrayLike, v: ArrayLike, t: float,
                    pieces: int) -> np.ndarray:
    """Points of the geodesic from ``p`` with coordinate velocity ``v`` at parameters
    ``0, t/pieces, …, t`` (the integration continues from each point to the next).

    Returns
    -------
    ndarray, shape (pieces + 1, 2)

    Raises
    ------
    SurfaceDomainError
        If the geodesic leaves the surface's domain before ``t``.
    """
    ctx = _context(surface)
    point, velocity = _vector(p, "p"), _vector(v, "v")
    step = _real(t, "t", strictly_positive=False) / _count(pieces, "pieces", 1)
    points = [point]
    for _ in range(pieces):
        point, velocity = _flow(ctx, point, velocity, step, "geodesic")
        points.append(point)
    return np.array(points)


def rod_normal(surface: Surface, p: ArrayLike, heading: ArrayLike, side: int = 1) -> np.ndarray:
    """Unit (in g) rod direction at ``p`` for ``heading``, g-orthogonal to it.

    ``w = (−h_y, h_x)``, ``n = side·unit_g(w − g(w,h)/g(h,h)·h)``: ``side = +1`` is the
    left of the heading, ``−1`` the right.

    Parameters
    ----------
    surface : Surface
    p, heading : array_like, shape (2,)
        Position and (nonzero) heading, any length.
    side : {1, -1}

    Returns
    -------
    ndarray, shape (2,)
    """
    return _normal_at(_context(surface), _vector(p, "p"), _heading(heading), _side(side))


def rod_end(surface: Surface, p: ArrayLike, heading: ArrayLike, length: float,
            side: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """End of the rod of ``length`` held at ``p``: ``exp_p(length·n)``, n the rod normal.

    Parameters
    ----------
    surface : Surface
    p, heading : array_like, shape (2,)
        The holder's position and (nonzero) heading.
    length : float
        Rod length (Riemannian), ``>= 0``.
    side : {1, -1}

    Returns
    -------
    end : ndarray, shape (2,)
        The rod end.
    u : ndarray, shape (2,)
        g-unit tangent of the rod geodesic at its end (pointing away from ``p``).

    Raises
    ------
    SurfaceDomainError
        If ``p`` or the rod leaves the surface's domain.
    """
    ctx = _context(surface)
    point, h = _vector(p, "p"), _heading(heading)
    rod_length = _real(length, "length", strictly_positive=False)
    n = _normal_at(ctx, point, h, _side(side))
    end, velocity = _flow(ctx, point, n, rod_length, "rod")
    fx, fy = _gradient_inside(ctx, end, "the rod end")
    return end, velocity / _g_norm(fx, fy, velocity[0], velocity[1])


def heading_at_rod_end(surface: Surface, end: ArrayLike, u: ArrayLike,
                       side: int = 1) -> np.ndarray:
    """Heading of an agent standing at a rod end so that its own rod continues the geodesic.

    Parameters
    ----------
    surface : Surface
    end : array_like, shape (2,)
        The rod end.
    u : array_like, shape (2,)
        The rod's tangent there (nonzero; only its direction matters).
    side : {1, -1}
        The side both rods are held on.

    Returns
    -------
    ndarray, shape (2,)
        g-unit ``h`` with ``g(h, u) = 0`` and ``rod_normal(surface, end, h, side) ∥ u``
        (equal for g-unit ``u``).
    """
    ctx = _context(surface)
    point, tangent = _vector(end, "end"), _heading(u, "u")
    fx, fy = _gradient_inside(ctx, point, "end")
    return np.array(_heading_direction(fx, fy, tangent[0], tangent[1], _side(side)))


def column(surface: Surface, leader: ArrayLike, heading: ArrayLike, n_followers: int,
           spacing: float, side: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Chained rod ends behind one leader pose: the ideal column at one instant.

    Returns
    -------
    positions, headings : ndarray, shape (n_followers + 1, 2)
        Row 0 the leader's pose; row ``k`` the rod end of agent ``k−1`` and the heading of
        :func:`heading_at_rod_end` there.
    """
    positions = np.empty((n_followers + 1, 2))
    headings = np.empty((n_followers + 1, 2))
    positions[0], headings[0] = leader, heading
    for k in range(1, n_followers + 1):
        positions[k], u = rod_end(surface, positions[k - 1], headings[k - 1], spacing, side)
        headings[k] = heading_at_rod_end(surface, positions[k], u, side)
    return positions, headings


def ideal_formation(surface: Surface, leader_start: ArrayLike | None, n_followers: int,
                    spacing: float, comm_period: float, n_ticks: int,
                    side: int = 1, *, until_domain_exit: bool = False) -> np.ndarray:
    """Ideal xy positions of the leader and its followers at ticks ``0 … n_ticks−1``.

    The leader follows the geodesic from ``leader_start``; at each tick ``t_j = j·comm_period``
    follower ``k`` sits at the rod end of agent ``k−1``, whose heading is the leader's velocity
    for ``k = 1`` and :func:`heading_at_rod_end` otherwise.

    Parameters
    ----------
    surface : Surface
    leader_start : array_like, shape (4,), or None
        ``(x, y, vx, vy)``; None takes the surface's default (see
        :func:`world.surfaces.surface_leader_start`).
    n_followers : int
        ``>= 0``.
    spacing : float
        Rod length ``d > 0``.
    comm_period : float
        ``T_c > 0``.
    n_ticks : int
        ``>= 1``.
    side : {1, -1}
    until_domain_exit : bool
        If the formation leaves the surface's domain, fill that tick and all later ones with
        NaN instead of raising :class:`SurfaceDomainError`.

    Returns
    -------
    ndarray, shape (n_followers + 1, n_ticks, 2)
        Row 0 the leader, row ``k`` follower ``k``.
    """
    _context(surface)  # rejects a non-surface before any other work
    if leader_start is None:
        leader_start = surface_leader_start(surface)
        if leader_start is None:
            raise ValueError("leader_start is required: the surface has no default_leader_start")
    start = _vector(leader_start, "leader_start", size=4)
    followers = _count(n_followers, "n_followers", 0)
    d = _real(spacing, "spacing", strictly_positive=True)
    period = _real(comm_period, "comm_period", strictly_positive=True)
    ticks = _count(n_ticks, "n_ticks", 1)
    rod_side = _side(side)
    if followers and not np.any(start[2:]):
        raise ValueError("leader_start must have a nonzero velocity when there are followers")
    formation = np.full((followers + 1, ticks, 2), np.nan)
    position, velocity = start[:2], start[2:]
    for j in range(ticks):
        try:
            if j:
                position, velocity = integrate_geodesic(surface, position, velocity, period)
            formation[:, j] = column(surface, position, velocity, followers, d, rod_side)[0]
        except SurfaceDomainError:
            if not until_domain_exit:
                raise
            break
    return formation
