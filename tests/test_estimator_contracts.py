"""Contracts of the estimators (design §6, issue 10): pure ``propose`` and replayable state,
fallback to persist, honest baselines from the same noisy readings, the classical baselines,
transparency of ``auto``. Run through the in-memory layout (same code as over Zenoh)."""
from __future__ import annotations

import csv

import msgpack
import numpy as np
import pytest

from agents.estimators import NotFitted
from agents.policies import ARX, Auto, FallbackToPersist, NotReady, Persist, Policy, make_policy
from protocol.config import AgentSettings, RunConfig
from protocol.messages import Observation, decode
from swarm.local import run_local

NOISY = dict(noise_range=0.02, noise_bearing=0.01)
CONFIGS = {
    "edmd-a": dict(dictionary="a", noise_velocity=0.01),
    "edmd-b": dict(dictionary="b"),
    "edmd-b-online-forget": dict(dictionary="b", online=True, forget=0.9, delays=1),
    "edmd-c-estimated": dict(dictionary="c", velocity="estimated"),
    "edmd-f": dict(dictionary="f", gps=True),
    "cv": dict(estimator="cv"),
    "kalman": dict(estimator="kalman"),
    "arx": dict(estimator="arx"),
    "gp": dict(estimator="gp"),
    "gp-motion": dict(estimator="gp-motion", noise_move=0.02),
    "gp-ratio": dict(estimator="gp-ratio"),
    "ekf": dict(estimator="ekf"),
    "ekf-actuation": dict(estimator="ekf", noise_move=0.02, noise_velocity=0.01),
    "auto": dict(estimator="auto"),
    "auto-mix": dict(estimator="auto-mix"),
}


class ReplayChecker(Policy):
    """Wraps a policy; at every tick checks that ``propose`` is a pure read (same answer
    twice) and that a fresh policy fed the logged ``learn``/``skip`` calls proposes the same
    (the follower's state is that log)."""

    def __init__(self, settings: AgentSettings) -> None:
        self.settings = settings
        self.policy = make_policy(settings)
        self.name = self.policy.name
        self.log: list[tuple] = []
        self.checked = 0

    def propose(self, pre):
        first = _attempt(self.policy, pre)
        assert _same(first, _attempt(self.policy, pre)), "propose changed the policy's state"
        fresh = make_policy(self.settings)
        for call in self.log:
            getattr(fresh, call[0])(*call[1:])
        assert _same(first, _attempt(fresh, pre)), "replaying the log gives another policy"
        self.checked += 1
        if isinstance(first, Exception):
            raise first
        return first

    def learn(self, settled, target, before=None):
        self.log.append(("learn", settled, None if target is None else np.array(target),
                         before))
        return self.policy.learn(settled, target, before)

    def skip(self):
        self.log.append(("skip",))
        self.policy.skip()


def _attempt(policy, pre):
    try:
        return policy.propose(pre)
    except NotFitted as exc:
        return exc


def _same(a, b) -> bool:
    if isinstance(a, Exception) or isinstance(b, Exception):
        return type(a) is type(b)
    return (np.array_equal(a.offset, b.offset) and a.prediction == b.prediction
            and a.followed == b.followed and a.fallback == b.fallback)


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_propose_is_pure_and_state_is_the_call_log(name):
    """Noise and a finite sensing range (lost ticks, bridged by predictions) included."""
    checkers = []

    def factory(settings):
        checkers.append(ReplayChecker(settings))
        return checkers[-1]

    cfg = RunConfig(surface="wavy", ticks=16, sensing_range=0.02, seed=2, noise_range=0.005,
                    noise_bearing=0.002, **CONFIGS[name])
    _, rows = run_local(cfg, policy_factory=factory)
    _, plain_rows = run_local(cfg)
    assert rows == plain_rows  # the checks themselves change nothing
    assert checkers[0].checked == cfg.ticks
    assert any(call[0] == "learn" and call[2] is None for call in checkers[0].log), "no lost tick"
    assert all(call[3] is not None for call in checkers[0].log if call[0] == "learn")


def test_not_ready_policy_falls_back_to_persist_and_is_counted(tmp_path):
    """--delays 10: the first ticks are persist's, flagged, counted, not called estimated."""
    base = dict(surface="elliptic", ticks=24)
    summary, rows = run_local(RunConfig(delays=10, **base), out_dir=tmp_path / "d10")
    persist, persist_rows = run_local(RunConfig(estimator="persist", **base))
    s = summary["followers"]["1"]
    # delays=10 needs 12 samples: ticks 4..11 fall back.
    assert s["fallback_ticks"] == 8 and s["estimated_ticks"] == 20 - 8
    mine = {r["tick"]: r for r in rows if r["agent"] == 1}
    theirs = {r["tick"]: r for r in persist_rows if r["agent"] == 1}
    for j in range(4, 12):
        assert mine[j]["required_range"] == pytest.approx(theirs[j]["required_range"], abs=1e-12)
    with open(tmp_path / "d10" / "observations.csv", newline="") as fh:
        obs = [r for r in csv.DictReader(fh) if r["agent"] == "1"]
    assert [r["fallback"] for r in obs[4:13]] == ["1"] * 8 + ["0"]
    assert [r["followed"] for r in obs[11:13]] == ["persist", "edmd-b"]

    never, _ = run_local(RunConfig(delays=1000, **base))
    n = never["followers"]["1"]
    assert n["fallback_ticks"] == 20 and n["estimated_ticks"] == 0
    assert n["mean_required_range"] == pytest.approx(
        persist["followers"]["1"]["mean_required_range"], rel=1e-12)


def test_persist_baseline_comes_from_the_same_noisy_readings():
    """In a noisy run the world's persist column is what the persist estimator achieves."""
    cfg = RunConfig(surface="wavy", estimator="persist", ticks=20, seed=1, **NOISY)
    summary, rows = run_local(cfg)
    estimated = [r for r in rows if r["agent"] == 1 and r.get("required_range") is not None]
    assert len(estimated) == 16
    for r in estimated:
        assert r["persist_range"] == pytest.approx(r["required_range"], rel=1e-9, abs=1e-12)
    s = summary["followers"]["1"]
    # ... while the noise-free counterfactual, named as such, is another number.
    assert abs(s["mean_persist_range_noise_free"] - s["mean_persist_range"]) > 1e-3
    clean, _ = run_local(cfg.replace(noise_range=0.0, noise_bearing=0.0))
    c = clean["followers"]["1"]
    assert c["mean_persist_range_noise_free"] == pytest.approx(c["mean_persist_range"], rel=1e-12)


@pytest.mark.parametrize("estimator", ["cv", "kalman", "arx", "gp"])
def test_classical_baselines_exact_on_tilted_plane(estimator):
    """On a plane the relative position is constant: every tracker predicts it exactly."""
    cfg = RunConfig(surface="plane", leader_start=(0.0, 0.0, 1.0, 0.3), ticks=12,
                    estimator=estimator)
    summary, _ = run_local(cfg)
    s = summary["followers"]["1"]
    assert s["mean_required_range"] < 1e-9 < s["mean_stay_range"]
    assert s["fallback_ticks"] == 0 and s["followed"] == {estimator: 1.0}


def test_classical_baselines_beat_persist_where_the_formation_turns():
    for estimator in ("cv", "kalman", "arx", "gp"):
        s = run_local(RunConfig(surface="elliptic", estimator=estimator))[0]["followers"]["1"]
        assert s["mean_required_range"] < 0.5 * s["mean_persist_range"], estimator


class CountedARX(ARX):
    """ARX logging, per state of its data (a new one after every ``record``/``skip``), each
    proposal and the least-squares fits (``np.linalg.pinv`` calls) it took, and the fits each
    ``leverage`` (which ``auto`` asks first) took. With ``refit`` every proposal comes from a
    fresh ARX given the same data: a fit each time, as before ARX remembered its fit."""

    def __init__(self, fits: list[int], refit: bool, **options) -> None:
        super().__init__(**options)
        self.fits, self.refit = fits, refit
        self.data_state = 0
        self.log: list[tuple] = []  # (data state, fits taken, proposal or None)
        self.leverage_fits: list[tuple] = []  # (data state, fits taken)

    def _source(self):
        if not self.refit:
            return self
        source = ARX(self.order, self.window, self.affine, self.name)
        # the same data (samples, and the pairs made from them as they came), no fit yet
        source.xs, source.us, source.last_seen = self.xs, self.us, self.last_seen
        source._pairs, source._summary = self._pairs, self._summary
        return source

    def leverage(self, pre):
        before = self.fits[0]
        value = ARX.leverage(self._source(), pre)
        self.leverage_fits.append((self.data_state, self.fits[0] - before))
        return value

    def propose(self, pre):
        before = self.fits[0]
        try:
            proposal = ARX.propose(self._source(), pre)
        except NotFitted:
            proposal = None
        self.log.append((self.data_state, self.fits[0] - before, None if proposal is None
                         else (proposal.offset.tobytes(), proposal.prediction)))
        if proposal is None:
            raise NotFitted(f"{self.name} is not fitted")
        return proposal

    def record(self, settled, target):
        self.data_state += 1
        return super().record(settled, target)

    def skip(self):
        self.data_state += 1
        super().skip()


def test_arx_fits_once_per_data_change_under_auto(monkeypatch):
    """``auto`` asks every candidate twice a tick (its proposal, then its score in ``record``)
    from the same data: ARX fits once per change of its data, and every proposal is
    bit-identical to one from a fresh fit. Noisy, with lost ticks (the chain restarts)."""
    fits = [0]
    pinv = np.linalg.pinv

    def counting_pinv(*args, **kwargs):
        fits[0] += 1
        return pinv(*args, **kwargs)

    monkeypatch.setattr(np.linalg, "pinv", counting_pinv)
    cfg = RunConfig(surface="elliptic", estimator="auto", ticks=30, sensing_range=0.05, seed=0,
                    noise_range=0.005, noise_bearing=0.002)  # lost at ticks 23-29
    runs = {}
    for refit in (False, True):
        arx = [CountedARX(fits, refit, order=2, window=10, affine=False, name="arx-o2-w10-lin"),
               CountedARX(fits, refit, order=1, window=None, affine=True, name="arx-o1")]
        _, rows = run_local(cfg, policy_factory=lambda s, arx=arx: FallbackToPersist(
            Auto([Persist(), *arx])))
        runs[refit] = rows, arx
    (rows, cached), (rows_refit, refitted) = runs[False], runs[True]
    assert rows == rows_refit
    for mine, fresh in zip(cached, refitted):
        assert [e[::2] for e in mine.log] == [e[::2] for e in fresh.log]  # same proposals
        assert all(taken == (proposal is not None) for _, taken, proposal in fresh.log)
        per_state: dict[int, list[tuple]] = {}
        for state, taken, proposal in mine.log:
            per_state.setdefault(state, []).append((taken, proposal))
        leverage_fits: dict[int, int] = {}
        for state, taken in mine.leverage_fits:
            leverage_fits[state] = leverage_fits.get(state, 0) + taken
        for state, entries in per_state.items():
            assert sum(t for t, _ in entries) + leverage_fits.get(state, 0) == int(
                any(p is not None for _, p in entries))
        asked_twice = sum(1 for e in per_state.values() if sum(p is not None for _, p in e) == 2)
        assert asked_twice > 0  # auto's pattern happened, with one fit each time
        fitted = [p is not None for _, _, p in mine.log]
        assert True in fitted and False in fitted[fitted.index(True):]  # a restart, too


@pytest.mark.parametrize("estimator", ["gp-motion", "gp-ratio"])
def test_own_motion_exact_on_tilted_plane(estimator):
    """On a plane the follower's displacement repeats the leader's: both predict it exactly
    from the second estimated tick on (the first has one displacement to go by, and it is
    already the right one)."""
    cfg = RunConfig(surface="plane", leader_start=(0.0, 0.0, 1.0, 0.3), ticks=12,
                    estimator=estimator)
    s = run_local(cfg)[0]["followers"]["1"]
    assert s["mean_required_range"] < 1e-9 < s["mean_stay_range"]
    assert s["fallback_ticks"] == 0 and s["followed"] == {estimator: 1.0}


def test_gp_ratio_carries_the_leaders_displacement_by_the_learnt_rotation():
    """d = q u with q the complex ratio: a leader that turns is followed at once."""
    from agents.policies import RatioGP
    from protocol.messages import Sensing

    def at(tick, x, y):
        return Sensing(tick=tick, r=float(np.hypot(x, y)), theta=float(np.arctan2(y, x)),
                       rod=(0.0, 0.0))  # settled on the rod end

    policy = RatioGP()
    q = complex(np.cos(0.3), np.sin(0.3)) * 0.9  # the follower's step: the leader's, turned
    seen = np.array([3.0, 0.0])
    for tick in range(6):
        u = np.array([1.0, 0.0])
        d = np.array([(q * complex(*u)).real, (q * complex(*u)).imag])
        seen = seen + u - d if tick else seen
        policy.record(at(tick, *seen), d if tick else np.zeros(2))
    u = np.array([0.0, -2.0])  # now the leader steps south
    proposal = policy.propose(at(6, *(seen + u)))
    expected = q * complex(*u)
    assert proposal.offset == pytest.approx([expected.real, expected.imag], abs=1e-9)


class TargetRecorder(Policy):
    """persist that keeps every offset it proposes and every ``target`` it is given."""

    def __init__(self, settings: AgentSettings) -> None:
        self.policy, self.name = make_policy(settings), "persist"
        self.offsets, self.targets = [], []

    def propose(self, pre):
        proposal = self.policy.propose(pre)
        self.offsets.append(proposal.offset)
        return proposal

    def record(self, settled, target):
        self.targets.append(None if target is None else np.array(target))
        return self.policy.record(settled, target)


@pytest.mark.parametrize("noise", [{}, NOISY])
def test_target_corrects_for_actuation_noise(noise):
    """The target a policy learns from is where the ideal position was relative to where the
    follower stood: the commanded offset plus the rod end seen after the move would miss by the
    move's actuation noise; the readings around the move estimate that noise. Without sensor
    noise the estimate is exact; with it, the target is still much closer than offset + rod."""
    recorders = []

    def factory(settings):
        recorders.append(TargetRecorder(settings))
        return recorders[-1]

    ticks, init = 24, 4
    cfg = RunConfig(surface="wavy", estimator="persist", ticks=ticks, seed=5, noise_move=0.1,
                    **noise)
    _, rows = run_local(cfg, policy_factory=factory)
    f1 = {r["tick"]: r for r in rows if r["agent"] == 1}
    rec = recorders[0]
    corrected, uncorrected = [], []
    for j in range(init, ticks):
        truth = np.array([f1[j]["ideal_x"] - f1[j - 1]["pos_x"],
                          f1[j]["ideal_y"] - f1[j - 1]["pos_y"]])
        rod = np.array([f1[j]["ideal_x"] - f1[j]["est_x"], f1[j]["ideal_y"] - f1[j]["est_y"]])
        offset = rec.offsets[j - 1]  # propose is called from tick 1 (tick 0 has no history)
        uncorrected.append(float(np.hypot(*(offset + rod - truth))))
        corrected.append(float(np.hypot(*(rec.targets[j] - truth))))
    assert min(uncorrected) > 1e-3  # the actuation noise itself
    if not noise:
        assert max(corrected) < 1e-9
    else:
        # expected about 0.5 here: w = 0.86 keeps 14% of the move noise and adds 86% of the
        # difference of two readings (range 0.02, bearing 0.01 at 3.57: 0.02 and 0.036)
        assert np.mean(corrected) < 0.75 * np.mean(uncorrected)


def test_own_motion_restarts_after_a_lost_tick():
    from agents.policies import MotionGP
    from protocol.messages import Sensing

    policy = MotionGP()
    for tick in range(3):
        policy.record(Sensing(tick=tick, r=3.0, theta=0.0, rod=(0.0, 0.0)), np.array([0.5, 0.0]))
    assert policy.propose(Sensing(tick=3, r=3.5, theta=0.0)).offset == pytest.approx([0.5, 0])
    policy.record(Sensing(tick=3, r=3.0, theta=0.0), None)  # lost
    with pytest.raises(NotReady):
        policy.propose(Sensing(tick=4, r=3.5, theta=0.0))
    with pytest.raises(ValueError, match="move_variance"):
        MotionGP(move_variance=-1.0)


@pytest.mark.parametrize("estimator", ["auto", "auto-mix"])
def test_auto_records_what_it_followed(tmp_path, estimator):
    """auto: the candidate it used; auto-mix: the one with the largest weight in the mixture."""
    summary, _ = run_local(RunConfig(surface="wavy", estimator=estimator, ticks=20),
                           out_dir=tmp_path)
    shares = summary["followers"]["1"]["followed"]
    names = {c.name for c in make_policy(AgentSettings.from_config(
        RunConfig(estimator=estimator))).policy.candidates} | {"blend"}
    assert set(shares) <= names and sum(shares.values()) == pytest.approx(1.0)
    with open(tmp_path / "observations.csv", newline="") as fh:
        followed = [r["followed"] for r in csv.DictReader(fh) if int(r["tick"]) >= 4]
    assert len(followed) == 16 and set(followed) == set(shares)
    for name, share in shares.items():
        assert followed.count(name) / 16 == pytest.approx(share)


def test_observation_without_the_new_fields_still_decodes():
    old = msgpack.packb({"v": 1, "type": "obs", "tick": 3, "estimator": "edmd-b",
                         "measurement": [1.0, 2.0], "prediction": None, "lost": False})
    msg = decode(old, Observation)
    assert msg.followed == "" and msg.fallback is False
    bad = msgpack.packb({"v": 1, "type": "obs", "tick": 3, "estimator": "x", "measurement": None,
                         "prediction": None, "lost": False, "fallback": "yes"})
    with pytest.raises(ValueError, match="fallback"):
        decode(bad, Observation)


def test_not_ready_is_the_not_fitted_exception():
    assert NotReady is NotFitted and issubclass(NotFitted, RuntimeError)


def test_auto_leaves_the_blend_only_for_a_significantly_better_candidate():
    """``auto`` follows the lowest score only when it beat the blend by more than
    ``significance`` standard errors of the paired differences (the winner's curse)."""
    from collections import deque

    from agents.policies import Stay

    auto = Auto([Persist(), Stay()], horizon=4)
    blend = len(auto.candidates)
    auto.errors[blend] = deque([0.2, 0.21, 0.19, 0.2], maxlen=4)
    auto.errors[0] = deque([0.1, 0.3, 0.1, 0.3], maxlen=4)  # as good on average, noisier
    assert not auto._beats(0, blend, None)
    auto.errors[0] = deque([0.1, 0.11, 0.09, 0.1], maxlen=4)  # better on every tick
    assert auto._beats(0, blend, None)
    auto.errors[0] = deque([0.1], maxlen=4)  # one score says nothing
    assert not auto._beats(0, blend, None)
    assert Auto([Persist(), Stay()], significance=None)._beats(0, blend, None)
    with pytest.raises(ValueError, match="significance"):
        Auto([Persist()], significance=-1.0)


@pytest.mark.parametrize("surface", ["elliptic", "wavy"])
def test_auto_is_no_worse_than_persist_under_honest_noise(surface):
    """Means over seeds at the middle noise level, from the same noisy readings."""
    means = {}
    for estimator in ("persist", "auto"):
        means[estimator] = np.mean([
            run_local(RunConfig(surface=surface, estimator=estimator, seed=seed, **NOISY))[0]
            ["followers"]["1"]["mean_required_range"] for seed in range(3)])
    assert means["auto"] <= means["persist"]


@pytest.mark.parametrize("order, window", [(1, None), (2, None), (2, 4)])
def test_arx_keeps_each_pair_as_a_refit_from_its_samples_would_make_it(order, window):
    """ARX makes each pair's regressor once, as its sample arrives, and keeps of the samples
    only the lags a regressor needs; what it fits on is what rebuilding every pair from all
    the samples gives (the newest ``window``), across a chain restarted by a lost tick and
    windows that drop old pairs."""
    from agents.policies.base import relative
    from protocol.messages import Sensing

    rng = np.random.default_rng(7)
    arx = ARX(order=order, window=window, affine=True)
    xs, us = [], []  # the chain's samples, all of them: x_i and u_i of the same tick
    for tick in range(30):
        settled = Sensing(tick=tick, r=3.0 + rng.normal(0, 0.1), theta=rng.normal(0, 0.3))
        target = None if tick == 12 else rng.normal(0, 0.5, 2)
        arx.record(settled, target)
        seen = relative(settled)
        if target is None:  # lost: the chain restarts at the next sample
            xs, us = [], []
            continue
        if xs:
            us.append(seen + target - xs[-1])
        xs.append(seen)
        assert len(arx.xs) <= order + 1 and len(arx.us) <= order  # lags only
        rows = [i for i in range(order - 1, len(us))][-window if window else 0:]
        if not rows:
            with pytest.raises(NotFitted):
                arx._fit()
            continue
        phi = np.array([np.concatenate([part for k in range(order) for part in (
            xs[i - k], us[i - k])] + [np.ones(1)]) for i in rows])
        arx._fit()  # fits (its pairs are what it fits on, up to SUMMARY_PAIRS of them)
        fitted = np.array([row for row, _ in arx._pairs])
        assert fitted.tolist() == phi.tolist()
