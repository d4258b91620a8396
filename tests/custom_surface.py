"""A user-defined surface, loaded by the tests as ``tests.custom_surface:...`` (design §3)."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


class Bowl:
    """``F = (x² + y²)/30`` (the elliptic preset) as a plain Python surface."""

    default_leader_start = (50.0, -10.0, -1.0, 0.0)

    def height(self, p: ArrayLike) -> float:
        x, y = np.asarray(p, dtype=float)
        return float((x * x + y * y) / 30.0)

    def gradient(self, p: ArrayLike) -> np.ndarray:
        return np.asarray(p, dtype=float) / 15.0

    def hessian(self, p: ArrayLike) -> np.ndarray:
        return np.eye(2) / 15.0


bowl = Bowl()


def make_bowl() -> Bowl:
    """A zero-argument factory, the other accepted form of a custom surface."""
    return Bowl()


NOT_A_SURFACE = 42
