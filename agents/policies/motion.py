"""Predictors of the follower's own next displacement (beyond the paper; ``auto`` candidates).

What a follower must propose each tick is an offset: its own displacement from where it stands
to its next ideal position. It splits into two parts it can see separately:

- where its ideal position moves over the tick, ``s_{j+1} = e_{j+1} - e_j`` — a smooth series
  (the rod end of a leader driving a geodesic), seen after each tick as
  ``s_i = d_i - c_{i-1}``, with ``d_i`` the ``target`` of tick ``i`` (its move plus the rod-end
  offset it read after the move: the ideal position relative to where it stood before moving)
  and ``c_{i-1}`` the rod-end offset it read after settling at tick ``i-1`` (where it stands
  relative to its ideal position: a snap lands near, not on, the rod end, design §4);
- where it stands relative to its ideal position now: the settled rod-end reading ``c_j``.

The proposal is ``ŝ_{j+1} + c_j``. Both parts come from rod-end readings at a short distance,
where range/bearing noise is smallest (bearing noise grows with distance): neither looks at the
leader's reading at the rod's length, which is what a relative-position estimator must use.
With no noise ``c = 0`` exactly and the series is the follower's own displacements.

- ``gp-motion`` (:class:`MotionGP`): Gaussian-process extrapolation
  (:func:`agents.policies.classical.gp_forecast`) of ``s_i`` itself — the paper's dictionary a
  idea (predict the follower's velocity from its past velocities) with the ideal position's
  displacement instead of odometry.
- ``gp-ratio`` (:class:`RatioGP`): the complex ratio ``q_i = s_i / u_i`` (xy read as complex
  numbers: the rotation and scaling that carry the leader's displacement ``u_i`` into the
  ideal position's), proposing ``q̂ · u_{j+1} + c_j`` with the leader's displacement just seen,
  ``u_{j+1} = relative(pre_{j+1}) - relative(settled_j)`` (as ``arx`` uses it). ``q`` does not
  depend on the frame and changes only as slowly as the surface under the rod does.

A lost or missed tick, or a settled reading without the rod end, restarts the series.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Policy, Proposal, relative
from agents.policies.classical import gp_forecast
from protocol.messages import Sensing
from protocol.sensing import reading_variance


class OwnMotion(Policy):
    """Base: a series of one value per tick from ``(u_i, s_i)``, extrapolated by a GP.

    Subclasses define :meth:`value` (the series' value for one tick, or None to leave the
    tick out), :meth:`offset` (the ideal position's predicted displacement from the forecast
    value and ``u_{j+1}``) and :meth:`noise` (the series' measurement-noise variance per
    coordinate). ``move_variance``, ``sigma_r`` and ``sigma_theta`` are the run's declared
    actuation and sensor noise.
    """

    def __init__(self, samples: int = 8, move_variance: float = 0.0, sigma_r: float = 0.0,
                 sigma_theta: float = 0.0) -> None:
        if samples < 3:
            raise ValueError(f"samples must be >= 3, got {samples}")
        for label, value in (("move_variance", move_variance), ("sigma_r", sigma_r),
                             ("sigma_theta", sigma_theta)):
            if not value >= 0.0:
                raise ValueError(f"{label} must be >= 0, got {value}")
        self.move_variance, self.sigma_r, self.sigma_theta = move_variance, sigma_r, sigma_theta
        self.series: deque[np.ndarray] = deque(maxlen=samples)
        self.sizes: deque[float] = deque(maxlen=samples)  # |u_i|^2 of the same ticks
        self.rod_noise: deque[float] = deque(maxlen=samples)  # variance the readings add to s_i
        self.last_seen: np.ndarray | None = None  # measured relative(settled_j)
        self.last_rod: np.ndarray | None = None  # c_j: the rod end read after settling at j

    def value(self, u: np.ndarray, step: np.ndarray) -> np.ndarray | None:
        raise NotImplementedError

    def offset(self, forecast: np.ndarray, u: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def noise(self) -> float:
        raise NotImplementedError

    def step_variance(self) -> float:
        """Declared variance per coordinate of a value ``s_i = d_i - c_{i-1}``: the move's
        actuation noise and the two rod-end readings (at the settled readings' distances)."""
        return self.move_variance + float(np.mean(self.rod_noise))

    def _rod_variance(self, rod: np.ndarray) -> float:
        return reading_variance(float(np.hypot(*rod)), self.sigma_r, self.sigma_theta)

    def propose(self, pre: Sensing) -> Proposal:
        if self.last_seen is None or not self.series:
            raise NotFitted(f"{self.name} needs a displacement and the reading after it")
        seen = relative(pre)
        forecast = (self.series[-1] if len(self.series) == 1  # one value: it persists
                    else gp_forecast(np.array(self.series), self.noise()))
        offset = self.offset(forecast, seen - self.last_seen) + self.last_rod
        x = seen - offset
        return Proposal(offset, (float(x[0]), float(x[1])))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        seen = relative(settled)
        if target is None or settled.rod is None:  # the next step does not start at c_j
            self.skip()
            return float(seen[0]), float(seen[1])
        d, rod = np.asarray(target, dtype=float), np.asarray(settled.rod, dtype=float)
        if self.last_seen is not None:
            # the leader as seen from where the follower stood before moving is
            # relative(settled) plus the follower's own displacement d - c_j
            u = seen + d - rod - self.last_seen
            value = self.value(u, d - self.last_rod)
            if value is not None:
                self.series.append(value)
                self.sizes.append(float(u @ u))
                self.rod_noise.append(self._rod_variance(self.last_rod) + self._rod_variance(rod))
        self.last_seen, self.last_rod = seen, rod
        return float(seen[0]), float(seen[1])

    def skip(self) -> None:
        self.series.clear()
        self.sizes.clear()
        self.rod_noise.clear()
        self.last_seen = self.last_rod = None


class MotionGP(OwnMotion):
    """``gp-motion``: GP extrapolation of the ideal position's displacement per tick.

    The series' noise variance per coordinate is :meth:`OwnMotion.step_variance`.

    Examples
    --------
    >>> from protocol.messages import Sensing
    >>> p = MotionGP()
    >>> for j in range(4):  # displacements 0.5, 0.6, 0.7 east after the first settled reading
    ...     s = Sensing(tick=j, r=3.0, theta=0.0, rod=(0.0, 0.0))
    ...     _ = p.record(s, np.array([0.4 + 0.1 * j, 0.0]))
    >>> p.propose(Sensing(tick=4, r=3.9, theta=0.0)).offset.round(6)
    array([0.8, 0. ])
    """

    name = "gp-motion"

    def value(self, u: np.ndarray, step: np.ndarray) -> np.ndarray:
        return step

    def offset(self, forecast: np.ndarray, u: np.ndarray) -> np.ndarray:
        return forecast

    def noise(self) -> float:
        return self.step_variance()


class RatioGP(OwnMotion):
    """``gp-ratio``: GP extrapolation of ``q = s / u`` (complex), proposing ``q̂ · u + c``.

    A tick whose leader displacement is shorter than ``min_step`` is left out of the series
    (its ratio is undefined). The noise of ``q`` per coordinate is taken as
    ``(step variance + 2 reading_variance) / mean |u|^2`` (``|q|`` near 1; ``u`` is the
    difference of two leader readings of per-coordinate variance ``reading_variance``).

    Examples
    --------
    >>> from protocol.messages import Sensing
    >>> at = lambda j, x, y: Sensing(tick=j, r=float(np.hypot(x, y)),
    ...                              theta=float(np.arctan2(y, x)), rod=(0.0, 0.0))
    >>> p = RatioGP()
    >>> for j in range(4):  # the leader steps 1 east, the follower 1 north: q = i
    ...     _ = p.record(at(j, 3.0 + j, -j), np.array([0.0, 1.0]))
    >>> p.propose(at(4, 6.0, -1.0)).offset.round(6) + 0.0  # the leader stepped 2 north
    array([-2.,  0.])
    """

    name = "gp-ratio"

    def __init__(self, samples: int = 8, move_variance: float = 0.0, sigma_r: float = 0.0,
                 sigma_theta: float = 0.0, reading_variance: float = 0.0,
                 min_step: float = 1e-9) -> None:
        for label, value in (("reading_variance", reading_variance), ("min_step", min_step)):
            if not value >= 0.0:
                raise ValueError(f"{label} must be >= 0, got {value}")
        super().__init__(samples, move_variance, sigma_r, sigma_theta)
        self.reading_variance, self.min_step = reading_variance, min_step

    def value(self, u: np.ndarray, step: np.ndarray) -> np.ndarray | None:
        if float(np.hypot(*u)) <= self.min_step:
            return None
        q = complex(*step) / complex(*u)
        return np.array([q.real, q.imag])

    def offset(self, forecast: np.ndarray, u: np.ndarray) -> np.ndarray:
        d = complex(*forecast) * complex(*u)
        return np.array([d.real, d.imag])

    def noise(self) -> float:
        return (self.step_variance() + 2.0 * self.reading_variance) / max(
            float(np.mean(self.sizes)), self.min_step**2)
