"""Data-streaming EDMD: the follower's one-step predictor (pure numpy).

`StreamingEDMD` implements the paper's Algorithm 1 (batch pseudoinverse refitted at every
step) and an online variant with rank-one (Sherman–Morrison) updates, plus the options of
design §6 beyond the paper: time-delay lifting, an affine observable, exponential forgetting,
a sliding window and Tikhonov regularisation. `delay_embed` is the time-delay (Hankel)
lifting of a whole measurement history.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["NotFitted", "StreamingEDMD", "delay_embed"]

FloatArray = NDArray[np.float64]

# The online estimator starts (or resumes) its rank-one recursion only once the weighted
# data matrix has a condition number below this. The recursion works with the inverse Gram
# matrix P, whose condition number is the square of the data's, so its rounding error is
# about eps * cond**2 ~ 2e-10 relative at this limit (far less in practice); a worse
# conditioned fit is computed by the exact pseudoinverse instead.
_MAX_RECURSIVE_COND = 1e3
# A window downdate with Sherman–Morrison denominator 1 - w x^T P x (in (0, 1]) amplifies
# the rounding errors already in P and K by up to its inverse; updates (denominator >= 1)
# do not. Once the product of these factors since the last exact fit exceeds this bound,
# the fit is recomputed from the window's pairs. For a window much longer than n the
# factors are about 1 / (1 - n / window), so this happens every ~2.3 window / n pairs at a
# cost O(window n^2): O(n^3) amortised per pair, whatever the history length.
_MAX_DOWNDATE_GROWTH = 10.0
# Forgetting without ridge and without a window: data that stop exciting a direction make the
# weighted Gram matrix G decay there by `forget` per pair, and P = G^{-1} grows without bound
# (recursive-least-squares wind-up). The recursion is stopped once the bound
# trace(P) * trace(G) >= cond(G) reaches this (the square of the limit at which it starts,
# times a margin of 100); the fit is then the exact pseudoinverse of a bounded summary, as at
# the start, until the data are well conditioned again.
_MAX_WINDUP = 100.0 * _MAX_RECURSIVE_COND**2


class NotFitted(RuntimeError):
    """Too few samples to fit or predict yet; the message says how many are needed."""


def delay_embed(history: ArrayLike, delays: int) -> FloatArray:
    """Lift a measurement history by time-delay (Hankel) embedding.

    Parameters
    ----------
    history : array_like, shape (m, d)
        Measurements ``z_0 ... z_{m-1}``, oldest first.
    delays : int
        Number ``D >= 0`` of past copies appended to each measurement.

    Returns
    -------
    ndarray, shape (m - D, d * (D + 1))
        Row ``i`` is ``[z_{i+D}, z_{i+D-1}, ..., z_i]``: the newest measurement first, then
        its ``D`` predecessors. The first ``D`` measurements only fill the delay line.

    Raises
    ------
    ValueError
        If `history` is not a finite 2-D array with more than `delays` rows, or `delays` is
        not an integer ``>= 0``.

    Examples
    --------
    >>> delay_embed([[1.0], [2.0], [3.0]], delays=1)
    array([[2., 1.],
           [3., 2.]])
    """
    delays = _check_count("delays", delays, minimum=0)
    samples = np.asarray(history, dtype=float)
    if samples.ndim != 2:
        raise ValueError(f"history must be a 2-D array (m, d), got shape {samples.shape}")
    if samples.shape[0] <= delays:
        raise ValueError(
            f"history must have more than delays={delays} rows, got {samples.shape[0]}"
        )
    if not np.isfinite(samples).all():
        raise ValueError("history must contain only finite values")
    m = samples.shape[0]
    return np.hstack([samples[delays - k : m - k] for k in range(delays + 1)])


class StreamingEDMD:
    """Data-streaming EDMD: fit a Koopman matrix to a measurement stream, predict one step.

    Each measurement ``z_i`` (shape ``(d,)``) is lifted to ``psi_i`` (shape ``(n,)``)::

        psi_i = [z_i, z_{i-1}, ..., z_{i-D}, 1]      (D = delays; the 1 only if affine)

    so ``n = d * (D + 1) + affine``. With lifted samples ``psi_0 ... psi_m`` the snapshot
    pairs are ``X = [psi_0 ... psi_{m-1}]`` and ``Y = [psi_1 ... psi_m]`` (both
    ``(n, m)``), and ``K`` (``(n, n)``) solves the weighted, regularised least-squares
    problem::

        K = argmin  sum_i w_i ||y_i - K x_i||^2 + ridge * ||K||_F^2,   w_i = forget**(m-1-i)

    over the ``window`` newest pairs (all pairs if ``window`` is None). With ``W =
    diag(w)`` the solution is ``K = Y W X^T (X W X^T + ridge I)^{-1}``; it is computed as
    ``K = Y W^{1/2} (X W^{1/2})^+`` (Moore–Penrose, ``numpy.linalg.pinv``) when ``ridge ==
    0``, so rank-deficient data still get the minimum-norm fit, and as the pseudoinverse
    of the data augmented with ``sqrt(ridge) I`` otherwise. The defaults give the paper's
    Algorithm 1: ``K = Y X^+`` and the prediction ``K psi_m``, of which the first ``d``
    entries (the measurement block) are returned. Singular values of the (weighted) data
    below ``rcond`` times the largest count as zero: a stream that is rank-deficient in
    exact arithmetic (a follower moving at constant velocity, say) carries rounding noise of
    ~1e-15 relative in the missing directions, and the bare pseudoinverse (numpy's default
    cut-off ~4e-16) would amplify that noise into the prediction.

    ``online=False`` refits ``K`` from the stored history at each prediction (cost
    ``O(m n^2)``). ``online=True`` updates ``K`` and ``P = (X W X^T + ridge I)^{-1}`` by
    recursive least squares at each `observe`: Sherman–Morrison rank-one steps, ``O(n^2)``
    per pair whatever the history length (``O(n^3)`` when forgetting and ridge are
    combined). The new pair is added and, with a window, the pair leaving it is removed by
    a rank-one downdate; the window's fit is recomputed exactly from its pairs whenever the
    downdates' error amplification reaches a bound (amortised ``O(n^3)``). While ``X W X^T
    + ridge I`` is singular or badly conditioned (too few independent pairs, e.g. at the
    start), the online estimator computes the same pseudoinverse fit as the batch one from
    a bounded summary of the data (the window's pairs, or a ``(2n, 2n)`` triangular factor
    of all pairs) and starts the recursion from the exact inverse once the data are well
    conditioned. From then on the two agree to rounding error.

    Parameters
    ----------
    online : bool, default False
        Recursive rank-one updates (True) or the batch pseudoinverse (False).
    delays : int, default 0
        Number ``D >= 0`` of past measurements in the lifted vector.
    affine : bool, default False
        Append the constant observable 1 to the lifted vector.
    forget : float, default 1.0
        Exponential forgetting factor in ``(0, 1]``; a pair ``k`` steps older than the
        newest has weight ``forget**k``.
    window : int or None, default None
        Use only the ``window >= 1`` newest pairs.
    ridge : float, default 0.0
        Tikhonov regularisation ``>= 0``.
    rcond : float, default 1e-10
        Relative cut-off for small singular values in the pseudoinverse, in ``[0, 1)``.

    Attributes
    ----------
    K : ndarray, shape (n, n)
        The fitted matrix (a copy).
    n_observed : int
        Measurements observed since construction or `reset`.
    n_pairs : int
        Snapshot pairs the current fit uses.
    lifted_dim : int
        ``n``, the length of the lifted vector.
    recursive : bool
        Whether the online estimator is currently updating ``K`` by rank-one steps.

    Notes
    -----
    With ``forget < 1`` and ``ridge == 0``, data that stop exciting some direction make
    ``X W X^T`` decay towards singularity in that direction and ``P`` grow like
    ``forget**-k`` (the classic recursive-least-squares wind-up). Without a window the
    online estimator therefore keeps its ``(2n, 2n)`` summary of the pairs while recursing
    (one QR step per pair) and tracks ``trace(X W X^T)``; once ``trace(P) trace(X W X^T)``
    (an upper bound of the condition number) passes ``1e8 n^2`` it stops the recursion and
    computes the batch pseudoinverse fit from the summary until the data are well
    conditioned again. A ``ridge`` keeps ``P <= I / ridge``; a ``window`` is refitted from its
    pairs when a downdate nearly empties a direction. So no setting winds up: the online fit
    follows the batch one to about ``eps * cond(X W^{1/2})**2`` relative, at most ~1e-10
    while recursing (the recursion runs only below cond 1e3 at its start).

    References
    ----------
    M. O. Williams, I. G. Kevrekidis and C. W. Rowley, "A data-driven approximation of
    the Koopman operator: extending dynamic mode decomposition", J. Nonlinear Sci. 25
    (2015) 1307-1346. The data-streaming form is Algorithm 1 of Wang, Banks, Mezić and
    Hikihara, "Trajectory estimation in unknown nonlinear manifold using Koopman operator
    theory" (``paper/trajectory-estimation-koopman.tex``).

    Examples
    --------
    A linear system ``z_{i+1} = A z_i`` is recovered exactly:

    >>> import numpy as np
    >>> A = np.array([[0.9, -0.2], [0.2, 0.9]])
    >>> est = StreamingEDMD(online=True)
    >>> z = np.array([1.0, 0.5])
    >>> for _ in range(10):
    ...     est.observe(z)
    ...     z = A @ z
    >>> bool(np.allclose(est.K, A))
    True
    >>> bool(np.allclose(est.predict(), z))
    True
    >>> est.predict([1.0, 0.0]).round(12)
    array([0.9, 0.2])
    """

    def __init__(
        self,
        online: bool = False,
        delays: int = 0,
        affine: bool = False,
        forget: float = 1.0,
        window: int | None = None,
        ridge: float = 0.0,
        rcond: float = 1e-10,
    ) -> None:
        self.online = _check_bool("online", online)
        self.delays = _check_count("delays", delays, minimum=0)
        self.affine = _check_bool("affine", affine)
        self.forget = _check_real("forget", forget, "(0, 1]", lambda v: 0.0 < v <= 1.0)
        self.window = None if window is None else _check_count("window", window, minimum=1)
        self.ridge = _check_real("ridge", ridge, "[0, inf)", lambda v: 0.0 <= v < np.inf)
        self.rcond = _check_real("rcond", rcond, "[0, 1)", lambda v: 0.0 <= v < 1.0)
        self.reset()

    def reset(self) -> None:
        """Forget all data and the fit; keep the settings."""
        self._dim: int | None = None
        # Delay line [z_m, ..., z_{m-D}(, 1)]: the lifted newest sample once D + 1
        # measurements have been observed.
        self._line: FloatArray | None = None
        self._n_observed = 0
        self._n_pairs_seen = 0
        # Lifted samples, oldest first: all of them in batch mode, the window + 1 newest
        # when there is a window; none for the online estimator without a window.
        self._history: FloatArray | None = None
        self._history_len = 0
        self._K: FloatArray | None = None  # batch: cache cleared by observe
        self._P: FloatArray | None = None  # online: inverse regularised Gram matrix
        self._downdate_growth = 1.0  # online, window: error amplification since a refit
        # Online without a window, before the recursion starts: R with R^T R equal to the
        # weighted sum of [x; y][x; y]^T, i.e. the pairs up to an orthogonal transform.
        self._sqrt_data: FloatArray | None = None
        self._gram_trace = 0.0  # online, wind-up guard: trace of X W X^T

    # ------------------------------------------------------------------ public API

    @property
    def n_observed(self) -> int:
        """Measurements observed since construction or `reset`."""
        return self._n_observed

    @property
    def n_pairs(self) -> int:
        """Snapshot pairs the current fit uses (at most `window`)."""
        if self.window is None:
            return self._n_pairs_seen
        return min(self._n_pairs_seen, self.window)

    @property
    def lifted_dim(self) -> int:
        """Length ``n = d * (delays + 1) + affine`` of the lifted vector.

        Raises
        ------
        RuntimeError
            Before the first `observe` (the measurement dimension ``d`` is not known).
        """
        if self._dim is None:
            raise RuntimeError("lifted_dim is known only after the first observe")
        return self._dim * (self.delays + 1) + int(self.affine)

    @property
    def recursive(self) -> bool:
        """Whether the online estimator currently updates K by rank-one steps."""
        return self._P is not None

    @property
    def K(self) -> FloatArray:
        """The fitted matrix, shape ``(n, n)`` (a copy).

        Raises
        ------
        RuntimeError
            Before ``delays + 2`` measurements have been observed.
        """
        return self._fitted_K().copy()

    def observe(self, z: ArrayLike) -> None:
        """Append the newest measurement and update the fit.

        Parameters
        ----------
        z : array_like, shape (d,)
            The measurement; ``d`` is fixed by the first call.

        Raises
        ------
        ValueError
            If `z` is not a finite 1-D array of the established length.
        """
        z = self._check_measurement(z)
        if self._line is None:
            self._dim = z.size
            self._line = np.zeros(z.size * (self.delays + 1) + int(self.affine))
            if self.affine:
                self._line[-1] = 1.0
        x = self._line if self._n_observed > self.delays else None
        psi = self._line = self._lift(z)
        self._n_observed += 1
        if self._n_observed <= self.delays:
            return  # still filling the delay line: no lifted sample yet
        leaving = self._leaving_pair() if self.online and x is not None else None
        if not self.online or self.window is not None:
            self._push_history(psi)  # the online estimator without a window keeps none
        if x is None:
            return  # the first lifted sample: no pair yet
        self._n_pairs_seen += 1
        if not self.online:
            self._K = None
        elif self._P is None:
            if self.window is None:
                self._absorb_pair(x, psi)
            self._refit()
        else:
            self._recursive_step(x, psi, leaving)
            if self._guards_windup:
                self._absorb_pair(x, psi)
                self._gram_trace = self.forget * self._gram_trace + float(x.dot(x))
                if float(np.trace(self._P)) * self._gram_trace > _MAX_WINDUP * x.size**2:
                    self._P = None
                    self._refit()

    def predict(self, z: ArrayLike | None = None) -> FloatArray:
        """Predict the next measurement.

        Parameters
        ----------
        z : array_like, shape (d,), optional
            If given, predict from `z` taken as the newest measurement (one step after the
            last observed one, whose delays it uses), without appending it: for when the
            newest measurement is only approximately known. By default predict from the
            last observed measurement.

        Returns
        -------
        ndarray, shape (d,)
            The measurement block of ``K psi``.

        Raises
        ------
        RuntimeError
            Before ``delays + 2`` measurements have been observed.
        ValueError
            If `z` is not a finite 1-D array of the observed length.
        """
        K = self._fitted_K()
        psi = self._line if z is None else self._lift(self._check_measurement(z))
        return K[: self._dim] @ psi

    def noise_gain(self, z: ArrayLike | None = None) -> float:
        """The statistical leverage ``h = psi^T (X W X^T + ridge I)^+ psi`` of the lifted
        sample a prediction starts from (`z` as in `predict`): how many readings' worth of
        noise the fit carries into that prediction (not :meth:`Policy.leverage
        <agents.policies.base.Policy.leverage>`, the share of a regressor outside the data's
        span, which ``auto`` scales young scores by). With readings of noise variance ``s`` in the
        measured block, a least-squares prediction ``K psi`` errs by ``s h`` from the fit
        alone (forgetting counted as fewer pairs), where reusing the newest reading, as
        ``persist`` does, errs by ``s``. Below 1 the data determine the prediction better
        than one reading; far above it ``psi`` lies where the pairs barely reach (too few of
        them, or a direction only their noise spans), and the fit's coefficients there are
        the noise's. Pseudoinverse directions, as in the fit: below ``rcond`` they count as
        absent.

        Raises
        ------
        RuntimeError
            Before ``delays + 2`` measurements have been observed.
        """
        self._fitted_K()
        psi = self._line if z is None else self._lift(self._check_measurement(z))
        if self._P is not None:  # online, recursing: P is that inverse
            return float(psi @ self._P @ psi)
        x, _ = self._weighted_pairs()
        gram = x @ x.T
        if self.ridge > 0.0:
            gram = gram + self.ridge * np.eye(gram.shape[0])
        return float(psi @ np.linalg.pinv(gram, rcond=self.rcond**2, hermitian=True) @ psi)

    # ------------------------------------------------------------------ internals

    def _check_measurement(self, z: ArrayLike) -> FloatArray:
        try:
            arr = np.asarray(z, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"z must be a 1-D array of floats: {exc}") from exc
        if arr.ndim != 1 or arr.size == 0:
            raise ValueError(f"z must be a non-empty 1-D array, got shape {arr.shape}")
        if self._dim is not None and arr.size != self._dim:
            raise ValueError(
                f"z must have length {self._dim} (fixed by the first observe), got {arr.size}"
            )
        if not all(map(math.isfinite, arr.tolist())):  # the fastest check for short z
            raise ValueError(f"z must be finite, got {arr}")
        return arr

    def _lift(self, z: FloatArray) -> FloatArray:
        """The delay line ``(n,)`` with `z` pushed in as the newest measurement (a copy)."""
        d = self._dim
        psi = self._line.copy()
        psi[d : d * (self.delays + 1)] = self._line[: d * self.delays]
        psi[:d] = z
        return psi

    def _fitted_K(self) -> FloatArray:
        if self._n_pairs_seen == 0:
            raise NotFitted(
                f"StreamingEDMD(delays={self.delays}) needs {self.delays + 2} observed "
                f"samples to fit K, it has {self._n_observed}"
            )
        if self._K is None:  # batch mode, new data since the last fit
            self._refit()
        return self._K

    def _push_history(self, psi: FloatArray) -> None:
        if self._history is None:
            capacity = 64 if self.window is None else 2 * (self.window + 1)
            self._history = np.empty((capacity, psi.size))
        if self._history_len == self._history.shape[0]:
            if self.window is None:
                grown = np.empty((2 * self._history_len, psi.size))
                grown[: self._history_len] = self._history
                self._history = grown
            else:  # keep the `window` newest samples; with psi they span the window
                keep = self._history[self._history_len - self.window : self._history_len]
                self._history[: self.window] = keep
                self._history_len = self.window
        self._history[self._history_len] = psi
        self._history_len += 1

    def _held_samples(self) -> FloatArray:
        """Lifted samples ``(p + 1, n)`` spanning the pairs in use, oldest first."""
        start = 0 if self.window is None else max(0, self._history_len - self.window - 1)
        return self._history[start : self._history_len]

    def _leaving_pair(self) -> tuple[FloatArray, FloatArray] | None:
        """The pair that the next one pushes out of a full window (copies), else None."""
        if self.window is None:
            return None
        held = self._held_samples()
        if held.shape[0] < self.window + 1:
            return None
        return held[0].copy(), held[1].copy()

    def _absorb_pair(self, x: FloatArray, y: FloatArray) -> None:
        """Add a pair to the triangular summary of all pairs (online, no window)."""
        row = np.concatenate([x, y])[np.newaxis]
        if self._sqrt_data is None:
            stacked = row
        else:
            stacked = np.vstack([np.sqrt(self.forget) * self._sqrt_data, row])
        # With stacked = Q R (Q orthonormal columns), R keeps stacked^T stacked, and the fit
        # Y W^{1/2} (X W^{1/2})^+ = R_y^T (R_x^T)^+, R_x, R_y the first and last n columns
        # of R: at most 2n rows ever need to be kept.
        if stacked.shape[0] > stacked.shape[1]:
            stacked = np.linalg.qr(stacked, mode="r")
        self._sqrt_data = stacked

    def _weighted_pairs(self) -> tuple[FloatArray, FloatArray]:
        """``(X W^{1/2}, Y W^{1/2})``, each ``(n, columns)``, of the pairs in use."""
        if self.online and self.window is None:
            n = self._sqrt_data.shape[1] // 2
            return self._sqrt_data[:, :n].T, self._sqrt_data[:, n:].T
        held = self._held_samples()
        x, y = held[:-1].T, held[1:].T
        if self.forget < 1.0:
            ages = np.arange(x.shape[1] - 1, -1, -1)
            root_weights = np.sqrt(self.forget) ** ages
            x, y = x * root_weights, y * root_weights
        return x, y

    def _refit(self) -> None:
        """Fit K from the held data; online, start the recursion if well conditioned."""
        x, y = self._weighted_pairs()
        if self.ridge > 0.0:
            # Tikhonov as least squares on the data plus n pseudo-pairs (sqrt(ridge) e_k, 0).
            n = x.shape[0]
            x = np.hstack([x, np.sqrt(self.ridge) * np.eye(n)])
            y = np.hstack([y, np.zeros((n, n))])
        self._K = y @ np.linalg.pinv(x, rcond=self.rcond)
        self._downdate_growth = 1.0
        if self.online:
            self._P = _inverse_gram(x)
            if self._P is not None and self._guards_windup:
                self._gram_trace = float(np.sum(x * x))  # trace of X W X^T
            elif self._P is not None:
                self._sqrt_data = None

    @property
    def _guards_windup(self) -> bool:
        """Online fit that can wind up (forgetting, no ridge, no window): it keeps the
        bounded summary of its pairs while recursing, to refit from when P grows too large."""
        return self.online and self.window is None and self.forget < 1.0 and self.ridge == 0.0

    def _recursive_step(
        self, x: FloatArray, y: FloatArray, leaving: tuple[FloatArray, FloatArray] | None
    ) -> None:
        """Add pair ``(x, y)`` and remove `leaving` by rank-one steps on ``K`` and ``P``."""
        lam = self.forget
        if lam < 1.0:
            beta = (1.0 - lam) * self.ridge
            if beta == 0.0:
                # G <- lam G and C <- lam C (C = Y W X^T): P scales, K = C P does not.
                self._P /= lam
            else:
                # G <- lam G + beta I keeps the ridge at `ridge`, not lam * ridge:
                # P' = (lam P^{-1} + beta I)^{-1} = (lam I + beta P)^{-1} P, and with
                # C' = lam C, K' = C' P' = K (I - beta P'). lam I + beta P has eigenvalues
                # in [lam, 1] because P <= I / ridge, so the solve is well conditioned.
                n = self._P.shape[0]
                self._P = _symmetric_part(
                    np.linalg.solve(lam * np.eye(n) + beta * self._P, self._P)
                )
                self._K -= beta * (self._K @ self._P)
        self._rank_one(x, y, 1.0)
        if leaving is not None and not self._rank_one(*leaving, -(lam**self.window)):
            self._refit()

    def _rank_one(self, x: FloatArray, y: FloatArray, weight: float) -> bool:
        """Add the pair ``(x, y)`` with `weight` to the fit (remove it if negative).

        Returns False, leaving the fit unchanged, if a removal would make the Gram matrix
        (nearly) singular or push the accumulated error amplification past its bound.
        """
        Px = self._P.dot(x)
        denominator = 1.0 + weight * x.dot(Px)
        if weight < 0.0:
            if denominator <= 0.0:
                return False
            self._downdate_growth /= denominator
            if self._downdate_growth > _MAX_DOWNDATE_GROWTH:
                return False
        coefficient = weight / denominator
        self._K += (y - self._K.dot(x))[:, np.newaxis] * (coefficient * Px)
        # P <- P - coefficient Px Px^T, applied as -+ u u^T with u = sqrt(|coefficient|) Px:
        # u_i u_j and u_j u_i are the same floating-point product, so P stays exactly
        # symmetric (see _symmetric_part for why that matters).
        u = math.sqrt(abs(coefficient)) * Px
        if coefficient > 0.0:
            self._P -= u[:, np.newaxis] * u
        else:
            self._P += u[:, np.newaxis] * u
        return True


def _inverse_gram(x: FloatArray) -> FloatArray | None:
    """``(x x^T)^{-1}`` for ``x`` of shape ``(n, c)``, or None unless well conditioned."""
    n, columns = x.shape
    if columns < n:
        return None
    u, s, _ = np.linalg.svd(x, full_matrices=False)
    if not s[-1] > s[0] / _MAX_RECURSIVE_COND:
        return None
    return _symmetric_part((u / s**2) @ u.T)


def _symmetric_part(P: FloatArray) -> FloatArray:
    """``(P + P^T) / 2``, the nearest symmetric matrix to ``P``.

    The recursion needs ``P`` exactly symmetric: rounding errors that make it asymmetric
    feed asymmetric errors into every later gain, the asymmetry grows, and ``P`` can lose
    positive definiteness. Steps that are not symmetric by construction (a matrix product
    or a solve) are therefore followed by this.
    """
    return 0.5 * (P + P.T)


def _check_bool(name: str, value: object) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a bool, got {value!r}")
    return bool(value)


def _check_count(name: str, value: object, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _check_real(name: str, value: object, interval: str, inside: Callable[[float], bool]) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number in {interval}, got {value!r}")
    if not inside(float(value)):  # NaN fails every comparison
        raise ValueError(f"{name} must be a real number in {interval}, got {value!r}")
    return float(value)
