"""Predictors of the follower's own next displacement (beyond the paper; ``auto`` candidates).

What a follower must propose each tick is an offset: its own displacement ``d_j`` from where it
stands to its next ideal position. After the tick it knows that displacement exactly — it is
the ``target`` it snapped by (its move plus the rod-end offset it saw, SPEC §5; only actuation
noise enters it) — and it knows the leader's displacement over the same tick,
``u_j = relative(pre_{j+1}) - relative(settled_j)`` (as ``arx`` uses it). The policies here
extrapolate a smooth per-tick series built from those two over time, by Gaussian-process
regression (:func:`agents.policies.classical.gp_forecast`):

- ``gp-motion`` (:class:`MotionGP`): the series ``d_i`` itself — the paper's dictionary a idea
  (predict the follower's velocity from its past velocities) with the snapped displacement
  instead of odometry. It never looks at a range or bearing reading to propose, so sensor
  noise on them does not reach it.
- ``gp-ratio`` (:class:`RatioGP`): the complex ratio ``q_i = d_i / u_i`` (xy read as complex
  numbers: the rotation and scaling that carry the leader's displacement into the
  follower's), proposing ``q̂ · u_j`` with the leader's displacement just seen. ``q`` does not
  depend on the frame and changes only as slowly as the surface under the rod does.

A lost or missed tick restarts the series: the follower's displacement after it is not one
between two ideal positions.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Policy, Proposal, relative
from agents.policies.classical import gp_forecast
from protocol.messages import Sensing


class OwnMotion(Policy):
    """Base: a series of one value per tick from ``(u_i, d_i)``, extrapolated by a GP.

    Subclasses define :meth:`value` (the series' value for one tick, or None to leave the
    tick out), :meth:`offset` (the proposal from the forecast value and ``u_j``) and
    :meth:`noise` (the series' measurement-noise variance per coordinate).
    """

    def __init__(self, samples: int = 8) -> None:
        if samples < 3:
            raise ValueError(f"samples must be >= 3, got {samples}")
        self.series: deque[np.ndarray] = deque(maxlen=samples)
        self.sizes: deque[float] = deque(maxlen=samples)  # |u_i|^2 of the same ticks
        self.last_seen: np.ndarray | None = None  # measured relative(settled_j)

    def value(self, u: np.ndarray, d: np.ndarray) -> np.ndarray | None:
        raise NotImplementedError

    def offset(self, forecast: np.ndarray, u: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def noise(self) -> float:
        raise NotImplementedError

    def propose(self, pre: Sensing) -> Proposal:
        if self.last_seen is None or not self.series:
            raise NotFitted(f"{self.name} needs a displacement and the reading after it")
        seen = relative(pre)
        forecast = (self.series[-1] if len(self.series) == 1  # one value: it persists
                    else gp_forecast(np.array(self.series), self.noise()))
        offset = self.offset(forecast, seen - self.last_seen)
        x = seen - offset
        return Proposal(offset, (float(x[0]), float(x[1])))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        seen = relative(settled)
        if target is None:  # lost: the next displacement does not start at an ideal position
            self.skip()
            return float(seen[0]), float(seen[1])
        d = np.asarray(target, dtype=float)
        if self.last_seen is not None:
            u = seen + d - self.last_seen
            value = self.value(u, d)
            if value is not None:
                self.series.append(value)
                self.sizes.append(float(u @ u))
        self.last_seen = seen
        return float(seen[0]), float(seen[1])

    def skip(self) -> None:
        self.series.clear()
        self.sizes.clear()
        self.last_seen = None


class MotionGP(OwnMotion):
    """``gp-motion``: GP extrapolation of the follower's own displacement per tick.

    ``noise`` is the variance per coordinate of a recorded displacement: the declared
    actuation noise squared (the snapped displacement is otherwise exact).

    Examples
    --------
    >>> from protocol.messages import Sensing
    >>> p = MotionGP()
    >>> for j in range(4):  # displacements 0.5, 0.6, 0.7 east after the first settled reading
    ...     _ = p.record(Sensing(tick=j, r=3.0, theta=0.0), np.array([0.4 + 0.1 * j, 0.0]))
    >>> p.propose(Sensing(tick=4, r=3.9, theta=0.0)).offset.round(6)
    array([0.8, 0. ])
    """

    name = "gp-motion"

    def __init__(self, samples: int = 8, move_variance: float = 0.0) -> None:
        if not move_variance >= 0.0:
            raise ValueError(f"move_variance must be >= 0, got {move_variance}")
        super().__init__(samples)
        self.move_variance = move_variance

    def value(self, u: np.ndarray, d: np.ndarray) -> np.ndarray:
        return d

    def offset(self, forecast: np.ndarray, u: np.ndarray) -> np.ndarray:
        return forecast

    def noise(self) -> float:
        return self.move_variance


class RatioGP(OwnMotion):
    """``gp-ratio``: GP extrapolation of ``q = d / u`` (complex), proposing ``q̂ · u_j``.

    A tick whose leader displacement is shorter than ``min_step`` is left out of the series
    (its ratio is undefined). The noise of ``q`` per coordinate is taken as
    ``(move_variance + 2 reading_variance) / mean |u|^2`` (``|q|`` near 1; ``u`` is the
    difference of two readings of per-coordinate variance ``reading_variance``).

    Examples
    --------
    >>> from protocol.messages import Sensing
    >>> at = lambda j, x, y: Sensing(tick=j, r=float(np.hypot(x, y)), theta=float(np.arctan2(y, x)))
    >>> p = RatioGP()
    >>> for j in range(4):  # the leader steps 1 east, the follower 1 north: q = i
    ...     _ = p.record(at(j, 3.0 + j, -j), np.array([0.0, 1.0]))
    >>> p.propose(at(4, 6.0, -1.0)).offset.round(6) + 0.0  # the leader stepped 2 north
    array([-2.,  0.])
    """

    name = "gp-ratio"

    def __init__(self, samples: int = 8, move_variance: float = 0.0,
                 reading_variance: float = 0.0, min_step: float = 1e-9) -> None:
        for label, value in (("move_variance", move_variance),
                             ("reading_variance", reading_variance), ("min_step", min_step)):
            if not value >= 0.0:
                raise ValueError(f"{label} must be >= 0, got {value}")
        super().__init__(samples)
        self.move_variance, self.reading_variance = move_variance, reading_variance
        self.min_step = min_step

    def value(self, u: np.ndarray, d: np.ndarray) -> np.ndarray | None:
        if float(np.hypot(*u)) <= self.min_step:
            return None
        q = complex(*d) / complex(*u)
        return np.array([q.real, q.imag])

    def offset(self, forecast: np.ndarray, u: np.ndarray) -> np.ndarray:
        d = complex(*forecast) * complex(*u)
        return np.array([d.real, d.imag])

    def noise(self) -> float:
        return (self.move_variance + 2.0 * self.reading_variance) / max(
            float(np.mean(self.sizes)), self.min_step**2)
