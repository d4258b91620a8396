"""Tests of the follower's data-streaming EDMD (agents/estimators.py).

Ground truth: the paper's formula ``K = Y X^+`` and the closed-form weighted, regularised
least-squares solution built from the whole data at once; linear systems, which EDMD must
predict exactly; and the batch estimator, which the online one must match once the data
have full row rank.
"""

from __future__ import annotations

import numpy as np
import pytest

from agents.estimators import StreamingEDMD, delay_embed

# Any floating-point warning (division by zero, overflow, invalid value) is a bug here.
pytestmark = pytest.mark.filterwarnings("error")

ONLINE_BATCH_RTOL = 1e-9

CONFIGS = {
    "plain": {},
    "forget": {"forget": 0.9},
    "window": {"window": 25},
    "ridge": {"ridge": 0.5},
    "tiny ridge": {"ridge": 1e-9},
    "forget+window": {"forget": 0.95, "window": 30},
    "forget+ridge": {"forget": 0.9, "ridge": 0.1},
    "delays": {"delays": 2},
    "affine": {"affine": True},
    "everything": {"delays": 1, "affine": True, "forget": 0.97, "window": 40, "ridge": 1e-3},
}


def linear_stream(n_samples: int, seed: int) -> np.ndarray:
    """``(n_samples, 2)`` noisy linear stream ``z_{i+1} = A z_i + noise``."""
    rng = np.random.default_rng(seed)
    A = np.array([[0.95, -0.25], [0.25, 0.95]])
    z = rng.normal(size=2)
    out = np.empty((n_samples, 2))
    for i in range(n_samples):
        out[i] = z
        z = A @ z + 0.2 * rng.normal(size=2)
    return out


def nonlinear_stream(n_samples: int, seed: int) -> np.ndarray:
    """``(n_samples, 2)`` noisy nonlinear stream (rotation plus a tanh coupling)."""
    rng = np.random.default_rng(seed)
    A = np.array([[0.9, -0.3], [0.3, 0.9]])
    z = rng.normal(size=2)
    out = np.empty((n_samples, 2))
    for i in range(n_samples):
        out[i] = z
        z = A @ z + 0.4 * np.tanh(z[::-1] ** 2) + 0.2 * rng.normal(size=2)
    return out


STREAMS = {"linear": linear_stream, "nonlinear": nonlinear_stream}


def lifted(history: np.ndarray, delays: int = 0, affine: bool = False) -> np.ndarray:
    """Lifted samples ``(n, m - delays)`` as columns, built from the whole history."""
    psi = delay_embed(history, delays).T
    if affine:
        psi = np.vstack([psi, np.ones(psi.shape[1])])
    return psi


def closed_form_K(
    history: np.ndarray,
    delays: int = 0,
    affine: bool = False,
    forget: float = 1.0,
    window: int | None = None,
    ridge: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``(K, X W^{1/2})`` from the whole data: ``K = Y W X^T (X W X^T + ridge I)^{-1}``."""
    psi = lifted(history, delays, affine)
    X, Y = psi[:, :-1], psi[:, 1:]
    if window is not None:
        X, Y = X[:, -window:], Y[:, -window:]
    m = X.shape[1]
    w = forget ** np.arange(m - 1, -1, -1, dtype=float)
    n = X.shape[0]
    if ridge == 0.0:
        K = (Y * np.sqrt(w)) @ np.linalg.pinv(X * np.sqrt(w))
    else:
        K = np.linalg.solve((X * w) @ X.T + ridge * np.eye(n), (X * w) @ Y.T).T
    return K, X * np.sqrt(w)


def relative_difference(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# ---------------------------------------------------------------- online versus batch


@pytest.mark.parametrize("stream", STREAMS)
@pytest.mark.parametrize("config", CONFIGS)
def test_online_matches_batch_at_every_step(stream: str, config: str) -> None:
    options = CONFIGS[config]
    data = STREAMS[stream](400, seed=7)
    online = StreamingEDMD(online=True, **options)
    batch = StreamingEDMD(online=False, **options)
    delays = options.get("delays", 0)
    checked = recursive_steps = 0
    for i, z in enumerate(data):
        online.observe(z)
        batch.observe(z)
        if online.n_pairs == 0:
            continue
        _, xw = closed_form_K(data[: i + 1], **options)
        full_rank = options.get("ridge", 0.0) > 0 or np.linalg.matrix_rank(xw) == xw.shape[0]
        if not full_rank:
            continue
        diff = relative_difference(online.K, batch.K)
        assert diff <= ONLINE_BATCH_RTOL, f"step {i}: online differs from batch by {diff:.2e}"
        np.testing.assert_allclose(online.predict(), batch.predict(), rtol=1e-8, atol=1e-10)
        checked += 1
        recursive_steps += online.recursive
    assert checked >= 400 - delays - 20
    # The comparison must exercise the rank-one recursion, not only the pinv fallback.
    assert recursive_steps >= 0.9 * checked


@pytest.mark.parametrize("window", [1, 2, 3, 5, 8])
def test_online_matches_batch_for_short_windows(window: int) -> None:
    """Windows about as long as n: frequent near-singular downdates and exact refits."""
    data = nonlinear_stream(300, seed=3)
    online = StreamingEDMD(online=True, window=window, forget=0.9)
    batch = StreamingEDMD(window=window, forget=0.9)
    for i, z in enumerate(data):
        online.observe(z)
        batch.observe(z)
        if online.n_pairs == 0:
            continue
        _, xw = closed_form_K(data[: i + 1], window=window, forget=0.9)
        if np.linalg.matrix_rank(xw) == 2:
            assert relative_difference(online.K, batch.K) <= ONLINE_BATCH_RTOL


def test_online_matches_batch_when_window_loses_rank() -> None:
    """A window filled by a constant measurement is singular: both fall back to pinv."""
    rng = np.random.default_rng(11)
    data = np.vstack(
        [nonlinear_stream(80, seed=11), np.tile([0.3, -0.2], (30, 1)), rng.normal(size=(40, 2))]
    )
    online = StreamingEDMD(online=True, window=10)
    batch = StreamingEDMD(window=10)
    modes = set()
    for z in data:
        online.observe(z)
        batch.observe(z)
        if online.n_pairs:
            assert np.isfinite(online.K).all()
            np.testing.assert_allclose(online.K, batch.K, rtol=1e-9, atol=1e-9)
            modes.add(online.recursive)
    assert modes == {True, False}


def test_online_fallback_state_stays_bounded_for_rank_deficient_data() -> None:
    """Delay vectors of a linear system span only d of n directions, forever."""
    A = np.array([[0.8, -0.5], [0.5, 0.8]])
    online = StreamingEDMD(online=True, delays=1)
    batch = StreamingEDMD(delays=1)
    z = np.array([1.0, 0.0])
    for _ in range(300):
        online.observe(z)
        batch.observe(z)
        z = A @ z / np.linalg.norm(A @ z)  # stay on the unit circle: no decay
    assert not online.recursive
    # The summary of all pairs is a (<= 2n, 2n) factor, however long the history.
    n = online.lifted_dim
    assert online._sqrt_data.shape[0] <= 2 * n
    np.testing.assert_allclose(online.K, batch.K, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(online.predict(), z, atol=1e-10)


# ---------------------------------------------------------------- batch versus formulas


@pytest.mark.parametrize("stream", STREAMS)
def test_batch_is_the_papers_formula(stream: str) -> None:
    data = STREAMS[stream](60, seed=1)
    est = StreamingEDMD()
    for z in data:
        est.observe(z)
    X, Y = data[:-1].T, data[1:].T
    K = Y @ np.linalg.pinv(X)
    np.testing.assert_allclose(est.K, K, rtol=1e-13, atol=0)
    np.testing.assert_allclose(est.predict(), K @ data[-1], rtol=1e-13)


@pytest.mark.parametrize("online", [False, True])
@pytest.mark.parametrize("config", CONFIGS)
def test_loop_of_observes_equals_closed_form_on_all_data(online: bool, config: str) -> None:
    options = CONFIGS[config]
    data = nonlinear_stream(150, seed=5)
    est = StreamingEDMD(online=online, **options)
    for z in data:
        est.observe(z)
    K, _ = closed_form_K(data, **options)
    assert relative_difference(est.K, K) <= ONLINE_BATCH_RTOL


def test_batch_rank_deficient_data_gets_the_minimum_norm_fit() -> None:
    """Two pairs, lifted dimension 3: K = Y X^+ as in the paper, fitting both pairs."""
    A = np.array([[0.5, 0.1, 0.0], [0.0, 0.7, 0.2], [0.3, 0.0, 0.6]])
    z = [np.array([1.0, 2.0, -1.0])]
    for _ in range(2):
        z.append(A @ z[-1])
    est = StreamingEDMD()
    for sample in z:
        est.observe(sample)
    X, Y = np.array(z[:-1]).T, np.array(z[1:]).T
    np.testing.assert_allclose(est.K, Y @ np.linalg.pinv(X), rtol=1e-13)
    np.testing.assert_allclose(est.K @ X, Y, rtol=1e-12)


# ---------------------------------------------------------------- exact on linear systems


@pytest.mark.parametrize("online", [False, True])
@pytest.mark.parametrize(
    "options", [{}, {"delays": 1}, {"affine": True}, {"forget": 0.8}, {"window": 6}]
)
def test_linear_system_is_predicted_exactly(online: bool, options: dict) -> None:
    A = np.array([[0.9, -0.3, 0.1], [0.3, 0.9, 0.0], [0.0, 0.1, 0.95]])
    est = StreamingEDMD(online=online, **options)
    z = np.array([1.0, -0.5, 0.25])
    for i in range(40):
        est.observe(z)
        z = A @ z
        if i >= est.delays + 4:
            np.testing.assert_allclose(est.predict(), z, rtol=0, atol=1e-10)


def test_affine_system_is_predicted_exactly_only_with_the_affine_observable() -> None:
    A = np.array([[0.8, -0.4], [0.4, 0.8]])
    b = np.array([1.0, -2.0])
    with_affine = StreamingEDMD(online=True, affine=True)
    without = StreamingEDMD(online=True)
    z = np.array([3.0, 1.0])
    for _ in range(30):
        with_affine.observe(z)
        without.observe(z)
        z = A @ z + b
    np.testing.assert_allclose(with_affine.predict(), z, atol=1e-10)
    assert np.linalg.norm(without.predict() - z) > 1e-3
    # The constant observable maps to itself: the last row of K is [0, ..., 0, 1].
    np.testing.assert_allclose(with_affine.K[-1], [0.0, 0.0, 1.0], atol=1e-10)
    np.testing.assert_allclose(with_affine.K[:2, :2], A, atol=1e-10)
    np.testing.assert_allclose(with_affine.K[:2, 2], b, atol=1e-10)


def test_delays_make_a_second_order_scalar_recurrence_exact() -> None:
    """z_{i+1} = 1.5 z_i - 0.7 z_{i-1} needs one delay; without it EDMD cannot be exact."""
    z = [1.0, 0.2]
    for _ in range(30):
        z.append(1.5 * z[-1] - 0.7 * z[-2])
    with_delay = StreamingEDMD(delays=1)
    without = StreamingEDMD()
    for sample in z[:-1]:
        with_delay.observe([sample])
        without.observe([sample])
    np.testing.assert_allclose(with_delay.predict(), [z[-1]], atol=1e-10)
    assert abs(without.predict()[0] - z[-1]) > 1e-3
    np.testing.assert_allclose(with_delay.K[0], [1.5, -0.7], atol=1e-10)
    np.testing.assert_allclose(with_delay.K[1], [1.0, 0.0], atol=1e-10)


# ---------------------------------------------------------------- lifting


def test_delay_embed_shapes_and_contents() -> None:
    history = np.arange(12.0).reshape(6, 2)  # z_i = [2i, 2i + 1]
    out = delay_embed(history, 2)
    assert out.shape == (4, 6)
    np.testing.assert_array_equal(out[0], [4, 5, 2, 3, 0, 1])  # [z_2, z_1, z_0]
    np.testing.assert_array_equal(out[-1], [10, 11, 8, 9, 6, 7])  # [z_5, z_4, z_3]
    np.testing.assert_array_equal(delay_embed(history, 0), history)


def test_lifted_dim_and_K_shape() -> None:
    est = StreamingEDMD(delays=2, affine=True)
    data = nonlinear_stream(10, seed=0)
    for z in data:
        est.observe(z)
    assert est.lifted_dim == 2 * 3 + 1
    assert est.K.shape == (7, 7)
    assert est.predict().shape == (2,)
    assert est.n_observed == 10
    assert est.n_pairs == 10 - 2 - 1


def test_predict_uses_the_lifted_newest_sample() -> None:
    """predict() is the measurement block of K psi_m, psi_m = [z_m, z_{m-1}, z_{m-2}, 1]."""
    data = nonlinear_stream(40, seed=2)
    est = StreamingEDMD(delays=2, affine=True)
    for z in data:
        est.observe(z)
    psi = np.concatenate([data[-1], data[-2], data[-3], [1.0]])
    np.testing.assert_allclose(est.predict(), est.K[:2] @ psi, rtol=1e-13)


# ---------------------------------------------------------------- predict(z) and state


@pytest.mark.parametrize("online", [False, True])
def test_predict_from_given_z_does_not_append(online: bool) -> None:
    data = nonlinear_stream(30, seed=4)
    est = StreamingEDMD(online=online, delays=1)
    for z in data:
        est.observe(z)
    K, before = est.K, est.predict()
    newest = np.array([0.3, -0.1])
    predicted = est.predict(newest)
    # newest is taken one step after the last observed sample, which becomes its delay.
    np.testing.assert_allclose(predicted, K[:2] @ np.concatenate([newest, data[-1]]))
    assert est.n_observed == 30
    np.testing.assert_array_equal(est.K, K)
    np.testing.assert_array_equal(est.predict(), before)


@pytest.mark.parametrize("online", [False, True])
@pytest.mark.parametrize("delays", [0, 2])
def test_predict_before_enough_data_says_what_is_needed(online: bool, delays: int) -> None:
    est = StreamingEDMD(online=online, delays=delays)
    needed = delays + 2
    for i in range(needed - 1):
        with pytest.raises(RuntimeError, match=f"needs {needed} .* it has {i}"):
            est.predict()
        est.observe([float(i), 1.0])
    with pytest.raises(RuntimeError, match=f"it has {needed - 1}"):
        _ = est.K
    est.observe([5.0, 2.0])
    assert est.predict().shape == (2,)


def test_lifted_dim_before_first_observe_is_an_error() -> None:
    with pytest.raises(RuntimeError, match="first observe"):
        _ = StreamingEDMD().lifted_dim


@pytest.mark.parametrize("online", [False, True])
def test_reset_forgets_data_but_keeps_settings(online: bool) -> None:
    data = nonlinear_stream(50, seed=6)
    est = StreamingEDMD(online=online, window=10, forget=0.9)
    for z in data:
        est.observe(np.concatenate([z, z]))
    est.reset()
    assert est.n_observed == 0 and est.n_pairs == 0
    assert est.window == 10 and est.forget == 0.9
    fresh = StreamingEDMD(online=online, window=10, forget=0.9)
    for z in data:  # a new measurement dimension is allowed after reset
        est.observe(z)
        fresh.observe(z)
    np.testing.assert_array_equal(est.K, fresh.K)


# ---------------------------------------------------------------- argument checks


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("online", "yes"),
        ("online", 1),
        ("online", None),
        ("affine", 0),
        ("delays", -1),
        ("delays", 1.5),
        ("delays", True),
        ("delays", "2"),
        ("forget", 0.0),
        ("forget", -0.5),
        ("forget", 1.0001),
        ("forget", float("nan")),
        ("forget", "0.9"),
        ("window", 0),
        ("window", -3),
        ("window", 2.5),
        ("window", False),
        ("ridge", -1e-9),
        ("ridge", float("nan")),
        ("ridge", float("inf")),
        ("ridge", None),
    ],
)
def test_bad_settings_raise_value_error_naming_them(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=name):
        StreamingEDMD(**{name: value})


def test_numpy_scalars_are_accepted_as_settings() -> None:
    est = StreamingEDMD(
        online=np.bool_(True), delays=np.int64(1), forget=np.float32(0.5), window=np.int32(4)
    )
    assert (est.online, est.delays, est.forget, est.window) == (True, 1, 0.5, 4)


@pytest.mark.parametrize(
    "z", [[1.0, 2.0, 3.0], [1.0], [np.nan, 1.0], [np.inf, 0.0], [[1.0, 2.0]], 1.0, [], ["a", "b"]]
)
def test_bad_measurements_raise_value_error_naming_z(z: object) -> None:
    est = StreamingEDMD()
    est.observe([0.0, 1.0])
    est.observe([1.0, 0.0])
    with pytest.raises(ValueError, match="z must"):
        est.observe(z)
    with pytest.raises(ValueError, match="z must"):
        est.predict(z)
    assert est.n_observed == 2


@pytest.mark.parametrize(
    ("history", "delays", "name"),
    [
        (np.ones(5), 0, "history"),
        (np.ones((3, 2)), 3, "history"),
        (np.full((3, 2), np.nan), 0, "history"),
        (np.ones((3, 2)), -1, "delays"),
        (np.ones((3, 2)), 1.0, "delays"),
    ],
)
def test_delay_embed_rejects_bad_arguments(history: np.ndarray, delays: int, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        delay_embed(history, delays)


@pytest.mark.parametrize("options", [{"forget": 0.9}, {"forget": 0.9, "delays": 1},
                                     {"forget": 0.8, "affine": True}])
def test_online_forgetting_without_ridge_does_not_wind_up(options: dict) -> None:
    """Exciting data, then a stream that excites one direction only: with forgetting the Gram
    matrix decays in the others. Without the guard P grew to 1e14-1e38 here; with it P stays
    bounded (the fit switches to the summary's pseudoinverse) and online still equals batch."""
    rng = np.random.default_rng(7)
    data = np.r_[rng.normal(size=(40, 2)),
                 np.tile([0.3, -0.2], (400, 1)) + 1e-9 * np.arange(400)[:, None]]
    online = StreamingEDMD(online=True, **options)
    batch = StreamingEDMD(**options)
    largest_p, recursive_steps = 0.0, 0
    for z in data:
        online.observe(z)
        batch.observe(z)
        if online.n_pairs:
            np.testing.assert_allclose(online.predict(), batch.predict(), rtol=1e-7, atol=1e-8)
            if online.recursive:
                recursive_steps += 1
                largest_p = max(largest_p, float(np.trace(online._P)))
    assert recursive_steps > 50  # the recursion ran, and was stopped in time
    assert largest_p < 1e10
    assert not online.recursive


@pytest.mark.parametrize("online", [False, True])
@pytest.mark.parametrize("config", ["plain", "ridge", "window", "delays", "affine"])
def test_noise_gain_is_the_fits_variance_over_one_readings(online: bool, config: str) -> None:
    """``noise_gain`` is ``psi^T (X X^T + ridge I)^-1 psi`` from all the pairs at once, for the
    newest sample and for a given ``z``; and it is what it stands for: with white noise of
    variance s added to the pairs' outputs, the fit's prediction varies by ``s h``."""
    options = CONFIGS[config]
    data = linear_stream(40, seed=3)
    est = StreamingEDMD(online=online, **options)
    for z in data:
        est.observe(z)
    delays, tail = options.get("delays", 0), [1.0] if options.get("affine") else []
    lifted = np.hstack([data[delays - k: len(data) - k] for k in range(delays + 1)]
                       + [np.ones((len(data) - delays, 1))] * len(tail))
    window = options.get("window")
    x = lifted[:-1][-window:] if window else lifted[:-1]
    gram = x.T @ x + options.get("ridge", 0.0) * np.eye(x.shape[1])
    given = np.r_[[0.3, -0.2], lifted[-1][:2 * delays], tail]  # z pushed into the delay line
    for psi, z in ((lifted[-1], None), (given, [0.3, -0.2])):
        expected = psi @ np.linalg.solve(gram, psi)
        assert est.noise_gain(z) == pytest.approx(expected, rel=1e-9)
    if config == "plain":  # the variance it names, by Monte Carlo over the outputs' noise
        rng = np.random.default_rng(5)
        y = lifted[1:]
        predictions = [((y + 0.1 * rng.normal(size=y.shape)).T
                        @ np.linalg.pinv(x.T)) @ lifted[-1] for _ in range(4000)]
        variance = np.var(np.array(predictions), axis=0).mean()
        assert variance / 0.01 == pytest.approx(est.noise_gain(), rel=0.1)


def test_noise_gain_is_large_where_only_the_noise_spans_the_pairs() -> None:
    """Pairs spread along one direction, the other spanned only by noise of 1e-3: a sample
    like theirs has leverage below 1, one a noise step aside far above it."""
    rng = np.random.default_rng(0)
    est = StreamingEDMD()
    for t in range(6):
        est.observe([1.0 + 0.2 * t, 1e-3 * rng.normal()])
    assert est.noise_gain([1.5, 0.0]) < 1.0
    assert est.noise_gain([1.5, 0.01]) > 10.0


def test_noise_gain_before_a_fit_says_what_is_needed() -> None:
    est = StreamingEDMD()
    est.observe([1.0, 2.0])
    with pytest.raises(RuntimeError, match="needs 2 observed samples"):
        est.noise_gain()
