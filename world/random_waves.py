"""Surfaces drawn at random, for held-out checks nobody chose: ``world.random_waves:w<SEED>``.

Hand-made held-out surfaces are chosen by someone who knows the estimators; a surface drawn
from a seed is not. ``w<SEED>`` (any non-negative integer SEED, e.g. ``w17``) is

    F(p) = a·p + Σ_k A_k sin(ω_k·p + φ_k) + B exp(−|p − c|² / (2 s²)),

a random tilt ``a`` (each component in ±0.08), two to four plane waves of random direction,
wavelength 2π/|ω_k| in [12, 60] and amplitude |A_k| in [0.1, 0.9], and, on half the seeds, a
bump of height ±[0.5, 2] and width s in [3, 8] somewhere within 30 of the origin. It is smooth
everywhere (no domain) and of moderate slope: over ±100 about the origin, the largest |∇F| of
seeds 0–199 is 0.31 in the median and 0.74 at most. The leader starts at the origin with unit
speed in a random direction. Everything is drawn from ``numpy.random.default_rng(SEED)``, so
the same name is the same surface on every machine.

``bench/bench_estimator_table.py --random N --random-seed S`` runs its tables on ``w<S>`` …
``w<S+N-1>``.
"""
from __future__ import annotations

import math
import re

import numpy as np
from numpy.typing import ArrayLike

PREFIX = "w"


class RandomWaves:
    """One surface of the family above, drawn from ``seed``."""

    def __init__(self, seed: int) -> None:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed = seed
        rng = np.random.default_rng(seed)
        self.tilt = rng.uniform(-0.08, 0.08, 2)
        n = int(rng.integers(2, 5))
        direction = rng.uniform(0.0, 2.0 * math.pi, n)
        wavelength = rng.uniform(12.0, 60.0, n)
        self.omega = (2.0 * math.pi / wavelength)[:, None] * np.stack(
            [np.cos(direction), np.sin(direction)], axis=1)
        self.amplitude = rng.uniform(0.1, 0.9, n) * rng.choice([-1.0, 1.0], n)
        self.phase = rng.uniform(0.0, 2.0 * math.pi, n)
        bump = rng.random() < 0.5
        height = rng.uniform(0.5, 2.0) * rng.choice([-1.0, 1.0])
        self.bump_height = float(height) if bump else 0.0
        self.bump_centre = rng.uniform(-30.0, 30.0, 2)
        self.bump_width = float(rng.uniform(3.0, 8.0))
        heading = rng.uniform(0.0, 2.0 * math.pi)
        self.default_leader_start = (0.0, 0.0, math.cos(heading), math.sin(heading))

    def __repr__(self) -> str:
        return f"RandomWaves({self.seed})"

    def _bump(self, p: np.ndarray) -> tuple[float, np.ndarray]:
        """The bump's height and ``p − c`` over ``s²`` (for its derivatives)."""
        q = (p - self.bump_centre) / self.bump_width ** 2
        value = self.bump_height * math.exp(-0.5 * float((p - self.bump_centre) @ q))
        return value, q

    def height(self, p: ArrayLike) -> float:
        p = np.asarray(p, dtype=float)
        return float(self.tilt @ p + self.amplitude @ np.sin(self.omega @ p + self.phase)
                     + self._bump(p)[0])

    def gradient(self, p: ArrayLike) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        bump, q = self._bump(p)
        cos = np.cos(self.omega @ p + self.phase)
        return self.tilt + (self.amplitude * cos) @ self.omega - bump * q

    def hessian(self, p: ArrayLike) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        bump, q = self._bump(p)
        sin = np.sin(self.omega @ p + self.phase)
        waves = -np.einsum("k,ki,kj->ij", self.amplitude * sin, self.omega, self.omega)
        return waves + bump * (np.outer(q, q) - np.eye(2) / self.bump_width ** 2)


def name(seed: int) -> str:
    """The surface reference of ``seed``: ``world.random_waves:w<seed>``."""
    RandomWaves(seed)  # refuses a bad seed here, not in the world
    return f"{__name__}:{PREFIX}{seed}"


def __getattr__(attr: str) -> RandomWaves:
    """``w<SEED>`` is the surface drawn from SEED (made on first use)."""
    match = re.fullmatch(PREFIX + r"(0|[1-9][0-9]{0,8})", attr)
    if match is None:
        raise AttributeError(f"module {__name__!r} has no attribute {attr!r} "
                             f"(surfaces are named {PREFIX}<SEED>, e.g. {PREFIX}17)")
    return RandomWaves(int(match.group(1)))
