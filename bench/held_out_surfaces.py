"""A held-out surface of this benchmark's own (``bench.held_out_surfaces:crossed_waves``).

Defined after ``auto``'s candidates and rules were chosen and never used to choose them: a
gentle slope with crossed waves of two wavelengths, driven across obliquely.
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
