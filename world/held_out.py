"""Held-out surfaces of this benchmark's own (``world.held_out:crossed_waves``,
``slanted_folds``, ``dunes``, ``bowl_ridge``, ``egg_crate``, ``tilted_bump``, ``terraces``,
``twin_hills``, ``twisted_saddle`` and ``long_waves``); each class says when it was defined and
what it was used for.

``crossed_waves`` was defined after ``auto``'s candidates and rules were chosen and never used to
choose them: a gentle slope with crossed waves of two wavelengths, driven across obliquely.
``slanted_folds`` was defined before ``auto``'s inverse-error blend was designed.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike


class CrossedWaves:
    """``F = 0.05 x + 0.8 sin(x/4) cos(y/5)``."""

    default_leader_start = (-20.0, 3.0, 0.98, 0.2)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.05 * x + 0.8 * math.sin(x / 4) * math.cos(y / 5)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        return np.array([0.05 + 0.2 * math.cos(x / 4) * math.cos(y / 5),
                         -0.16 * math.sin(x / 4) * math.sin(y / 5)])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        fxx = -0.05 * math.sin(x / 4) * math.cos(y / 5)
        fxy = -0.04 * math.cos(x / 4) * math.sin(y / 5)
        fyy = -0.032 * math.sin(x / 4) * math.cos(y / 5)
        return np.array([[fxx, fxy], [fxy, fyy]])


crossed_waves = CrossedWaves()


class SlantedFolds:
    """``F = 0.04 x + 0.6 sin(x/6 + y/8) + 0.002 y²``: oblique folds on a slope, a gentle trough.

    Defined before ``auto``'s inverse-error blend (see the README) was designed and not looked
    at while designing it.
    """

    default_leader_start = (-20.0, -2.0, 0.98, 0.2)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.04 * x + 0.6 * math.sin(x / 6 + y / 8) + 0.002 * y * y

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        c = math.cos(x / 6 + y / 8)
        return np.array([0.04 + 0.1 * c, 0.075 * c + 0.004 * y])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        s = math.sin(x / 6 + y / 8)
        return np.array([[-0.6 / 36 * s, -0.6 / 48 * s], [-0.6 / 48 * s, -0.6 / 64 * s + 0.004]])


slanted_folds = SlantedFolds()


class Dunes:
    """``F = 0.7 sin(x/5) sin(x/13 + y/7) + 0.03 y``: skewed dunes on a cross slope.

    Defined after the own-motion candidates ``gp-motion`` and ``gp-ratio`` were added to
    ``auto`` (which were screened on the surfaces above), and not used to choose anything.
    """

    default_leader_start = (-20.0, 0.0, 0.98, 0.2)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.7 * math.sin(x / 5) * math.sin(x / 13 + y / 7) + 0.03 * y

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        s1, c1 = math.sin(x / 5), math.cos(x / 5)
        s2, c2 = math.sin(x / 13 + y / 7), math.cos(x / 13 + y / 7)
        return np.array([0.7 * (c1 * s2 / 5 + s1 * c2 / 13), 0.1 * s1 * c2 + 0.03])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        s1, c1 = math.sin(x / 5), math.cos(x / 5)
        s2, c2 = math.sin(x / 13 + y / 7), math.cos(x / 13 + y / 7)
        fxx = 0.7 * (-s1 * s2 * (1 / 25 + 1 / 169) + 2 * c1 * c2 / 65)
        fxy = 0.7 * (c1 * c2 / 35 - s1 * s2 / 91)
        fyy = -0.7 * s1 * s2 / 49
        return np.array([[fxx, fxy], [fxy, fyy]])


dunes = Dunes()


class BowlRidge:
    """``F = 0.003 (x² + 2 y²) + 0.4 cos((x - y)/3)``: a shallow oval bowl with diagonal
    ridges. Defined with :class:`Dunes`, under the same rule."""

    default_leader_start = (-25.0, 4.0, 1.0, -0.1)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.003 * (x * x + 2 * y * y) + 0.4 * math.cos((x - y) / 3)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        s = math.sin((x - y) / 3)
        return np.array([0.006 * x - 0.4 * s / 3, 0.012 * y + 0.4 * s / 3])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        c = 0.4 * math.cos((x - y) / 3) / 9
        return np.array([[0.006 - c, c], [c, 0.012 - c]])


bowl_ridge = BowlRidge()


class EggCrate:
    """``F = 0.5 sin(x/3) sin(y/3)``: an egg crate, more strongly curved than the others.

    Defined after ``auto``'s last change and before ``auto-mix``; looked at while weighing
    ``auto-mix`` (never used to choose its constants).
    """

    default_leader_start = (-20.0, 1.0, 1.0, 0.05)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.5 * math.sin(x / 3) * math.sin(y / 3)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        return np.array([0.5 / 3 * math.cos(x / 3) * math.sin(y / 3),
                         0.5 / 3 * math.sin(x / 3) * math.cos(y / 3)])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        diagonal = -0.5 / 9 * math.sin(x / 3) * math.sin(y / 3)
        mixed = 0.5 / 9 * math.cos(x / 3) * math.cos(y / 3)
        return np.array([[diagonal, mixed], [mixed, diagonal]])


egg_crate = EggCrate()


class TiltedBump:
    """``F = 0.2 x + 0.1 y + 0.5 exp(-((x - 5)² + y²)/30)``: a steep plane with one bump.
    Defined and used with :class:`EggCrate`."""

    default_leader_start = (-20.0, -3.0, 1.0, 0.1)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.2 * x + 0.1 * y + 0.5 * math.exp(-((x - 5) ** 2 + y * y) / 30)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        g = 0.5 * math.exp(-((x - 5) ** 2 + y * y) / 30)
        return np.array([0.2 - g * (x - 5) / 15, 0.1 - g * y / 15])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        g = 0.5 * math.exp(-((x - 5) ** 2 + y * y) / 30)
        a, b = (x - 5) / 15, y / 15
        return np.array([[g * (a * a - 1 / 15), g * a * b], [g * a * b, g * (b * b - 1 / 15)]])


tilted_bump = TiltedBump()


class Terraces:
    """``F = 0.6 tanh(2 sin(x/4)) + 0.05 y``: rounded terraces, crossed at an angle.

    Defined after ``auto-mix``, together with :class:`TwinHills`, and used for nothing but the
    benchmark's check.
    """

    default_leader_start = (-20.0, -1.0, 1.0, 0.15)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.6 * math.tanh(2 * math.sin(x / 4)) + 0.05 * y

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        sech2 = 1 - math.tanh(2 * math.sin(x / 4)) ** 2
        return np.array([0.6 * sech2 * 0.5 * math.cos(x / 4), 0.05])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        t = math.tanh(2 * math.sin(x / 4))
        sech2 = 1 - t * t
        u_x = 0.5 * math.cos(x / 4)  # d/dx of 2 sin(x/4)
        u_xx = -0.125 * math.sin(x / 4)
        fxx = 0.6 * (-2 * t * sech2 * u_x * u_x + sech2 * u_xx)
        return np.array([[fxx, 0.0], [0.0, 0.0]])


terraces = Terraces()


class TwinHills:
    """``F = exp(-((x+6)² + (y-3)²)/40) + 0.8 exp(-((x-8)² + (y+2)²)/25)``: two hills the
    column passes between. Defined with :class:`Terraces`, under the same rule."""

    default_leader_start = (-22.0, 0.0, 1.0, 0.02)
    _hills = ((-6.0, 3.0, 1.0, 40.0), (8.0, -2.0, 0.8, 25.0))  # centre x, y, height, width

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return sum(h * math.exp(-((x - cx) ** 2 + (y - cy) ** 2) / w)
                   for cx, cy, h, w in self._hills)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        out = np.zeros(2)
        for cx, cy, h, w in self._hills:
            g = h * math.exp(-((x - cx) ** 2 + (y - cy) ** 2) / w)
            out += -2 * g / w * np.array([x - cx, y - cy])
        return out

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        out = np.zeros((2, 2))
        for cx, cy, h, w in self._hills:
            g = h * math.exp(-((x - cx) ** 2 + (y - cy) ** 2) / w)
            d = np.array([x - cx, y - cy])
            out += g * (4 * np.outer(d, d) / (w * w) - 2 * np.eye(2) / w)
        return out


twin_hills = TwinHills()


class TwistedSaddle:
    """``F = 0.015 x y + 0.3 sin(y/3)``: a twisted saddle with ridges along x.

    Defined after the leverage rule of ``auto`` and ``auto-mix``, together with
    :class:`LongWaves`, and used for nothing but the check of that rule.
    """

    default_leader_start = (-20.0, 2.0, 1.0, 0.05)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 0.015 * x * y + 0.3 * math.sin(y / 3)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        return np.array([0.015 * y, 0.015 * x + 0.1 * math.cos(y / 3)])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        return np.array([[0.0, 0.015], [0.015, -0.1 / 3 * math.sin(y / 3)]])


twisted_saddle = TwistedSaddle()


class LongWaves:
    """``F = 1.2 sin(x/9) + 0.4 sin(y/6 - x/15)``: long swells with a crossing chop.
    Defined with :class:`TwistedSaddle`, under the same rule."""

    default_leader_start = (-20.0, -1.0, 1.0, 0.1)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return 1.2 * math.sin(x / 9) + 0.4 * math.sin(y / 6 - x / 15)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        c = math.cos(y / 6 - x / 15)
        return np.array([1.2 / 9 * math.cos(x / 9) - 0.4 / 15 * c, 0.4 / 6 * c])

    def hessian(self, p: ArrayLike) -> np.ndarray:
        x, y = np.asarray(p, dtype=float)
        s = math.sin(y / 6 - x / 15)
        fxx = -1.2 / 81 * math.sin(x / 9) - 0.4 / 225 * s
        fxy = 0.4 / 90 * s
        fyy = -0.4 / 36 * s
        return np.array([[fxx, fxy], [fxy, fyy]])


long_waves = LongWaves()
