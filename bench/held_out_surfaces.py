"""Held-out surfaces of this benchmark's own (``bench.held_out_surfaces:crossed_waves`` and
``bench.held_out_surfaces:slanted_folds``).

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
