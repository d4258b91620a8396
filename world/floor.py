"""The sensing floor (design §6): a bound no estimator beats in expectation.

The floor is the error of the minimum-mean-square estimator of a follower's ideal position that
**knows the formation's true motion** — its leader's and its ideal position's true
displacements, hence the leader as seen from the ideal position — and has **every reading the
follower has had up to its decision**, in every tick so far: the leader's range and bearing in
every sensing (before the move, after it, settled, after each control step), every rod-end
reading it looked for, GPS of its own position and the oracle velocity when the run sends them,
the odometry of every interval, its own commanded moves (a teleport move or snap is known up to
its actuation noise) and so the snap's relation (a snap moves by the rod-end reading, so where
the follower settles minus the ideal position is that reading's error plus the snap's
actuation). The leader's GPS says nothing the floor does not know; a driving robot's compass and
slope readings say nothing about where it is relative to the formation without the surface,
which the floor is not given, and are not used.

With the formation's motion known, the one unknown is ``s = ideal − own position`` (xy, 2-D):
every reading of the leader is ``s`` plus the known leader-from-ideal offset plus its noise, a
rod-end reading is ``s`` plus its noise, a move by a known command ``u`` makes ``s ← s − u − η``
with actuation noise ``η``, the ideal position's own motion is a known input, and the odometry
reads the sum of an interval's moves, so it measures the sum of their actuation noises ``w``.
That is a linear-Gaussian problem once each range/bearing reading's covariance is taken at its
true range and bearing (:func:`protocol.sensing.reading_covariance`), and its minimum-mean-square
estimator is a Kalman filter. It runs here in **error space**: its state is the estimator's
error ``[ŝ − s, ŵ − w]`` (4,), which depends only on the noise draws, never on the known inputs,
so the world feeds it the errors of what it drew and never the positions.

It starts knowing nothing of ``s`` (a flat prior, :data:`PRIOR_VARIANCE`) and with ``w = 0``;
each tick's events are applied in the order they happened (:class:`FloorEvent`), and the floor
of the tick is the norm of ``ŝ − s`` at its decision: after the pre-move sensing and, in a
teleport run, the move's actuation noise (the floor moves as the follower did). A driving
follower's moves are not additive noise on a known command (the unicycle's speed and turn noise
act through its dynamics): there each control step moves the floor by the step's odometry
reading, whose error is then the step's process noise, so the drive floor is the bound of
estimators that dead-reckon by odometry (the commands' own information is not used). With
every σ = 0 each error is an exact zero and so is the floor.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

PRIOR_VARIANCE = 1e6
"""Variance (m², per coordinate) of the floor's prior on ``s``: nothing known before tick 0."""
JITTER = 1e-18
"""Added to a reading's covariance so that a σ = 0 channel keeps it invertible."""
SINGULAR = 1e-12
"""A reading's predicted covariance ``S`` counts as singular when ``det S`` is at most this
share of the product of its diagonal: rounding then decides its sign (:func:`_inverse`)."""

READ = "read"  # a reading of s: error (2,), covariance (2, 2)
MOVE = "move"  # s moved by a known command: noise (2,) added to the error, its variance
INTERVAL = "interval"  # the interval's odometry read w (error, or None: no reading); w restarts
DECIDE = "decide"  # the follower's decision (after its move's actuation, in a teleport run)


@dataclass(frozen=True)
class FloorEvent:
    """One thing the floor learns of, or suffers, in a tick.

    Attributes
    ----------
    kind : str
        :data:`READ`, :data:`MOVE`, :data:`INTERVAL` or :data:`DECIDE`.
    error : ndarray, shape (2,), optional
        The reading's error (what it read minus the truth, as a reading of ``s`` or ``w``),
        or a move's noise (added to ``ŝ − s``).
    covariance : ndarray, shape (2, 2), optional
        The reading's covariance, or a move's noise covariance.
    odometered : bool
        For a move: whether its noise is part of the interval the odometry reads.
    """

    kind: str
    error: np.ndarray | None = None
    covariance: np.ndarray | None = None
    odometered: bool = False


def read(error: np.ndarray, covariance: np.ndarray) -> FloorEvent:
    """A reading of ``s`` with ``error`` (2,) and declared ``covariance`` (2, 2)."""
    return FloorEvent(READ, np.asarray(error, dtype=float), np.asarray(covariance, dtype=float))


def range_bearing(error: np.ndarray, offset: np.ndarray, sigma_r: float,
                  sigma_theta: float) -> FloorEvent:
    """A range/bearing reading of ``s`` (the leader's, less its known offset, or the rod
    end's) whose xy ``error`` was drawn at the true local ``offset`` (2,).

    Its covariance is :func:`protocol.sensing.reading_covariance` at the true bearing and at
    the range ``sqrt(r² + σ_r²)``: across the line of sight ``(r² + σ_r²) σ_θ²``, the first-order
    term plus the product of the two errors, which dominates near the rod end (``r → 0``,
    where the first order says a reading is exact across). Its known mean,
    ``r (exp(−σ_θ²/2) − 1)`` along the line of sight (a bearing error shortens the reading's
    projection), is taken off, as the minimum-mean-square estimator would."""
    x, y = float(offset[0]), float(offset[1])
    r = math.hypot(x, y)
    c, s = (x / r, y / r) if r > 0 else (1.0, 0.0)
    bias = r * math.expm1(-0.5 * sigma_theta**2)
    along, across = sigma_r**2, (r * r + sigma_r**2) * sigma_theta**2  # reading_covariance's
    unbiased = np.array([error[0] - bias * c, error[1] - bias * s], dtype=float)
    covariance = np.array([[along * c * c + across * s * s, (along - across) * c * s],
                           [(along - across) * c * s, along * s * s + across * c * c]])
    return FloorEvent(READ, unbiased, covariance)


def move(noise: np.ndarray, variance: float, odometered: bool) -> FloorEvent:
    """A move by a known command with ``noise`` (2,) of ``variance`` per coordinate."""
    return FloorEvent(MOVE, np.asarray(noise, dtype=float), variance * np.eye(2), odometered)


def interval(error: np.ndarray | None, variance: float) -> FloorEvent:
    """The end of an odometry interval: its reading's ``error`` (None: no reading) of
    ``variance`` per coordinate; ``w`` restarts from zero."""
    return FloorEvent(INTERVAL, None if error is None else np.asarray(error, dtype=float),
                      variance * np.eye(2))


DECISION = FloorEvent(DECIDE)


@numba.njit(cache=True)
def _inverse(a: float, b: float, d: float) -> tuple[float, float, float]:
    """The inverse of the symmetric ``[[a, b], [b, d]]`` (a reading's predicted covariance),
    as its entries ``(00, 01, 11)``.

    A sensor exact on one axis and noisy on the other (``σ_r = 0 < σ_θ`` or the reverse) reads
    ``s`` exactly along one direction, so after a reading or two the floor's covariance is
    zero along it up to rounding — and the next reading's covariance is singular up to
    rounding: its determinant, a difference of two nearly equal products, can come out zero or
    negative (the world then divided by zero). Such a matrix (:data:`SINGULAR`) is inverted
    with ``1e-12`` of its trace added to its diagonal: the exact direction is then known to
    within a variance of that size instead of exactly (about 1e-7 m for readings of 0.01 m²).
    A well-conditioned one (every run with both σ or neither) is inverted as it is.

    >>> _inverse(2.0, 0.0, 4.0)
    (0.5, -0.0, 0.25)
    >>> all(math.isfinite(x) for x in _inverse(0.01, 0.01, 0.01))  # singular: regularised
    True
    """
    det = a * d - b * b
    if not det > SINGULAR * a * d:
        a, d = a + SINGULAR * (a + d), d + SINGULAR * (a + d)
        det = a * d - b * b
    return d / det, -b / det, a / det


@numba.njit(cache=True)
def _joseph(p: np.ndarray, e: np.ndarray, i: int, y0: float, y1: float, r00: float,
            r01: float, r11: float) -> None:
    """The Kalman update, in place, of error ``e`` (4,) and covariance ``p`` (4, 4) by a
    reading of state entries ``i`` and ``i + 1`` (s or w) with error ``(y0, y1)`` and
    covariance ``[[r00, r01], [r01, r11]]``, in Joseph form (the covariance stays symmetric
    and positive). With ``H`` the two rows the reading picks, ``keep = I − K H`` is the
    identity less ``K`` in those two columns, so ``keep P`` and ``(keep P) keepᵀ + K R Kᵀ`` are
    rank-2 corrections, written out (numpy's 4 x 4 products cost most of a noisy run's floor);
    compiled, a loop of scalar operations (no reassociation: the same floats as written)."""
    j = i + 1
    i00, i01, i11 = _inverse(p[i, i] + r00, p[i, j] + r01, p[j, j] + r11)
    gain = np.empty((4, 2))
    for r in range(4):
        gain[r, 0] = p[r, i] * i00 + p[r, j] * i01
        gain[r, 1] = p[r, i] * i01 + p[r, j] * i11
    v0, v1 = y0 - e[i], y1 - e[j]
    for r in range(4):
        e[r] = e[r] + gain[r, 0] * v0 + gain[r, 1] * v1
    kept = np.empty((4, 4))  # keep P
    for r in range(4):
        for c in range(4):
            kept[r, c] = p[r, c] - gain[r, 0] * p[i, c] - gain[r, 1] * p[j, c]
    for r in range(4):
        n0 = gain[r, 0] * r00 + gain[r, 1] * r01  # K R
        n1 = gain[r, 0] * r01 + gain[r, 1] * r11
        for c in range(4):
            p[r, c] = (kept[r, c] - kept[r, i] * gain[c, 0] - kept[r, j] * gain[c, 1]
                       + n0 * gain[c, 0] + n1 * gain[c, 1])


def warm_up() -> None:
    """Load (or, the first time, compile) the update's compiled kernels now, not at a first
    reading."""
    _joseph(np.eye(4), np.zeros(4), 0, 0.0, 0.0, 1.0, 0.0, 1.0)


class FloorFilter:
    """The floor's Kalman filter for one follower, in error space (see the module's text).

    ``error`` (4,) is ``[ŝ − s, ŵ − w]`` and ``covariance`` (4, 4) its covariance.
    """

    def __init__(self) -> None:
        self.error = np.zeros(4)
        self.covariance = np.diag([PRIOR_VARIANCE, PRIOR_VARIANCE, 0.0, 0.0])

    def tick(self, events: list[FloorEvent]) -> float:
        """Apply one tick's ``events`` in order; return the floor of the tick: ``|ŝ − s|`` at
        its :data:`DECISION` (after all of them if it has none: it missed before deciding,
        or a driving follower skipped its pre-move sensing)."""
        decided = None
        # while w is known to be 0 (no odometered actuation noise since the interval began:
        # exact moves) a reading of s is a 2-D update, done in floats
        idle = not self.covariance[2:, :].any()
        for event in events:
            if event.kind == READ:
                if idle:
                    self._read_s(event.error, event.covariance)
                else:
                    self._update(slice(0, 2), event.error, event.covariance)
            elif event.kind == MOVE:
                self._move(event.error, event.covariance, event.odometered)
                idle = idle and not (event.odometered and event.covariance.any())
            elif event.kind == INTERVAL:
                if event.error is not None and not idle:
                    self._update(slice(2, 4), event.error, event.covariance)
                self.error[2:] = 0.0
                self.covariance[2:, :] = 0.0
                self.covariance[:, 2:] = 0.0
                idle = True
            elif event.kind == DECIDE:
                decided = self.error[:2].copy()
            else:
                raise ValueError(f"unknown floor event kind {event.kind!r}")
        if decided is None:
            decided = self.error[:2]
        return float(np.hypot(decided[0], decided[1]))

    def _move(self, noise: np.ndarray, covariance: np.ndarray, odometered: bool) -> None:
        # s ← s − u − η and w ← w + η (if odometered); the estimate moves by u only
        self.error[:2] += noise
        self.covariance[:2, :2] += covariance
        if odometered:
            self.error[2:] -= noise
            self.covariance[2:, 2:] += covariance
            self.covariance[:2, 2:] -= covariance
            self.covariance[2:, :2] -= covariance

    def _update(self, part: slice, error: np.ndarray, covariance: np.ndarray) -> None:
        """A reading of the ``part`` of the state (s or w) with ``error`` and ``covariance``
        (:func:`_joseph`, in place)."""
        _joseph(self.covariance, self.error, part.start, float(error[0]), float(error[1]),
                float(covariance[0, 0]) + JITTER, float(covariance[0, 1]),
                float(covariance[1, 1]) + JITTER)

    def _read_s(self, error: np.ndarray, covariance: np.ndarray) -> None:
        """:meth:`_update` of ``s`` while ``w``'s rows and columns are zero, in floats (the
        same gain and Joseph form on the 2 x 2 block: most of a noisy run's floor cost)."""
        p = self.covariance
        p00, p01, p11 = float(p[0, 0]), float(p[0, 1]), float(p[1, 1])
        r00, r01, r11 = (float(covariance[0, 0]) + JITTER, float(covariance[0, 1]),
                         float(covariance[1, 1]) + JITTER)
        i00, i01, i11 = _inverse(p00 + r00, p01 + r01, p11 + r11)
        k00, k01 = p00 * i00 + p01 * i01, p00 * i01 + p01 * i11
        k10, k11 = p01 * i00 + p11 * i01, p01 * i01 + p11 * i11
        v0, v1 = float(error[0]) - self.error[0], float(error[1]) - self.error[1]
        self.error[0] += k00 * v0 + k01 * v1
        self.error[1] += k10 * v0 + k11 * v1
        m00, m01, m10, m11 = 1.0 - k00, -k01, -k10, 1.0 - k11  # keep = I − K
        a00, a01 = m00 * p00 + m01 * p01, m00 * p01 + m01 * p11
        a10, a11 = m10 * p00 + m11 * p01, m10 * p01 + m11 * p11
        b00, b01 = k00 * r00 + k01 * r01, k00 * r01 + k01 * r11
        b10, b11 = k10 * r00 + k11 * r01, k10 * r01 + k11 * r11
        q00 = a00 * m00 + a01 * m01 + b00 * k00 + b01 * k01
        q01 = a00 * m10 + a01 * m11 + b00 * k10 + b01 * k11
        q11 = a10 * m10 + a11 * m11 + b10 * k10 + b11 * k11
        p[0, 0], p[0, 1], p[1, 0], p[1, 1] = q00, q01, q01, q11

    def state(self) -> dict:
        """JSON-ready state (floats round-trip exactly)."""
        return {"error": self.error.tolist(), "covariance": self.covariance.tolist()}

    @classmethod
    def from_state(cls, state: dict) -> FloorFilter:
        floor = cls()
        floor.error = np.array(state["error"], dtype=float).reshape(4)
        floor.covariance = np.array(state["covariance"], dtype=float).reshape(4, 4)
        return floor
