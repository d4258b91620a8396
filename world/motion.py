"""A unicycle robot on the surface: the world's model of a driving follower (design §4 "Motion").

The robot's state is its position ``p = (x, y)`` and its heading ``h``, a tangent vector of
unit length in the metric ``g = I + ∇F ∇Fᵀ``. It is commanded by a forward speed ``v``
(metres of arc along the surface per time unit; negative: reversing) and a turn rate ``ω``
(radians per time unit, an angle measured in the metric), held for one control step. Its
motion is

    ẋ = v h,        ḣᵏ = −Γᵏᵢⱼ ẋⁱ hʲ + ω (J h)ᵏ,

the heading parallel-transported along the path (for a graph ``Γᵏᵢⱼ = Fₖ Fᵢⱼ / (1 + |∇F|²)``,
so the transport term is ``−v ∇F (hᵀ H h) / (1 + |∇F|²)``) and rotated by ``ω`` in the tangent
plane: ``J h = √det g · g⁻¹ E h`` (``E`` the +90° rotation of the plane) is ``h`` turned by
+90° in the metric (g-orthogonal to ``h``, of the same g-length, positively oriented). With
``ω = 0`` the robot drives a geodesic; ``g(h, h)`` is conserved, so the path's arc length is
``|v|·t``.

Integration: the classical fourth-order Runge–Kutta method with fixed substeps, at most
:data:`ARC_STEP` metres of arc and :data:`TURN_STEP` radians of turn each (a test shows that
halving them moves a whole run by less than 1e-6 m), the heading put back to unit g-length at
the end of each control step. The right-hand side evaluates the surface with
:mod:`world.geometry`'s derivative evaluation, compiled by numba for the presets and DEMs,
plain Python for any other surface.
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba.extending import register_jitable
from numpy.typing import ArrayLike

from world.geometry import (
    _LEFT_DOMAIN,
    _MAX_SLOPE_SQUARED,
    _OK,
    Context,
    SurfaceDomainError,
    _check_status,
    _context,
    _surface_derivatives,
)
from world.surfaces import Surface

ARC_STEP = 0.02
"""Longest substep, in metres of arc along the surface."""
TURN_STEP = 0.02
"""Longest substep, in radians of commanded turn."""


@register_jitable
def _unicycle_rhs(ctx: Context, state: np.ndarray, v: float, omega: float,
                  out: np.ndarray) -> bool:
    """``(ẋ, ẏ, ḣx, ḣy)`` at ``state = (x, y, hx, hy)`` into ``out``; False if undefined."""
    inside, fx, fy, fxx, fxy, fyy = _surface_derivatives(ctx, state[0], state[1])
    hx, hy = state[2], state[3]
    q = 1.0 + fx * fx + fy * fy
    transport = v * (fxx * hx * hx + 2.0 * fxy * hx * hy + fyy * hy * hy) / q
    # J h = sqrt(q) g^-1 (E h), E h = (-hy, hx), g^-1 a = a - grad (grad . a) / q
    ax, ay = -hy, hx
    slope = (fx * ax + fy * ay) / q
    turn = omega * math.sqrt(q)
    out[0] = v * hx
    out[1] = v * hy
    out[2] = -fx * transport + turn * (ax - fx * slope)
    out[3] = -fy * transport + turn * (ay - fy * slope)
    return (inside and math.isfinite(out[2]) and math.isfinite(out[3])
            and fx * fx + fy * fy < _MAX_SLOPE_SQUARED)


@register_jitable
def _drive_state(ctx: Context, x: float, y: float, hx: float, hy: float, v: float, omega: float,
                 duration: float, substeps: int) -> tuple[int, float, float, float, float]:
    """``(status, x, y, hx, hy)`` after ``substeps`` RK4 steps over ``duration``."""
    state, stage = np.empty(4), np.empty(4)
    k1, k2, k3, k4 = np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    state[0], state[1], state[2], state[3] = x, y, hx, hy
    h = duration / substeps
    for _ in range(substeps):
        if not _unicycle_rhs(ctx, state, v, omega, k1):
            return _LEFT_DOMAIN, state[0], state[1], state[2], state[3]
        for i in range(4):
            stage[i] = state[i] + 0.5 * h * k1[i]
        if not _unicycle_rhs(ctx, stage, v, omega, k2):
            return _LEFT_DOMAIN, state[0], state[1], state[2], state[3]
        for i in range(4):
            stage[i] = state[i] + 0.5 * h * k2[i]
        if not _unicycle_rhs(ctx, stage, v, omega, k3):
            return _LEFT_DOMAIN, state[0], state[1], state[2], state[3]
        for i in range(4):
            stage[i] = state[i] + h * k3[i]
        if not _unicycle_rhs(ctx, stage, v, omega, k4):
            return _LEFT_DOMAIN, state[0], state[1], state[2], state[3]
        for i in range(4):
            state[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    if not _unicycle_rhs(ctx, state, v, omega, k1):  # the end must be on the surface too
        return _LEFT_DOMAIN, state[0], state[1], state[2], state[3]
    return _OK, state[0], state[1], state[2], state[3]


_drive_state_compiled = numba.njit(cache=True)(_drive_state)


def substeps(v: float, omega: float, duration: float) -> int:
    """How many RK4 substeps a control step takes: at most :data:`ARC_STEP` of arc and
    :data:`TURN_STEP` of turn each."""
    return max(1, math.ceil(max(abs(v) * duration / ARC_STEP, abs(omega) * duration / TURN_STEP)))


def unit_heading(surface: Surface, p: ArrayLike, heading: ArrayLike) -> np.ndarray:
    """``heading`` scaled to unit length in the metric at ``p``."""
    fx, fy = (float(c) for c in np.asarray(surface.gradient(np.asarray(p, dtype=float))))
    h = np.asarray(heading, dtype=float)
    norm = math.sqrt(h[0] ** 2 + h[1] ** 2 + (fx * h[0] + fy * h[1]) ** 2)
    if not norm > 0 or not math.isfinite(norm):
        raise ValueError(f"heading must be a nonzero finite vector, got {heading!r}")
    return h / norm


def drive(surface: Surface, p: ArrayLike, heading: ArrayLike, v: float, omega: float,
          duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Drive the unicycle at speed ``v`` and turn rate ``ω`` for ``duration``.

    Parameters
    ----------
    surface : Surface
    p : array_like, shape (2,)
        Start position.
    heading : array_like, shape (2,)
        Start heading (nonzero; scaled to unit g-length here).
    v : float
        Forward speed, metres of arc per time unit (negative: reversing).
    omega : float
        Turn rate, radians (in the metric) per time unit, positive to the left.
    duration : float
        ``>= 0``.

    Returns
    -------
    p_end, h_end : ndarray, shape (2,)
        Position and g-unit heading at the end.

    Raises
    ------
    SurfaceDomainError
        If the path leaves the surface's domain.
    """
    for name, value in (("v", v), ("omega", omega), ("duration", duration)):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value!r}")
    if duration < 0:
        raise ValueError(f"duration must be >= 0, got {duration!r}")
    point = np.asarray(p, dtype=float)
    h = unit_heading(surface, point, heading)
    if duration == 0:
        return point.copy(), h
    ctx = _context(surface)
    integrate = _drive_state_compiled if isinstance(ctx, tuple) else _drive_state
    status, x, y, hx, hy = integrate(ctx, float(point[0]), float(point[1]), float(h[0]),
                                     float(h[1]), float(v), float(omega), float(duration),
                                     substeps(v, omega, duration))
    _check_status(status, x, y, "the robot's path")
    end = np.array([x, y])
    return end, unit_heading(surface, end, (hx, hy))


__all__ = ["ARC_STEP", "SurfaceDomainError", "TURN_STEP", "drive", "substeps", "unit_heading"]
