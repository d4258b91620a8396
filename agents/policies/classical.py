"""Classical tracking baselines the paper does not compare with (design §6): ``cv``, ``kalman``,
``arx``, ``gp``.

Each predicts the leader's next position relative to the follower's next ideal position,
``x*_{j+1}`` (xy, local frame), and proposes ``relative(pre) - x*``, as dictionary b does. All
state is data (floats and small arrays) changed only by ``record`` and ``skip`` (fits derived
from it are remembered until then).
"""
from __future__ import annotations

import functools
import math
from collections import deque

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Policy, Proposal, relative
from protocol.messages import Sensing
from protocol.sensing import reading_covariance, reading_variance

# Relative cut-off of singular values in the least-squares fits (as StreamingEDMD's rcond).
RCOND = 1e-10


class RelativeTracker(Policy):
    """Base: keeps the last ``history`` relative positions; subclasses implement ``forecast``.

    A lost or missed tick is bridged with the tracker's own forecast (multi-step).
    """

    def __init__(self, history: int) -> None:
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        self.history: deque[np.ndarray] = deque(maxlen=history)

    def forecast(self) -> np.ndarray:
        """Predicted relative position (2,) at the next tick (raises NotFitted)."""
        raise NotImplementedError

    def propose(self, pre: Sensing) -> Proposal:
        x = self.forecast()
        return Proposal(relative(pre) - x, (float(x[0]), float(x[1])))

    def _forecast_or_none(self) -> np.ndarray | None:
        try:
            return self.forecast()
        except NotFitted:
            return None

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        x = self._forecast_or_none() if target is None else None
        x = relative(settled) if x is None else x
        self.history.append(x)
        return float(x[0]), float(x[1])

    def skip(self) -> None:
        x = self._forecast_or_none()
        if x is not None:
            self.history.append(x)


class ConstantVelocity(RelativeTracker):
    """``cv``: ``x*_{j+1} = 2 x_j - x_{j-1}`` (constant-velocity extrapolation).

    Examples
    --------
    >>> from protocol.messages import Sensing
    >>> cv = ConstantVelocity()
    >>> for r in (3.0, 3.1):
    ...     _ = cv.record(Sensing(tick=0, r=r, theta=0.0), target=np.zeros(2))
    >>> cv.forecast().round(12)
    array([3.2, 0. ])
    >>> cv.propose(Sensing(tick=2, r=3.5, theta=0.0)).offset.round(12)  # leader 0.3 further
    array([0.3, 0. ])
    """

    name = "cv"

    def __init__(self) -> None:
        super().__init__(history=2)

    def forecast(self) -> np.ndarray:
        if len(self.history) < 2:
            raise NotFitted("cv needs two relative positions")
        return 2.0 * self.history[-1] - self.history[-2]


GP_LENGTHS = (1.0, 2.0, 3.0, 5.0, 8.0)  # length scales (ticks) the likelihood chooses from
GP_JITTER = 1e-8


def gp_forecast(samples: np.ndarray, noise: float = 0.0) -> np.ndarray:
    """The next value of a series sampled once per tick, by Gaussian-process extrapolation.

    ``samples`` is (n, m), oldest first, n >= 2; each of the m coordinates is modelled over the
    tick index as a linear trend plus a squared-exponential residual with length scale ``ell``
    ticks and a measurement-noise variance ``noise`` (units of the samples, squared) plus a
    relative jitter of 1e-8. The noise enters relative to the samples' variance (standing in
    for the unknown signal variance); given that ratio the trend is fitted by generalised least
    squares (universal kriging), the signal variance takes its closed-form maximum-likelihood
    value, and ``ell`` the value in :data:`GP_LENGTHS` of highest (concentrated) likelihood.
    Deterministic: no optimiser, no random restarts. Two samples give the linear trend alone.
    Returns (m,).

    Examples
    --------
    >>> gp_forecast(np.array([[0.0], [1.0], [2.0], [3.0]])).round(6)  # a straight line
    array([4.])
    """
    y = np.ascontiguousarray(samples, dtype=float)
    if y.ndim != 2 or y.shape[0] < 2:
        raise ValueError(f"samples must be (n >= 2, m), got shape {y.shape}")
    if y.shape[0] == 2:  # too few for a residual: the trend alone
        return 2.0 * y[-1] - y[-2]
    return np.array(_gp_forecast(y.tobytes(), y.shape, float(noise)))


@functools.lru_cache(maxsize=256)
def _gp_forecast(data: bytes, shape: tuple[int, int], noise: float) -> tuple[float, ...]:
    """:func:`gp_forecast` of the samples in ``data``, remembered: a policy's forecast from
    the same history is asked for twice a tick (its proposal, then ``auto``'s scoring of it
    in ``record``, before the policy learns), and the fit is most of ``auto``'s time."""
    y = np.frombuffer(data, dtype=float).reshape(shape)
    n = shape[0]
    t = np.arange(n, dtype=float)
    basis = np.c_[np.ones(n), t]
    return tuple(_gp_coordinate(t, basis, y[:, i], noise) for i in range(shape[1]))


@functools.lru_cache(maxsize=64)
def _gp_kernels(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The squared-exponential kernels of ticks ``0..n-1``, one per length scale of
    :data:`GP_LENGTHS` (L, n, n), their columns to tick ``n`` (L, n), and the identity
    (n, n): they depend on ``n`` only."""
    t = np.arange(n, dtype=float)
    ells = np.array(GP_LENGTHS)[:, None, None]
    return (np.exp(-0.5 * ((t[None, :, None] - t[None, None, :]) / ells) ** 2),
            np.exp(-0.5 * ((t[None, :] - float(n)) / ells[:, 0]) ** 2), np.eye(n))


def _cholesky_solve(chol: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``C^-1 b`` for each ``C = chol @ chol.T`` of a stack (``chol`` (L, n, n) lower
    triangular, ``b`` (L, n, k))."""
    return np.linalg.solve(np.swapaxes(chol, -1, -2), np.linalg.solve(chol, b))


def _gp_coordinate(t: np.ndarray, basis: np.ndarray, y: np.ndarray, noise: float) -> float:
    """One coordinate's forecast: every length scale's fit at once (each is the same
    LAPACK computation on its own matrix as when they were fitted one by one), the one of
    highest likelihood taken."""
    scale = float(np.var(y)) + 1e-300
    k, k_new, eye = _gp_kernels(t.size)
    lengths = len(GP_LENGTHS)
    # Signal variance s2 and noise variance enter as C = k + (noise / s2 + jitter) I;
    # s2 is unknown, so the samples' variance stands in for it here.
    cov = k + (noise / scale + GP_JITTER) * eye
    chol = np.linalg.cholesky(cov)
    ci_h = _cholesky_solve(chol, np.broadcast_to(basis, (lengths, *basis.shape)))
    ci_y = _cholesky_solve(chol, np.broadcast_to(y[:, None], (lengths, y.size, 1)))[:, :, 0]
    betas = [np.linalg.lstsq(basis.T @ ci_h[i], basis.T @ ci_y[i], rcond=None)[0]
             for i in range(lengths)]
    resid = np.array([y - basis @ beta for beta in betas])
    ci_r = _cholesky_solve(chol, resid[:, :, None])[:, :, 0]
    best = None
    for i in range(lengths):
        s2 = max(float(resid[i] @ ci_r[i]) / t.size, 1e-300)
        nll = t.size * math.log(s2) + 2.0 * float(np.sum(np.log(np.diag(chol[i]))))
        if best is None or nll < best[0]:
            pred = float(np.array([1.0, float(t.size)]) @ betas[i] + k_new[i] @ ci_r[i])
            best = (nll, pred)
    return best[1]


class GaussianProcess(RelativeTracker):
    """``gp``: Gaussian-process extrapolation over time of the last ``samples`` relative
    positions (:func:`gp_forecast`), with the measurement-noise variance ``noise`` (length²;
    from the run's declared sensor noise)."""

    name = "gp"

    def __init__(self, samples: int = 8, noise: float = 0.0) -> None:
        if samples < 3:
            raise ValueError(f"samples must be >= 3, got {samples}")
        if not noise >= 0.0:
            raise ValueError(f"noise must be >= 0, got {noise}")
        super().__init__(history=samples)
        self.noise = noise

    def forecast(self) -> np.ndarray:
        if len(self.history) < 2:
            raise NotFitted("gp needs two relative positions")
        return gp_forecast(np.array(self.history), self.noise)


class Kalman(RelativeTracker):
    """``kalman``: constant-velocity Kalman filter on the relative position (per tick).

    State ``[x, y, vx, vy]`` with ``x_{j+1} = x_j + v_j``; white-acceleration process noise of
    variance ``accel`` (length² per tick⁴); measurement noise from the run's declared range and
    bearing noise (``sigma_r``, ``sigma_theta``), mapped to xy at each measurement, plus where
    the snap left the follower off its rod end: the rod-end reading's variance at the settled
    reading's distance and the actuation variance ``move_variance``, per coordinate.
    """

    name = "kalman"
    F = np.block([[np.eye(2), np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])

    def __init__(self, sigma_r: float = 0.0, sigma_theta: float = 0.0, accel: float = 1e-3,
                 move_variance: float = 0.0) -> None:
        super().__init__(history=1)
        for name, value in (("sigma_r", sigma_r), ("sigma_theta", sigma_theta)):
            if not value >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        if not accel > 0.0:
            raise ValueError(f"accel must be > 0, got {accel}")
        self.sigma_r, self.sigma_theta, self.move_variance = sigma_r, sigma_theta, move_variance
        half, one = 0.5 * np.eye(2), np.eye(2)
        self.Q = accel * np.block([[0.25 * one, half], [half, one]])
        self.mean: np.ndarray | None = None
        self.cov: np.ndarray | None = None

    def forecast(self) -> np.ndarray:
        if self.mean is None:
            raise NotFitted("kalman needs one relative position")
        return (self.F @ self.mean)[:2]

    def _predict_step(self) -> None:
        self.mean = self.F @ self.mean
        self.cov = self.F @ self.cov @ self.F.T + self.Q

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        noise = reading_covariance(settled.r, settled.theta, self.sigma_r, self.sigma_theta)
        if settled.rod is not None:  # the snap put it off the rod end: the reading and the move
            rod = float(np.hypot(*settled.rod))
            snap = reading_variance(rod, self.sigma_r, self.sigma_theta) + self.move_variance
            noise += snap * np.eye(2)
        noise += 1e-12 * np.eye(2)
        x = relative(settled)
        if self.mean is None:
            self.mean = np.r_[x, 0.0, 0.0]
            self.cov = np.block([[noise, np.zeros((2, 2))], [np.zeros((2, 2)), np.eye(2)]])
            return float(x[0]), float(x[1])
        self._predict_step()
        if target is not None:  # lost: predict only
            innovation_cov = self.cov[:2, :2] + noise
            gain = np.linalg.solve(innovation_cov, self.cov[:2, :]).T
            self.mean = self.mean + gain @ (x - self.mean[:2])
            self.cov = self.cov - gain @ self.cov[:2, :]
            self.cov = 0.5 * (self.cov + self.cov.T)
        return float(self.mean[0]), float(self.mean[1])

    def skip(self) -> None:
        if self.mean is not None:
            self._predict_step()


ONE = np.ones(1)  # the affine regressor's constant
SUMMARY_PAIRS = 512
"""How many pairs an ``arx`` that keeps every pair (``window`` None) fits from the pairs
themselves; beyond it, from their triangular factor (:class:`_Triangular`): the same
least-squares solution and the same rank cut, at a cost per tick that no longer grows with the
run (refitting every kept pair made a long ``auto`` run's ticks dearer by about 5 ms per
thousand ticks with 3 followers). Every run of up to this many ticks is computed as before, to
the bit."""


class _Triangular:
    """The R factor of ``[Φ | Y]`` over least-squares rows ``(φ, y)``, made from the rows kept
    so far and updated row by row (at most ``p + 2`` rows of it, whatever the number of
    rows): ``R[:p, :p]`` has the singular values and right singular vectors of ``Φ``,
    ``R[:p, p:]`` is ``Qᵀ Y``, so the minimum-norm solution and the projector onto ``Φ``'s
    row space follow from a ``p × p`` SVD."""

    def __init__(self, rows: np.ndarray, targets: np.ndarray) -> None:
        self.p = rows.shape[1]
        self.r = np.linalg.qr(np.hstack([rows, targets]), mode="r")

    def add(self, row: np.ndarray, target: np.ndarray) -> None:
        self.r = np.linalg.qr(np.vstack([self.r, np.concatenate([row, target])]), mode="r")

    def fit(self) -> tuple[np.ndarray, np.ndarray]:
        """The coefficients ``pinv(Φ) Y`` (p, 2), singular values below :data:`RCOND` of the
        largest cut as :func:`numpy.linalg.pinv` cuts them, and the projector ``pinv(Φ) Φ``."""
        p = self.p
        u, sv, vt = np.linalg.svd(self.r[:p, :p], full_matrices=False)
        kept = sv > RCOND * sv.max()
        u, sv, vt = u[:, kept], sv[kept], vt[kept]
        return vt.T @ ((u.T @ self.r[:p, p:]) / sv[:, None]), vt.T @ vt


class ARX(Policy):
    """``arx``: least-squares autoregression with the leader's displacement as input.

    Before moving at tick ``j+1`` the follower has not moved since it settled at tick ``j``, so
    ``u_j = relative(pre_{j+1}) - relative(settled_j)`` is the leader's displacement. The model
    ``x_{i+1} = sum_k (A_k x_{i-k} + B_k u_{i-k}) (+ c)``, ``k < order``, is fitted by least
    squares (minimum norm, singular values below ``1e-10`` of the largest cut) over the
    ``window`` newest pairs (all if None). ``record`` rebuilds each past ``u`` from the settled
    reading and the follower's displacement ``target``; a lost or missed tick restarts the
    chain of samples.
    This is EDMD with control on ``[x, u]`` (an EDMDc-style idea), least squares row by row.
    """

    def __init__(self, order: int = 1, window: int | None = 10, affine: bool = True,
                 name: str | None = None) -> None:
        if order < 1:
            raise ValueError(f"order must be >= 1, got {order}")
        if window is not None and window < 1:
            raise ValueError(f"window must be >= 1 or None, got {window}")
        self.order, self.window, self.affine = order, window, affine
        self.name = name or "arx"
        # the newest samples, x_{j-order} .. x_j and u_{j-order} .. u_{j-1}, as far back as a
        # regressor's lags reach (each pair's is made once, when its sample arrives): xs[i]
        # and us[i] belong to the same tick
        self.xs: deque[np.ndarray] = deque(maxlen=order + 1)
        self.us: deque[np.ndarray] = deque(maxlen=order)
        self.last_seen: np.ndarray | None = None  # measured relative(settled_j)
        # each pair's regressor and target, made once when its sample arrives (a pair never
        # changes while it is kept): the newest ``window`` of them, all if None
        self._pairs: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=window)
        # with every pair kept, once they outnumber SUMMARY_PAIRS: their triangular factor,
        # which the fit is made from instead (the pairs are no longer kept)
        self._summary: _Triangular | None = None
        # the fit of the data above (coefficients, projector), until they change
        self._fitted: tuple[np.ndarray, np.ndarray] | None = None

    def _regressor(self, end: int, u_now: np.ndarray | None = None) -> np.ndarray:
        """``[x_end, u_end, x_{end-1}, u_{end-1}, ... (, 1)]`` over ``order`` lags of the
        policy's samples, ``u_now`` appended to its ``u`` when given (the coming
        prediction's)."""
        parts = []
        for k in range(self.order):  # near the deques' end: each index is O(1)
            i = end - k
            u = u_now if u_now is not None and i == len(self.us) else self.us[i]
            parts += [self.xs[i], u]
        if self.affine:
            parts.append(ONE)
        return np.concatenate(parts)

    def _fit(self) -> tuple[np.ndarray, np.ndarray]:
        """The least-squares coefficients (p, 2) and the projector onto the fitted regressors'
        span (p, p), remembered until ``record`` or ``skip`` changes the data: ``auto`` asks
        for a proposal twice a tick (its proposal, then its score in ``record``, before the
        policy learns), from the same data."""
        if self._fitted is not None:
            return self._fitted
        if self._summary is not None:
            self._fitted = self._summary.fit()
            return self._fitted
        # pairs (phi_i -> x_{i+1}), i = order-1 .. j-1, the newest ``window`` of them
        if not self._pairs:
            raise NotFitted(f"{self.name} needs {self.order + 1} connected samples")
        phi = np.array([row for row, _ in self._pairs])
        target = np.array([x for _, x in self._pairs])
        pinv = np.linalg.pinv(phi, rcond=RCOND)
        self._fitted = (pinv @ target, pinv @ phi)
        return self._fitted

    def _coefficients(self) -> np.ndarray:
        return self._fit()[0]

    def _now(self, pre: Sensing) -> np.ndarray:
        """The regressor of the coming prediction, from the pre-move sensing."""
        if self.last_seen is None:
            raise NotFitted(f"{self.name} needs one settled measurement")
        if len(self.xs) < self.order:  # its lags reach before the chain's start
            raise NotFitted(f"{self.name} needs {self.order} connected samples to predict")
        return self._regressor(len(self.xs) - 1, u_now=relative(pre) - self.last_seen)

    def leverage(self, pre: Sensing) -> float | None:
        """How far the coming regressor lies outside the span of the fitted ones, relative to
        its length: ``|(I - P) phi| / |phi|`` (0: the prediction interpolates the data; near 1:
        the minimum-norm fit sets most of it to zero). None while the model cannot fit."""
        try:
            phi = self._now(pre)
            _, projector = self._fit()
        except NotFitted:
            return None
        return float(np.linalg.norm(phi - projector @ phi) / np.linalg.norm(phi))

    def propose(self, pre: Sensing) -> Proposal:
        phi = self._now(pre)
        x = phi @ self._coefficients()
        return Proposal(relative(pre) - x, (float(x[0]), float(x[1])))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        self._fitted = None
        seen = relative(settled)
        if target is None:
            # Lost: the follower is off its ideal position by an unknown amount, and bridging
            # with the model's own predictions compounds (a fitted A may be unstable). Restart
            # the chain at the next tick that sees the rod; persist stands in meanwhile.
            self.skip()
            return float(seen[0]), float(seen[1])
        if self.last_seen is not None:
            self.us.append(seen + np.asarray(target) - self.last_seen)
        else:
            self._restart()
        self.xs.append(seen)
        self.last_seen = seen
        if len(self.us) >= self.order:  # the pair ending at this sample
            row = self._regressor(len(self.us) - 1)
            if self._summary is not None:
                self._summary.add(row, seen)
            elif self.window is None and len(self._pairs) == SUMMARY_PAIRS:
                # fitted from their triangular factor from now on: the pairs are not needed
                self._summary = _Triangular(np.array([r for r, _ in self._pairs] + [row]),
                                            np.array([x for _, x in self._pairs] + [seen]))
                self._pairs.clear()
            else:
                self._pairs.append((row, seen))
        return float(seen[0]), float(seen[1])

    def _restart(self) -> None:
        """A new chain of samples: what was learnt of the old one is dropped."""
        self.xs.clear()
        self.us.clear()
        self._pairs.clear()
        self._summary = None

    def skip(self) -> None:
        """The leader's displacement over a missed tick is unknown: restart the chain."""
        self._fitted = None
        self._restart()
        self.last_seen = None
