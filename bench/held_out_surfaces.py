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
