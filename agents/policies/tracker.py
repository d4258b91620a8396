"""``ekf``: a model-based tracker of the leader and its rod in the follower's dead-reckoned frame
(beyond the paper; docs/estimators.md names its assumptions).

The follower's next ideal position is its leader's rod end, ``E = L + rho``: the leader's
position ``L`` plus the *rod vector* ``rho`` from the leader to the rod end (xy). Before moving
the follower reads ``L`` (the ``pre`` reading), so what it must predict is ``rho`` — and, to read
``L`` better than one reading does, where the leader was heading. This filter tracks both from
every honest reading of the tick: the leader before the move, after the move and once settled,
the rod end after the move and once settled, the moves the follower commanded, and its odometry.

State (relative to where the follower stands now, xy, one tick the time unit), 16 numbers:

- ``S, V, A``: the leader's track: position, displacement per tick and its change per tick
  (constant acceleration; the unmodelled change of ``A`` is white *jerk*);
- ``rho``: the rod vector at this tick, and ``lam = (kappa, omega)``: its log-length and turn
  rates per tick. Seen as complex numbers, ``rho_{j+1} = rho_j exp(kappa + i omega)``: the rod
  turns with the leader's heading at a rate that changes slowly, and its xy length changes with
  the slope under it at a rate that changes slowly (random walks of the rates);
- ``dev``: for a *swinging* rod, how far its log-length and heading stand off their mean
  (the rod of a follower further out swings over the surface's waves, and its xy length
  recovers as they pass): the rates are pulled back towards the mean, a damped oscillator,
  ``lam_{j+1} = phi lam_j - w² dev_j``, ``dev_{j+1} = dev_j + lam_{j+1}`` and
  ``rho_{j+1} = rho_j exp(kappa_{j+1} + i omega_{j+1})`` (``w = 2 pi / period``,
  ``phi = 1 - 2 zeta w`` for the damping ratio ``zeta``); for a rod of constant rates
  (``phi = 1``, ``w = 0``) it stays 0;
- ``D``: the actuation error of the follower's own moves since it last settled (teleport: the
  move's and the snap's noise), which the odometry of the interval reads;
- ``J``: the leader's *landing offset* this tick, off its track: none for a leader that drives
  its path; a leader that is itself a follower stands off its rod end by its snap's error
  (white, one draw per tick, shared by every reading of that tick).

Readings are linear in the state (leader: ``S + J``; rod end: ``S + J + rho``) with the
declared range/bearing covariance (:func:`protocol.sensing.reading_covariance`) at the reading;
the only nonlinearity is the rod's turn, linearised at the estimate (an extended Kalman filter).
A move by ``u`` shifts the positions by ``-u`` and adds the move's declared actuation variance
(shared with ``D``). The state after each tick is a deterministic function of the calls, so the
follower's replay log rebuilds it (:mod:`agents.checkpoint`); :meth:`RodTracker.state` and
:meth:`RodTracker.restore` give it as plain data as well.

How fast the leader's acceleration changes (its jerk), how far it lands off its track, how
fast the rod's rates drift and whether the rod swings (the rod of a follower further out
sweeps over the surface as the column turns) are properties of the hidden surface and of the
follower's place in the column, which it does not know: :class:`RodTracker` runs one filter
per combination of levels (``jerks`` x ``landings`` x ``rods``), side by side as one batch of
arrays, and proposes their mixture, each weighted by the likelihood of the readings it
predicted (multiple-model adaptive estimation).
"""
from __future__ import annotations

import math
from itertools import product

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Before, LearnsTick, Proposal, relative
from protocol.messages import Sensing
from protocol.sensing import reading_covariance

N = 16
S, V, A, RHO, LAM, D, J, DEV = (slice(i, i + 2) for i in range(0, N, 2))
JITTER = 1e-12  # added to every reading's covariance: a noise-free reading stays invertible
# Before any reading the leader's place and track and the rod vector are unknown: a prior far
# wider than any rod (in units of the rod's length squared); the first readings replace it.
DIFFUSE = 1e2
EYE2 = np.eye(2)
LOG_2PI = math.log(2.0 * math.pi)


# What a reading sums of the state's 2-vectors (its observation matrix is a sum of 2x2
# identities there), in the order of the state, which is the order a matrix product adds them.
LEADER, ROD_END, ACTUATION = (S, J), (S, RHO, J), (D,)
MOVED = np.zeros((N, N))  # a move's noise: -S, +D
MOVED[S, S] = MOVED[D, D] = EYE2
MOVED[S, D] = MOVED[D, S] = -EYE2
TRACK = np.eye(N)  # the linear part of a tick: constant acceleration; D and J start afresh
TRACK[S, V], TRACK[S, A], TRACK[V, A] = EYE2, 0.5 * EYE2, EYE2
TRACK[D, D] = TRACK[J, J] = TRACK[DEV, DEV] = 0.0
# white jerk's covariance of (position, displacement, acceleration) over one tick, per unit
JERK_DT = np.array([[1 / 20, 1 / 8, 1 / 6], [1 / 8, 1 / 3, 1 / 2], [1 / 6, 1 / 2, 1.0]])
ADJUGATE = np.array([[1.0, -1.0], [-1.0, 1.0]])  # the signs of a 2x2 matrix's adjugate


def _observed(x: np.ndarray, blocks: tuple[slice, ...], axis: int = 1) -> np.ndarray:
    """``H x`` (axis 1 of a batch) or ``x H^T`` (axis 2) for the observation matrix ``H``
    that sums the state's 2-vectors ``blocks``: their sum, added in the given order."""
    def pick(block):
        return x[:, block] if axis == 1 else x[:, :, block]
    total = pick(blocks[0])
    for block in blocks[1:]:
        total = total + pick(block)
    return total


class RodTracker(LearnsTick):
    """``ekf``: the extended Kalman filters of the module docstring, one per (jerk, landing,
    rod) combination, and their likelihood-weighted mixture.

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
        The rod's length ``d``: the scale of the priors and of the jerk.
    jerks : sequence of float
        Variances per coordinate of the leader's unmodelled change of acceleration per tick
        the filters assume, in units of ``d²`` (length² per tick⁶ divided by ``d²``).
    landings : sequence of float
        Variances per coordinate of the leader's landing off its track the filters assume
        (length²; 0: it drives its path).
    rods : sequence of (float, float)
        The rod models the filters assume, pairs (drift, period): the variance of the
        unmodelled change of the rod's turn rate and log-length rate per tick (rad² per
        tick²), and the period in ticks of the rod's swing about its mean (> 2, and stable
        with ``damping``; ``inf``: no swing, the rates persist).
    damping : float
        The damping ratio of a swinging rod (>= 0): each tick its rates keep
        ``1 - 2 damping (2 pi / period)`` of themselves before the pull back.
    memory : float
        In [0, 1]: each tick, the filters' past log-likelihoods are multiplied by it before the
        tick's are added (old evidence fades, so a surface whose curvature changes is
        followed).
    name : str
    """

    def __init__(self, sigma_r: float = 0.0, sigma_theta: float = 0.0,
                 move_variance: float = 0.0, odometry_variance: float | None = None,
                 comm_period: float = 1.0, spacing: float = 1.0, jerks=(1e-4,),
                 landings=(0.0,), rods=((1e-4, math.inf),),
                 damping: float = 0.3, memory: float = 0.8, name: str = "ekf") -> None:
        for key, value in (("sigma_r", sigma_r), ("sigma_theta", sigma_theta),
                           ("move_variance", move_variance)):
            if not 0.0 <= value < math.inf:
                raise ValueError(f"{key} must be finite and >= 0, got {value}")
        rods = tuple(tuple(rod) for rod in rods)
        if not len(rods) or not all(len(rod) == 2 and 0.0 <= rod[0] < math.inf
                                    and 2.0 < rod[1] <= math.inf for rod in rods):
            raise ValueError(f"rods must be pairs (drift >= 0, period > 2 or inf), at least "
                             f"one, got {rods}")
        for key, values in (("jerks", jerks), ("landings", landings)):
            if not len(values) or not all(0.0 <= v < math.inf for v in values):
                raise ValueError(f"{key} must be finite values >= 0, at least one, "
                                 f"got {values}")
        if not 0.0 <= damping < math.inf:
            raise ValueError(f"damping must be finite and >= 0, got {damping}")
        if odometry_variance is not None and not 0.0 <= odometry_variance < math.inf:
            raise ValueError(f"odometry_variance must be finite and >= 0 or None, "
                             f"got {odometry_variance}")
        for key, value in (("comm_period", comm_period), ("spacing", spacing)):
            if not 0.0 < value < math.inf:
                raise ValueError(f"{key} must be finite and > 0, got {value}")
        if not 0.0 <= memory <= 1.0:
            raise ValueError(f"memory must be in [0, 1], got {memory}")
        self.name = name
        self.sigma_r, self.sigma_theta = sigma_r, sigma_theta
        self.move_variance, self.odometry_variance = move_variance, odometry_variance
        self.comm_period, self.spacing, self.memory = comm_period, spacing, memory
        # each filter's (jerk, landing, drift, period), in the order of the batch
        self.levels = levels = [(jerk, landing, *rod) for jerk, landing, rod in product(
            jerks, landings, rods)]
        self.members = len(levels)
        # each filter's process noise per tick: the leader's jerk and landing, the rates' drift
        self._q = np.zeros((self.members, N, N))
        # each filter's rod: the rates' persistence and pull back towards the mean rod (0 and
        # 1 for a constant rate), and whether it tracks the rod's deviation from its mean
        self._persist, self._pull, self._swept = (np.ones(self.members),
                                                  np.zeros(self.members),
                                                  np.zeros(self.members))
        for k, (jerk, landing, turn, sweep) in enumerate(levels):
            for axis in range(2):
                idx = [S.start + axis, V.start + axis, A.start + axis]
                self._q[k][np.ix_(idx, idx)] = jerk * spacing**2 * JERK_DT
            self._q[k][LAM, LAM] = turn * EYE2
            self._q[k][J, J] = landing * EYE2
            if sweep < math.inf:
                frequency = 2.0 * math.pi / sweep
                persist, pull = 1.0 - 2.0 * damping * frequency, frequency**2
                # (lam, dev) -> (persist lam - pull dev, persist lam + (1 - pull) dev): its
                # eigenvalues' product is persist, their sum persist + 1 - pull
                if not (abs(persist) < 1.0 and abs(persist + 1.0 - pull) < 1.0 + persist):
                    raise ValueError(f"rods: a swing of period {sweep} with damping {damping} "
                                     f"is unstable (persistence {persist:.3g})")
                self._persist[k], self._pull[k], self._swept[k] = persist, pull, 1.0
        self.mean: np.ndarray | None = None  # (members, N)
        self.cov: np.ndarray | None = None  # (members, N, N)
        self.scores = np.zeros(self.members)  # discounted log-likelihoods
        self._ahead: tuple[np.ndarray, np.ndarray] | None = None  # _advanced(), until learn
        self._pre: tuple | None = None  # _before_move()'s reading and result, until learn
        self._weights: np.ndarray | None = None  # weights(), until the scores change
        self._evidence = np.zeros(self.members)

    # -- the filters' steps, on (mean, cov) batches ---------------------------------------

    def _update(self, mean, cov, blocks: tuple[slice, ...], z: np.ndarray,
                noise: np.ndarray):
        """Kalman update of every filter with the linear reading ``z = H x + noise`` (``H``
        sums the state's 2-vectors ``blocks``, :func:`_observed`); adds the reading's
        log-likelihood under each prediction to the evidence."""
        hc = _observed(cov, blocks)  # H P (members, 2, N)
        s = _observed(hc, blocks, axis=2) + noise
        det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
        inverse = np.swapaxes(s[:, ::-1, ::-1], 1, 2) * ADJUGATE / det[:, None, None]
        gain = np.swapaxes(inverse @ hc, 1, 2)  # (members, N, 2)
        surprise = z - _observed(mean, blocks)  # (members, 2)
        mean = mean + np.einsum("kij,kj->ki", gain, surprise)
        with np.errstate(invalid="ignore", divide="ignore"):  # a run-away filter: NaN
            self._evidence -= 0.5 * (np.einsum("ki,kij,kj->k", surprise, inverse, surprise)
                                     + np.log(det) + 2.0 * LOG_2PI)
        # symmetric but for rounding: symmetrised once a tick, by _advance
        return mean, cov - gain @ hc

    def _reading(self, mean, cov, z: np.ndarray, rod: bool):
        """Update with a leader (``rod`` False) or rod-end reading ``z`` (2,)."""
        r = math.hypot(z[0], z[1])
        noise = reading_covariance(r, math.atan2(z[1], z[0]), self.sigma_r, self.sigma_theta)
        return self._update(mean, cov, ROD_END if rod else LEADER, z, noise + JITTER * EYE2)

    def _sensed(self, mean, cov, sensing: Sensing):
        """Update with a sensing's leader reading, then its rod end's if it carries one."""
        mean, cov = self._reading(mean, cov, relative(sensing), rod=False)
        if sensing.rod is not None:
            mean, cov = self._reading(mean, cov, np.asarray(sensing.rod), rod=True)
        return mean, cov

    def _move(self, mean, cov, u: np.ndarray):
        """The follower moved by ``u`` (2,) with the declared actuation variance."""
        mean = mean.copy()
        mean[:, S] -= u
        if self.move_variance:
            cov = cov + self.move_variance * MOVED
        return mean, cov

    def _advance(self, mean, cov):
        """One tick of the models: the leader's track and the rod's turn; a new landing
        offset; the actuation error restarts."""
        persist, pull, swept = self._persist[:, None], self._pull[:, None], self._swept[:, None]
        rho, dev = mean[:, RHO], mean[:, DEV]
        lam = persist * mean[:, LAM] - pull * dev  # the tick's rates
        scale, cos, sin = np.exp(lam[:, 0]), np.cos(lam[:, 1]), np.sin(lam[:, 1])
        turn = scale[:, None, None] * np.stack([cos, -sin, sin, cos], -1).reshape(-1, 2, 2)
        turned = np.einsum("kij,kj->ki", turn, rho)
        # d rho' / d lam: rho' and rho' turned a quarter
        by_rate = np.stack([turned[:, 0], -turned[:, 1], turned[:, 1], turned[:, 0]],
                           -1).reshape(-1, 2, 2)
        f = np.broadcast_to(TRACK, cov.shape).copy()
        f[:, RHO, RHO] = turn
        f[:, RHO, LAM] = persist[:, :, None] * by_rate
        f[:, RHO, DEV] = -pull[:, :, None] * by_rate
        f[:, LAM, LAM] = persist[:, :, None] * EYE2
        f[:, LAM, DEV] = -pull[:, :, None] * EYE2
        f[:, DEV, LAM] = (swept * persist)[:, :, None] * EYE2
        f[:, DEV, DEV] = (swept * (1.0 - pull))[:, :, None] * EYE2
        new = mean @ TRACK.T
        new[:, RHO], new[:, LAM], new[:, DEV] = turned, lam, swept * (dev + lam)
        cov = f @ cov @ np.swapaxes(f, 1, 2) + self._q
        return new, 0.5 * (cov + np.swapaxes(cov, 1, 2))

    def _start(self):
        """The prior before the first tick: nothing known but the scales (the leader's place
        and track, the rod vector and its rates are found by the first readings)."""
        cov = np.zeros((self.members, N, N))
        wide = DIFFUSE * self.spacing**2 * EYE2
        cov[:, S, S] = cov[:, V, V] = cov[:, A, A] = cov[:, RHO, RHO] = wide
        cov[:, LAM, LAM] = EYE2  # rates of the order of a radian per tick
        cov[:, DEV, DEV] = self._swept[:, None, None] * EYE2  # a deviation of about a radian
        cov[:, J, J] = self._q[:, J, J]
        return np.zeros((self.members, N)), cov

    def _advanced(self):
        """The filters at the start of the coming tick, before its readings (remembered until
        the state changes: the tick's proposals, one per reading asked about, and its
        learning all start from it)."""
        if self._ahead is None:
            self._ahead = self._start() if self.mean is None else self._advance(self.mean,
                                                                                  self.cov)
        return self._ahead

    def _before_move(self, pre: Sensing):
        """The filters at this tick after its ``pre`` reading, and that reading's evidence
        (members,), remembered for the last ``pre`` until the state changes: learning
        starts again from the reading the tick's proposal was made from (``auto`` keeps the
        proposals it made, :meth:`Auto._asked_for`, so it does not ask twice from one
        reading). Read-only: copy before changing them."""
        if self._pre is None or self._pre[0] != pre:
            kept, self._evidence = self._evidence, np.zeros(self.members)
            mean, cov = self._advanced()
            mean, cov = self._reading(mean, cov, relative(pre), rod=False)
            self._pre, self._evidence = (pre, mean, cov, self._evidence), kept
        return self._pre[1:]

    def _forget(self) -> None:
        """The filters' state or scores changed: drop what was derived from them."""
        self._ahead = self._pre = self._weights = None

    def weights(self) -> np.ndarray:
        """Each filter's weight in the mixture (members,), summing to 1."""
        if self._weights is None:
            w = np.exp(self.scores - self.scores.max())
            self._weights = w / w.sum()
        return self._weights

    def _rod_end(self, mean: np.ndarray) -> np.ndarray:
        """The mixture's rod end relative to the follower (2,), over the filters whose
        numbers are finite (a filter whose model ran away, e.g. its rod's rates grown to
        radians a tick, drops out until it is restarted; see :meth:`_restart_broken`)."""
        ends, weights = mean[:, S] + mean[:, J] + mean[:, RHO], self.weights()
        finite = np.isfinite(ends).all(axis=1)
        if not finite.all():
            if not finite.any():
                raise NotFitted("ekf: every filter's numbers ran away")
            weights = np.where(finite, weights, 0.0)
            weights, ends = weights / weights.sum(), np.where(finite[:, None], ends, 0.0)
        return weights @ ends

    def _restart_broken(self) -> None:
        """Restart from the prior every filter whose numbers are no longer finite (its model
        ran away: a reading's predicted covariance lost its positive determinant, or its
        rates grew until the rod's scale overflowed), with the lowest score of the others:
        the mixture goes on without it, and the state stays finite (:meth:`restore`)."""
        broken = ~(np.isfinite(self.scores) & np.isfinite(self.mean).all(axis=1)
                   & np.isfinite(self.cov).all(axis=(1, 2)))
        if broken.any():
            mean, cov = self._start()
            self.mean, self.cov = self.mean.copy(), self.cov.copy()
            self.mean[broken], self.cov[broken] = mean[broken], cov[broken]
            self.scores = self.scores.copy()
            self.scores[broken] = self.scores[~broken].min() if (~broken).any() else 0.0

    # -- the policy interface ----------------------------------------------------------------

    def propose(self, pre: Sensing) -> Proposal:
        if self.mean is None:
            raise NotFitted("ekf needs one settled tick")
        mean, _, _ = self._before_move(pre)
        e = self._rod_end(mean)
        return Proposal(e, (float(e[0]), float(e[1])))

    def learn(self, settled: Sensing, target: np.ndarray | None,
              before: Before | None = None) -> tuple[float, ...]:
        self._evidence = np.zeros(self.members)
        if before is None:
            # No earlier readings (a plain record): the follower is where ``target`` took it
            # (lost: where it was, as far as it knows).
            mean, cov = self._advanced()
            if target is not None:
                mean, cov = self._move(mean, cov, np.asarray(target, dtype=float))
        else:
            mean, cov, evidence = self._before_move(before.pre)
            self._evidence = evidence.copy()
            offset = np.asarray(before.offset, dtype=float)
            mean, cov = self._move(mean, cov, offset)
            moved = before.moved
            if moved is not None:
                mean, cov = self._sensed(mean, cov, moved)
            if target is not None:  # it snapped onto the rod end it read
                snap = self._snap(moved, target, offset)
                mean, cov = self._move(mean, cov, snap)
        mean, cov = self._sensed(mean, cov, settled)
        if before is not None and target is not None:
            mean, cov = self._odometry(mean, cov, settled, offset + snap)
        self.mean, self.cov = mean, cov
        self.scores = self.memory * self.scores + self._evidence
        self._restart_broken()
        self._forget()
        e = self._rod_end(mean)
        return float(e[0]), float(e[1])

    @staticmethod
    def _snap(moved: Sensing | None, target: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """The snap the follower commanded: by the rod end it read after the move; without a
        move (an initial tick) by the offset its ``target`` says it went."""
        if moved is not None and moved.rod is not None:
            return np.asarray(moved.rod, dtype=float)
        return np.asarray(target, dtype=float) - offset

    def _odometry(self, mean, cov, settled: Sensing, commanded: np.ndarray):
        """The odometry of the interval read the actuation error ``D`` of this tick's moves
        (``commanded``: the move and the snap, (2,))."""
        if (self.odometry_variance is None or not self.move_variance
                or settled.velocity is None):
            return mean, cov
        z = np.asarray(settled.velocity, dtype=float) * self.comm_period - commanded
        return self._update(mean, cov, ACTUATION, z, (self.odometry_variance + JITTER) * EYE2)

    def skip(self) -> None:
        if self.mean is not None:
            self.mean, self.cov = self._advance(self.mean, self.cov)
            self._restart_broken()
            self._forget()

    def state(self) -> dict:
        """The filters' state as plain data (lists of floats; None before the first tick)."""
        if self.mean is None:
            return {"mean": None, "cov": None, "scores": self.scores.tolist()}
        return {"mean": self.mean.tolist(), "cov": self.cov.tolist(),
                "scores": self.scores.tolist()}

    def restore(self, state: dict) -> None:
        """Take the state :meth:`state` gave (ValueError naming ``state`` if malformed)."""
        k = self.members
        try:
            scores = np.asarray(state["scores"], dtype=float)
            mean = None if state["mean"] is None else np.asarray(state["mean"], dtype=float)
            cov = None if state["cov"] is None else np.asarray(state["cov"], dtype=float)
        except (KeyError, TypeError, ValueError):
            raise ValueError("state must be a map of mean, cov and scores") from None
        if scores.shape != (k,) or not np.all(np.isfinite(scores)) or (mean is None) != (
                cov is None) or mean is not None and (
                mean.shape != (k, N) or cov.shape != (k, N, N)
                or not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)))):
            raise ValueError(f"state must hold finite scores ({k},), mean ({k}, {N}) and cov "
                             f"({k}, {N}, {N})")
        self.mean, self.cov, self.scores = mean, cov, scores
        self._forget()
