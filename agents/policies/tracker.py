"""``ekf``: a model-based tracker of the leader and its rod in the follower's dead-reckoned frame
(beyond the paper; docs/estimators.md names its assumptions).

The follower's next ideal position is its leader's rod end, ``E = L + rho``: the leader's
position ``L`` plus the *rod vector* ``rho`` from the leader to the rod end (xy). Before moving
the follower reads ``L`` (the ``pre`` reading), so what it must predict is ``rho`` — and, to read
``L`` better than one reading does, where the leader was heading. This filter tracks both from
every honest reading of the tick: the leader before the move, after the move and once settled,
the rod end after the move and once settled, the moves the follower commanded, and its odometry.

State (relative to where the follower stands now, xy, one tick the time unit), 12 numbers:

- ``S, V, A``: the leader's track: position, displacement per tick and its change per tick
  (constant acceleration; the unmodelled change of ``A`` is white *jerk*);
- ``rho``: the rod vector at this tick, and ``lam = (kappa, omega)``: its log-length and turn
  rates per tick. Seen as complex numbers, ``rho_{j+1} = rho_j exp(kappa + i omega)``: the rod
  turns with the leader's heading at a rate that changes slowly, and its xy length changes with
  the slope under it at a rate that changes slowly (random walks of the rates);
- ``D``: the actuation error of the follower's own moves since it last settled (teleport: the
  move's and the snap's noise), which the odometry of the interval reads.

Readings are linear in the state (leader: ``S``; rod end: ``S + rho``) with the
declared range/bearing covariance (:func:`protocol.sensing.reading_covariance`) at the reading;
the only nonlinearity is the rod's turn, linearised at the estimate (an extended Kalman filter).
A move by ``u`` shifts the positions by ``-u`` and adds the move's declared actuation variance
(shared with ``D``). The state after each tick is a deterministic function of the calls, so the
follower's replay log rebuilds it (:mod:`agents.checkpoint`); :meth:`RodTracker.state` and
:meth:`RodTracker.restore` give it as plain data as well.
"""
from __future__ import annotations

import math

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Before, Policy, Proposal, relative
from protocol.messages import Sensing
from protocol.sensing import reading_covariance

N = 12
S, V, A, RHO, LAM, D = (slice(i, i + 2) for i in range(0, N, 2))
JITTER = 1e-12  # added to every reading's covariance: a noise-free reading stays invertible
# The leader's displacement and its change per tick before any reading of them: unknown, so
# a prior far wider than any rod (in units of the rod's length squared); its first readings
# replace it.
DIFFUSE = 1e2
JERK_DT = np.array([[1 / 20, 1 / 8, 1 / 6], [1 / 8, 1 / 3, 1 / 2], [1 / 6, 1 / 2, 1.0]])


def _rotate(v: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``v exp(kappa + i omega)``, ``v`` (2,) and ``lam = (kappa, omega)`` as complex numbers."""
    scale, c, s = math.exp(lam[0]), math.cos(lam[1]), math.sin(lam[1])
    return scale * np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


class RodTracker(Policy):
    """``ekf``: the extended Kalman filter of the module docstring.

    Parameters
    ----------
    sigma_r, sigma_theta : float
        The declared range (length) and bearing (rad) noise of a reading.
    move_variance : float
        Declared variance per coordinate of where a move (and a snap) took the follower, as far
        as it can tell (length²).
    odometry_variance : float or None
        Variance per coordinate of the odometry's displacement over one interval
        (``(noise_velocity T_c)²``), or None when the odometry is what the moves were
        reckoned with (a driving follower): then it tells nothing more.
    comm_period : float
        ``T_c``: the odometry's velocity times it is a displacement.
    spacing : float
        The rod's length ``d``: the scale of the priors and of the process noise.
    jerk : float
        Variance per coordinate of the leader's unmodelled change of acceleration per tick, in
        units of ``d²`` (length² per tick⁶ divided by ``d²``).
    turn : float
        Variance of the unmodelled change of the rod's turn rate and log-length rate per tick
        (rad² per tick²).
    name : str
    """

    def __init__(self, sigma_r: float = 0.0, sigma_theta: float = 0.0,
                 move_variance: float = 0.0, odometry_variance: float | None = None,
                 comm_period: float = 1.0, spacing: float = 1.0, jerk: float = 1e-4,
                 turn: float = 1e-4, name: str = "ekf") -> None:
        for key, value in (("sigma_r", sigma_r), ("sigma_theta", sigma_theta),
                           ("move_variance", move_variance), ("jerk", jerk), ("turn", turn)):
            if not 0.0 <= value < math.inf:
                raise ValueError(f"{key} must be finite and >= 0, got {value}")
        if odometry_variance is not None and not 0.0 <= odometry_variance < math.inf:
            raise ValueError(f"odometry_variance must be finite and >= 0 or None, "
                             f"got {odometry_variance}")
        for key, value in (("comm_period", comm_period), ("spacing", spacing)):
            if not 0.0 < value < math.inf:
                raise ValueError(f"{key} must be finite and > 0, got {value}")
        self.name = name
        self.sigma_r, self.sigma_theta = sigma_r, sigma_theta
        self.move_variance, self.odometry_variance = move_variance, odometry_variance
        self.comm_period, self.spacing = comm_period, spacing
        self.jerk, self.turn = jerk, turn
        self.mean: np.ndarray | None = None
        self.cov: np.ndarray | None = None
        self._ahead: tuple[np.ndarray, np.ndarray] | None = None  # _advanced(), until learn
        # the models' process noise per tick: the leader's jerk, the drift of the rod's rates
        self._q = np.zeros((N, N))
        for axis in range(2):
            idx = [S.start + axis, V.start + axis, A.start + axis]
            self._q[np.ix_(idx, idx)] = jerk * spacing**2 * JERK_DT
        self._q[LAM, LAM] = turn * np.eye(2)
        self.evidence = 0.0  # log-likelihood of the last tick's readings under the model
        self._evidence: list[float] = []

    # -- the filter's steps, on (mean, cov) pairs -------------------------------------------

    def _reading(self, mean, cov, z: np.ndarray, rod: bool):
        """Update with a leader (``rod`` False) or rod-end reading ``z`` (2,)."""
        h = np.zeros((2, N))
        h[:, S] = np.eye(2)
        if rod:
            h[:, RHO] = np.eye(2)
        r = math.hypot(z[0], z[1])
        noise = reading_covariance(r, math.atan2(z[1], z[0]), self.sigma_r, self.sigma_theta)
        return _update(mean, cov, h, z, noise + JITTER * np.eye(2), self._evidence)

    def _move(self, mean, cov, u: np.ndarray):
        """The follower moved by ``u`` (2,) with the declared actuation variance."""
        mean = mean.copy()
        mean[S] -= u
        if self.move_variance:
            b = np.zeros((N, 2))
            b[S], b[D] = -np.eye(2), np.eye(2)
            cov = cov + self.move_variance * b @ b.T
        return mean, cov

    def _advance(self, mean, cov):
        """One tick of the models: the leader's track and the rod's turn; the actuation error
        restarts."""
        f = np.eye(N)
        f[S, V], f[S, A], f[V, A] = np.eye(2), 0.5 * np.eye(2), np.eye(2)
        rho, lam = mean[RHO], mean[LAM]
        turned = _rotate(rho, lam)
        f[RHO, RHO] = np.array([[math.cos(lam[1]), -math.sin(lam[1])],
                                [math.sin(lam[1]), math.cos(lam[1])]]) * math.exp(lam[0])
        f[RHO, LAM] = np.c_[turned, [-turned[1], turned[0]]]
        new = f @ mean
        new[RHO] = turned
        f[D, D] = 0.0
        new[D] = 0.0
        return new, _symmetric(f @ cov @ f.T + self._q)

    def _start(self):
        """The prior before the first tick: nothing known but the scales (the leader's place
        and track, the rod vector and its rates are found by the first readings)."""
        cov = np.zeros((N, N))
        cov[S, S] = cov[V, V] = cov[A, A] = cov[RHO, RHO] = DIFFUSE * self.spacing**2 * np.eye(2)
        cov[LAM, LAM] = np.eye(2)  # rates of the order of a radian per tick
        return np.zeros(N), cov

    def _advanced(self):
        """The state at the start of the coming tick, before its readings (remembered until
        the state changes: ``auto`` asks for two proposals a tick before the policy learns)."""
        if self._ahead is None:
            self._ahead = self._start() if self.mean is None else self._advance(self.mean,
                                                                                  self.cov)
        return self._ahead

    def _before_move(self, pre: Sensing):
        """The state at this tick after its ``pre`` reading (a copy)."""
        mean, cov = self._advanced()
        return self._reading(mean, cov, relative(pre), rod=False)

    # -- the policy interface ----------------------------------------------------------------

    def propose(self, pre: Sensing) -> Proposal:
        if self.mean is None:
            raise NotFitted("ekf needs one settled tick")
        self._evidence = []  # a pure read: its readings' evidence is not kept
        mean, _ = self._before_move(pre)
        e = mean[S] + mean[RHO]
        return Proposal(e, (float(e[0]), float(e[1])))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return self.learn(settled, target)

    def learn(self, settled: Sensing, target: np.ndarray | None,
              before: Before | None = None) -> tuple[float, ...]:
        self._evidence = []
        if before is None:
            # No earlier readings (a plain record): the follower is where ``target`` took it
            # (lost: where it was, as far as it knows).
            mean, cov = self._advanced()
            if target is not None:
                mean, cov = self._move(mean, cov, np.asarray(target, dtype=float))
        else:
            mean, cov = self._before_move(before.pre)
            offset = np.asarray(before.offset, dtype=float)
            mean, cov = self._move(mean, cov, offset)
            moved = before.moved
            if moved is not None:
                mean, cov = self._reading(mean, cov, relative(moved), rod=False)
                if moved.rod is not None:
                    mean, cov = self._reading(mean, cov, np.asarray(moved.rod), rod=True)
            if target is not None:  # it snapped onto the rod end it read
                mean, cov = self._move(mean, cov, self._snap(moved, target, offset))
        mean, cov = self._reading(mean, cov, relative(settled), rod=False)
        if settled.rod is not None:
            mean, cov = self._reading(mean, cov, np.asarray(settled.rod), rod=True)
        if before is not None and target is not None:
            mean, cov = self._odometry(mean, cov, settled, before, target)
        self.mean, self.cov, self._ahead = mean, _symmetric(cov), None
        self.evidence = math.fsum(self._evidence)
        e = self.mean[S] + self.mean[RHO]
        return float(e[0]), float(e[1])

    @staticmethod
    def _snap(moved: Sensing | None, target: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """The snap the follower commanded: by the rod end it read after the move; without a
        move (an initial tick) by the offset its ``target`` says it went."""
        if moved is not None and moved.rod is not None:
            return np.asarray(moved.rod, dtype=float)
        return np.asarray(target, dtype=float) - offset

    def _odometry(self, mean, cov, settled: Sensing, before: Before, target: np.ndarray):
        """The odometry of the interval read the actuation error ``D`` of this tick's moves."""
        if (self.odometry_variance is None or not self.move_variance
                or settled.velocity is None):
            return mean, cov
        offset = np.asarray(before.offset, dtype=float)
        commanded = offset + self._snap(before.moved, target, offset)
        z = np.asarray(settled.velocity, dtype=float) * self.comm_period - commanded
        h = np.zeros((2, N))
        h[:, D] = np.eye(2)
        return _update(mean, cov, h, z, (self.odometry_variance + JITTER) * np.eye(2),
                       self._evidence)

    def skip(self) -> None:
        if self.mean is not None:
            self.mean, self.cov = self._advance(self.mean, self.cov)
            self._ahead = None

    def state(self) -> dict:
        """The filter's state as plain data (lists of floats; None before the first tick)."""
        if self.mean is None:
            return {"mean": None, "cov": None}
        return {"mean": self.mean.tolist(), "cov": self.cov.tolist()}

    def restore(self, state: dict) -> None:
        """Take the state :meth:`state` gave (ValueError naming ``state`` if malformed)."""
        self._ahead = None
        if state.get("mean") is None:
            self.mean = self.cov = None
            return
        mean, cov = np.asarray(state["mean"], dtype=float), np.asarray(state["cov"], dtype=float)
        if mean.shape != (N,) or cov.shape != (N, N) or not (
                np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise ValueError(f"state must hold a finite mean ({N},) and cov ({N}, {N})")
        self.mean, self.cov = mean, cov


def _symmetric(cov: np.ndarray) -> np.ndarray:
    return 0.5 * (cov + cov.T)


def _update(mean, cov, h: np.ndarray, z: np.ndarray, noise: np.ndarray, evidence: list):
    """Kalman update with the linear reading ``z = h x + noise`` (Joseph form); appends the
    reading's log-likelihood under the prediction to ``evidence``."""
    hc = h @ cov
    (a, b), (c, d) = hc @ h.T + noise
    det = a * d - b * c
    inverse = np.array([[d, -b], [-c, a]]) / det  # of the innovation's covariance (2, 2)
    gain = (inverse @ hc).T
    surprise = z - h @ mean
    mean = mean + gain @ surprise
    keep = np.eye(N) - gain @ h
    evidence.append(-0.5 * (float(surprise @ inverse @ surprise) + math.log(det)
                            + 2.0 * math.log(2.0 * math.pi)))
    return mean, _symmetric(keep @ cov @ keep.T + gain @ noise @ gain.T)


class TrackerBank(Policy):
    """``ekf``: :class:`RodTracker` s that differ only in the leader's ``jerk``, weighted by
    how well each predicted the readings so far (multiple-model adaptive estimation).

    How fast the leader's acceleration changes is a property of the hidden surface the
    follower cannot read, so it is not fixed: each member assumes one level (``jerks``, a
    decade apart), and the proposal is their mixture with weights proportional to the
    likelihood of every reading each member has seen, ``exp(sum_t memory^(T - t) l_t)``
    (``memory`` discounts old ticks so that a surface whose curvature changes is followed).
    """

    def __init__(self, members: list[RodTracker], memory: float = 0.8,
                 name: str = "ekf") -> None:
        if not members:
            raise ValueError("members must not be empty")
        if not 0.0 <= memory <= 1.0:
            raise ValueError(f"memory must be in [0, 1], got {memory}")
        self.members, self.memory, self.name = members, memory, name
        self.scores = [0.0] * len(members)

    def weights(self) -> np.ndarray:
        """Each member's weight (summing to 1)."""
        top = max(self.scores)
        w = np.exp(np.array(self.scores) - top)
        return w / w.sum()

    def propose(self, pre: Sensing) -> Proposal:
        offsets = [m.propose(pre).offset for m in self.members]
        e = np.einsum("k,ki->i", self.weights(), np.array(offsets))
        return Proposal(e, (float(e[0]), float(e[1])))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return self.learn(settled, target)

    def learn(self, settled: Sensing, target: np.ndarray | None,
              before: Before | None = None) -> tuple[float, ...]:
        seen = [m.learn(settled, target, before) for m in self.members]
        self.scores = [self.memory * s + m.evidence for s, m in zip(self.scores, self.members)]
        e = np.einsum("k,ki->i", self.weights(), np.array(seen))
        return float(e[0]), float(e[1])

    def skip(self) -> None:
        for m in self.members:
            m.skip()
