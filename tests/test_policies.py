"""Follower policies: exactness where the truth is known, baselines, auto, finite sensing range,
noise determinism. Run through the in-memory layout (same code as over Zenoh)."""
from __future__ import annotations

import importlib
import math

import numpy as np
import pytest

from agents.policies import (
    Auto,
    NotReady,
    Persist,
    Proposal,
    Stay,
    Unwrapper,
    make_policy,
    relative,
)
from agents.policies.base import Before
from protocol.config import AgentSettings, RunConfig
from protocol.messages import Sensing
from swarm.local import run_local

PLANE = dict(surface="plane", leader_start=(0.0, 0.0, 1.0, 0.3), followers=2, ticks=12)
CASES = [("a", "lagged", False), ("b", "lagged", False), ("c", "oracle", False),
         ("c", "lagged", False), ("c", "estimated", False), ("d", "lagged", True),
         ("e", "lagged", True), ("f", "lagged", True), ("g", "lagged", True)]


@pytest.mark.parametrize("dictionary, velocity, gps", CASES)
def test_every_dictionary_exact_on_tilted_plane(dictionary, velocity, gps):
    """Straight leader on a tilted plane: the truth is known, every estimate is exact."""
    cfg = RunConfig(dictionary=dictionary, velocity=velocity, gps=gps, **PLANE)
    summary, rows = run_local(cfg)
    est = [r for r in rows if r["agent"] > 0 and r.get("required_range") is not None]
    assert len(est) == 2 * (cfg.ticks - cfg.init_ticks)
    worst = max(r["required_range"] for r in est)
    assert worst < 1e-9, f"dictionary {dictionary}/{velocity}: worst required range {worst}"
    # ... while waiting is far off: the check can fail.
    assert summary["followers"]["1"]["mean_stay_range"] > 0.5


@pytest.mark.parametrize("estimator", ["stay", "persist", "auto"])
def test_baselines_and_auto_on_plane(estimator):
    summary, _ = run_local(RunConfig(estimator=estimator, **PLANE))
    s = summary["followers"]["1"]
    if estimator == "stay":
        assert s["mean_required_range"] == pytest.approx(s["mean_stay_range"], rel=1e-12)
    else:  # relative position is constant on a plane: persist (and auto) are exact
        assert s["mean_required_range"] < 1e-9


def test_world_baselines_match_policies():
    """The world's counterfactual stay/persist ranges equal what those policies achieve."""
    cfg = dict(surface="wavy", ticks=20)
    base, _ = run_local(RunConfig(estimator="edmd", **cfg))
    for name, key in (("stay", "mean_stay_range"), ("persist", "mean_persist_range")):
        run, _ = run_local(RunConfig(estimator=name, **cfg))
        assert run["followers"]["1"]["mean_required_range"] == pytest.approx(
            base["followers"]["1"][key], rel=1e-9)


def test_paper_edmd_beats_stay_on_paper_surfaces():
    for surface in ("elliptic", "hyperbolic", "wavy"):
        s = run_local(RunConfig(surface=surface))[0]["followers"]["1"]
        assert s["mean_required_range"] < 0.1 * s["mean_stay_range"]


def test_finite_sensing_range_counts_lost_ticks():
    inf, _ = run_local(RunConfig(surface="wavy", estimator="persist"))
    lost, rows = run_local(RunConfig(surface="wavy", estimator="persist", sensing_range=0.05))
    assert inf["followers"]["1"]["lost_ticks"] == 0
    n_lost = lost["followers"]["1"]["lost_ticks"]
    assert 0 < n_lost <= 36
    assert sum(r["lost"] for r in rows if r["agent"] == 1) == n_lost
    lost_rows = [r for r in rows if r["agent"] == 1 and r["lost"]]
    for r in lost_rows:  # a lost follower stays where its estimate took it
        assert (r["pos_x"], r["pos_y"]) == (r["est_x"], r["est_y"])
        assert r["required_range"] > 0.05
    seen = [r for r in rows if r["agent"] == 1 and not r["lost"] and r["tick"] >= 4]
    assert all(r["required_range"] <= 0.05 for r in seen)


def test_noise_is_keyed_not_timed():
    """Same seed -> same numbers; another seed -> different numbers; noise changes results."""
    noisy = dict(surface="elliptic", dictionary="c", velocity="estimated", noise_range=0.01,
                 noise_bearing=0.005, noise_velocity=0.02, noise_move=0.01, ticks=16)
    a = run_local(RunConfig(seed=3, **noisy))[1]
    b = run_local(RunConfig(seed=3, **noisy))[1]
    c = run_local(RunConfig(seed=4, **noisy))[1]
    clean = run_local(RunConfig(seed=3, **{**noisy, "noise_range": 0.0, "noise_bearing": 0.0,
                                           "noise_velocity": 0.0, "noise_move": 0.0}))[1]
    assert a == b
    assert a != c and a != clean


def _sensing(r=1.0, theta=0.0):
    return Sensing(tick=0, r=r, theta=theta)


def test_unwrapper_keeps_bearing_continuous():
    unwrap = Unwrapper()
    seq = [3.0, -3.0, 3.1, -3.1]
    out = [unwrap(t) for t in seq]
    assert all(abs(b - a) < math.pi for a, b in zip(out, out[1:]))
    assert out[1] == pytest.approx(-3.0 + 2 * math.pi)


class _Fixed(Stay):
    """A candidate that always proposes the same offset."""

    def __init__(self, name, offset):
        super().__init__()
        self.name, self.offset = name, np.asarray(offset, float)

    def propose(self, pre):
        return Proposal(self.offset.copy())


def _three(**options):
    options = {"horizon": 2, "trust": 3.0, "burn_in": 0, **options}
    return Auto([_Fixed("a", [0.0, 0.0]), _Fixed("b", [1.0, 0.0]), _Fixed("c", [0.5, 0.0])],
                **options)


def test_auto_follows_the_lowest_recent_error_and_the_blend_is_a_candidate():
    auto = _three()
    first = auto.propose(_sensing())
    assert first.followed == "a" and np.allclose(first.offset, [0.0, 0.0])  # nothing scored
    auto.record(_sensing(), np.array([0.4, 0.0]))  # errors 0.4, 0.6, 0.1; the blend unscored
    chosen = auto.propose(_sensing())
    assert np.array_equal(chosen.offset, [0.5, 0.0]) and chosen.followed == "c"
    # the blend: weights 1/MSE, normalised (Bates-Granger)
    inverse = np.array([1 / 0.4**2, 1 / 0.6**2, 1 / 0.1**2])
    expected = inverse @ np.array([0.0, 1.0, 0.5]) / inverse.sum()  # 0.4840...
    blend = auto._proposals(_sensing())[-1]
    assert blend.offset == pytest.approx([expected, 0.0], abs=1e-12) and blend.followed == "blend"
    assert np.allclose(blend.prediction, relative(_sensing()) - blend.offset)
    assert sum(auto.weights(auto._proposals(_sensing())[:-1]).values()) == pytest.approx(1.0)
    # the true offset is 0.48 this time: the blend (scored with the weights it had) wins
    auto.record(_sensing(), np.array([expected, 0.0]))
    assert auto.errors[-1][-1] == pytest.approx(0.0, abs=1e-12)
    assert auto.propose(_sensing()).followed == "blend"
    # blend=False: the candidates alone, the lowest error followed
    hard = _three(blend=False)
    hard.record(_sensing(), np.array([0.4, 0.0]))
    hard.record(_sensing(), np.array([0.48, 0.0]))
    assert hard._proposals(_sensing())[-1] is None and hard.propose(_sensing()).followed == "c"


def test_auto_exact_candidates_share_the_blend_weight():
    auto = _three()
    auto.errors[0].extend([0.5, 0.5])
    auto.errors[1].extend([0.0, 0.0])
    auto.errors[2].extend([0.0, 0.0])
    assert auto._proposals(_sensing())[-1].offset == pytest.approx([0.75, 0.0])
    assert auto.propose(_sensing()).followed == "b"  # exact, and first among the exact ones


def test_auto_leaves_out_wild_proposals_and_falls_back_to_anchor():
    auto = _three()
    auto.errors[0].extend([0.4, 0.05])  # anchor: largest recent change 0.4, radius 1.2
    auto.errors[1].extend([0.6, 0.95])
    auto.errors[2].extend([0.0, 0.0])  # candidate c looks perfect ...
    auto.candidates[2].offset = np.array([5.0, 0.0])  # ... but proposes a wild jump
    assert set(auto.weights(auto._proposals(_sensing())[:-1])) == {0, 1}  # not in the blend
    proposal = auto.propose(_sensing())
    assert proposal.followed == "a"  # c left out; a's error is below b's
    auto.candidates[1].offset = np.array([2.0, 0.0])  # b beyond the radius too
    proposal = auto.propose(_sensing())
    assert np.array_equal(proposal.offset, [0.0, 0.0]) and proposal.followed == "a"


def test_auto_trusts_its_default_beyond_the_radius():
    """The ``default`` (the filter weighing the pre reading against its model) departs from the
    anchor by the reading's error: the trust radius does not leave it out."""
    auto = _three(default="c")
    auto.errors[0].extend([0.4, 0.05])  # radius 1.2
    auto.errors[1].extend([0.6, 0.95])
    auto.errors[2].extend([0.0, 0.0])
    auto.candidates[2].offset = np.array([5.0, 0.0])
    assert auto._eligible(auto._proposals(_sensing())) == [0, 1, 2]
    assert auto.propose(_sensing()).followed == "c"
    auto.candidates[1].offset = np.array([4.0, 0.0])  # any other candidate still is left out
    assert auto._eligible(auto._proposals(_sensing())) == [0, 2]


class _Reading(Stay):
    """A candidate that proposes the pre reading it is given, moved by ``shift``."""

    def __init__(self, name, shift):
        super().__init__()
        self.name, self.shift = name, np.asarray(shift, float)

    def propose(self, pre):
        return Proposal(relative(pre) + self.shift)


def test_auto_made_scores_each_candidate_on_the_proposal_it_made():
    """With ``made``, a candidate is scored on what it proposed from the tick's own ``pre``
    reading (``before.pre``), not on a proposal from the reconstructed one."""
    pre = Sensing(tick=3, r=2.0, theta=0.0)
    settled = Sensing(tick=3, r=1.5, theta=0.0)  # the reconstruction: 1.5 + 0.3 = 1.8
    target = np.array([0.3, 0.0])
    before = Before(pre=pre, moved=None, offset=(0.0, 0.0))
    for made, expected in ((True, 2.0 + 0.1 - 0.3), (False, 1.8 + 0.1 - 0.3)):
        auto = Auto([_Fixed("a", [0.0, 0.0]), _Reading("r", [0.1, 0.0])], burn_in=0,
                    made=made)
        auto.learn(settled, target, before)
        assert auto.errors[1][-1] == pytest.approx(expected, abs=1e-12)
    auto = Auto([_Fixed("a", [0.0, 0.0]), _Reading("r", [0.1, 0.0])], burn_in=0, made=True)
    auto.record(settled, target)  # no ``before``: the reconstruction
    assert auto.errors[1][-1] == pytest.approx(1.6, abs=1e-12)


def test_auto_compares_candidates_on_the_same_ticks():
    """A late starter is compared on the ticks it was scored on, not against older errors."""
    auto = Auto([_Fixed("anchor", [0.0, 0.0]), _Fixed("late", [0.3, 0.0])], horizon=4,
                trust=None, burn_in=0)
    auto.errors[0].extend([0.0, 0.0, 0.5])  # the anchor was perfect early, poor lately
    auto.errors[1].extend([0.2])  # the late starter was scored only on the last tick
    assert auto.propose(_sensing()).followed == "late"


def test_auto_weights_mix_the_candidates_by_discounted_loss():
    """The default: weights exp(-sharpness (L - L_min) / L_min), L the discounted e**2."""
    auto = _three(combine="weights", blend=False, trust=None, memory=0.5, sharpness=1.0)
    auto.record(_sensing(), np.array([0.4, 0.0]))  # errors 0.4, 0.6, 0.1
    auto.record(_sensing(), np.array([0.2, 0.0]))  # errors 0.2, 0.8, 0.3
    assert auto.loss[:3] == pytest.approx([0.10, 0.50, 0.05])  # 0.5 L + 0.5 e**2
    raw = np.exp([-(0.10 - 0.05) / 0.05, -(0.50 - 0.05) / 0.05, 0.0])  # e^-1, e^-9, 1
    expected = raw @ np.array([0.0, 1.0, 0.5]) / raw.sum()
    proposal = auto.propose(_sensing())
    assert proposal.offset == pytest.approx([expected, 0.0], abs=1e-12)
    assert proposal.followed == "c"  # the largest weight
    assert np.allclose(proposal.prediction, relative(_sensing()) - proposal.offset)
    # a sharper mixture leans further to the lowest loss
    sharp = _three(combine="weights", blend=False, trust=None, memory=0.5, sharpness=20.0)
    for target in ([0.4, 0.0], [0.2, 0.0]):
        sharp.record(_sensing(), np.array(target))
    assert abs(sharp.propose(_sensing()).offset[0] - 0.5) < abs(expected - 0.5)


def test_auto_weights_follow_an_exact_candidate_alone():
    auto = _three(combine="weights", blend=False, trust=None)
    auto.record(_sensing(), np.array([1.0, 0.0]))  # b is exact
    proposal = auto.propose(_sensing())
    assert np.array_equal(proposal.offset, [1.0, 0.0]) and proposal.followed == "b"
    for bad, match in (({"combine": "vote"}, "combine"), ({"sharpness": 0.0}, "sharpness"),
                       ({"memory": 1.0}, "memory"), ({"memory": -0.1}, "memory")):
        with pytest.raises(ValueError, match=match):
            Auto([_Fixed("a", [0, 0])], **bad)


class _Leveraged(_Fixed):
    """A fixed candidate that reports a settable leverage, like a least-squares model."""

    lev = None

    def leverage(self, pre):
        return self.lev


@pytest.mark.parametrize("combine", ["best", "weights"])
def test_auto_scales_a_young_least_squares_score_by_its_leverage(combine):
    """While its window is not full, a candidate's scores are scaled by min(1, now / then) of
    its leverage: a fit whose coming regressor sticks out of its data 100x less than when it
    was scored is judged by 1/100 of that error."""
    def fresh():
        ls = _Leveraged("ls", [1.0, 0.0])
        auto = Auto([_Fixed("anchor", [0.0, 0.0]), ls], horizon=4, trust=None, burn_in=0,
                    blend=False, combine=combine)
        return auto, ls

    auto, ls = fresh()
    ls.lev = 1e-2
    auto.record(_sensing(), np.array([0.5, 0.0]))  # errors 0.5 (anchor), 0.5 (ls, lev 1e-2)
    auto.record(_sensing(), np.array([0.7, 0.0]))  # 0.7, 0.3
    assert list(auto.levels[1]) == [1e-2, 1e-2] and auto.levels[0][0] is None
    assert auto.propose(_sensing()).followed == "ls"  # 0.3 beats 0.7 anyway
    auto.record(_sensing(), np.array([0.0, 0.0]))  # 0.0 (anchor), 1.0 (ls): the anchor leads
    assert auto.propose(_sensing()).followed == "anchor"
    ls.lev = 1e-4  # the coming regressor lies 100x closer to the data's span
    scaled = auto._adjusted(1, auto._leverages(_sensing()))
    assert scaled == pytest.approx([0.005, 0.003, 0.01])
    assert auto.propose(_sensing()).followed == "ls"
    ls.lev = 1.0  # never scaled up
    assert auto._adjusted(1, auto._leverages(_sensing())) == pytest.approx([0.5, 0.3, 1.0])
    auto.record(_sensing(), np.array([0.0, 0.0]))  # the window is full: plain scores again
    ls.lev = 1e-4
    assert auto._adjusted(1, auto._leverages(_sensing())) == list(auto.errors[1])
    assert auto.propose(_sensing()).followed == "anchor"


def test_auto_leaves_the_noise_floor_of_a_young_score_unscaled():
    """Only the part of a squared score above the readings' noise floor shrinks with the
    leverage; a score below the floor is judged at the floor."""
    ls = _Leveraged("ls", [1.0, 0.0])
    auto = Auto([_Fixed("anchor", [0.0, 0.0]), ls], horizon=4, trust=None, burn_in=0,
                noise_floor=0.01)
    ls.lev = 1e-2
    auto.record(_sensing(), np.array([0.5, 0.0]))  # ls: 0.5
    auto.record(_sensing(), np.array([0.95, 0.0]))  # ls: 0.05, below the floor's 0.1
    ls.lev = 1e-3
    expected = [math.sqrt(0.01 + (0.25 - 0.01) * 0.01), math.sqrt(0.01)]
    assert auto._adjusted(1, auto._leverages(_sensing())) == pytest.approx(expected)
    with pytest.raises(ValueError, match="noise_floor"):
        Auto([_Fixed("a", [0, 0])], noise_floor=-1.0)
    settings = AgentSettings.from_config(RunConfig(estimator="auto-mix", noise_range=0.02,
                                                   noise_bearing=0.01))
    mix = make_policy(settings).policy  # twice the variance per coordinate of a reading
    assert mix.noise_floor == pytest.approx(0.02**2 + (settings.spacing * 0.01) ** 2)


def test_arx_leverage_is_the_part_of_the_regressor_outside_the_data():
    from agents.policies import ARX
    rng = np.random.default_rng(5)
    arx = ARX(order=1, window=None)  # regressor [x (2), u (2), 1]: 5 coefficients per row
    assert arx.leverage(_sensing()) is None and Persist().leverage(_sensing()) is None
    seen = []
    for k in range(9):
        r, theta = 3.0 + rng.normal(0, 0.3), rng.normal(0, 0.5)
        arx.record(Sensing(tick=k, r=r, theta=theta), rng.normal(0, 0.2, size=2))
        seen.append(arx.leverage(Sensing(tick=k + 1, r=3.1, theta=0.2)))
    assert seen[0] is None  # no pair yet
    assert all(0.0 < v < 1.0 for v in seen[1:4])  # 1-3 pairs span less than 5 dimensions
    assert all(v < 1e-9 for v in seen[5:])  # 5 pairs in general position span them all


def test_arx_with_lags_before_its_samples_is_not_fitted_yet():
    """An order above the samples it has (``--arx-order 20`` with estimation from tick 2, or
    after a lost tick restarted its chain) indexed its lags before the chain's start: an
    IndexError ended the run (or a wrapped-round regressor). It is not fitted yet instead,
    and the run goes on with persist until it is."""
    from agents.policies import ARX
    arx = ARX(order=5, window=None)
    for k in range(4):
        arx.record(Sensing(tick=k, r=3.0, theta=0.1 * k), np.array([0.1, 0.0]))
        with pytest.raises(NotReady):
            arx.propose(Sensing(tick=k + 1, r=3.0, theta=0.1 * k))
        assert arx.leverage(Sensing(tick=k + 1, r=3.0, theta=0.1 * k)) is None
    summary, _ = run_local(RunConfig(surface="elliptic", followers=2, ticks=30, seed=44,
                                     init_ticks=2, estimator="arx", arx_order=20, arx_window=0,
                                     noise_range=0.01, noise_move=0.01))
    assert summary["complete"]
    summary, _ = run_local(RunConfig(surface="wavy", ticks=30, seed=17, init_ticks=2,
                                     estimator="auto-mix", arx_order=5, arx_window=1,
                                     noise_range=0.01, noise_bearing=0.005))
    assert summary["complete"]


@pytest.mark.parametrize("order, affine, rank_deficient", [(1, True, False), (2, True, False),
                                                           (2, False, False), (1, True, True)])
def test_arx_with_every_pair_fits_from_a_summary_beyond_its_pairs_as_from_the_pairs(
        monkeypatch, order, affine, rank_deficient):
    """Every pair kept (window None, ``auto``'s ``arx-o1`` and ``arx-o2``): refitting all of
    them every tick made a long run's ticks dearer and dearer. Beyond SUMMARY_PAIRS the fit
    comes from their triangular factor: the same coefficients, rank cut and leverage as the
    pseudoinverse of every pair (computed here with the threshold out of reach), and the
    pairs themselves are no longer kept. Rank-deficient: a leader that never moves relative
    to the follower (x constant, u zero), whose regressors span one dimension."""
    from agents.policies import ARX
    classical = importlib.import_module("agents.policies.classical")

    def stream(arx: ARX) -> list[tuple]:
        rng = np.random.default_rng(11)
        out = []
        for k in range(60):
            r, theta = ((3.0, 0.2) if rank_deficient else
                        (3.0 + 0.5 * math.sin(0.3 * k) + rng.normal(0, 0.02),
                         0.4 * math.cos(0.2 * k) + rng.normal(0, 0.01)))
            target = np.zeros(2) if rank_deficient else rng.normal(0, 0.1, size=2)
            arx.record(Sensing(tick=k, r=r, theta=theta), target)
            pre = Sensing(tick=k + 1, r=r + 0.01, theta=theta)
            try:
                out.append((arx.propose(pre).offset, arx.leverage(pre)))
            except NotReady:
                out.append(None)
        return out

    monkeypatch.setattr(classical, "SUMMARY_PAIRS", 10**9)
    reference = ARX(order=order, window=None, affine=affine)
    expected = stream(reference)
    monkeypatch.setattr(classical, "SUMMARY_PAIRS", 7)
    summarised = ARX(order=order, window=None, affine=affine)
    got = stream(summarised)
    assert len(summarised._pairs) == 0 and len(reference._pairs) == 60 - order
    for want, have in zip(expected, got):
        assert (want is None) == (have is None)
        if want is not None:
            np.testing.assert_allclose(have[0], want[0], rtol=1e-9, atol=1e-12)
            assert have[1] == pytest.approx(want[1], rel=1e-6, abs=1e-9)
    assert expected[-1] is not None


def test_auto_burn_in_drops_each_candidates_first_score():
    auto = Auto([_Fixed("a", [0.0, 0.0]), _Fixed("b", [1.0, 0.0])], burn_in=1)
    auto.record(_sensing(), np.array([0.4, 0.0]))
    assert [len(e) for e in auto.errors] == [0, 0, 0]
    auto.record(_sensing(), np.array([0.4, 0.0]))
    assert [list(e) for e in auto.errors[:2]] == [[pytest.approx(0.4)], [pytest.approx(0.6)]]
    with pytest.raises(ValueError, match="candidate names must be unique"):
        Auto([_Fixed("a", [0, 0]), _Fixed("a", [1, 0])])


def test_not_ready_and_factory():
    with pytest.raises(NotReady):
        Persist().propose(_sensing())
    settings = AgentSettings.from_config(RunConfig(estimator="auto"))
    assert make_policy(settings).name == "auto" and make_policy(settings).policy.combine == "best"
    mix = make_policy(AgentSettings.from_config(RunConfig(estimator="auto-mix"))).policy
    assert mix.name == "auto-mix" and mix.combine == "weights"
    settings = AgentSettings.from_config(RunConfig(dictionary="c", velocity="estimated"))
    assert make_policy(settings).name == "edmd-c-estimated"
    with pytest.raises(ValueError, match="candidates must not be empty"):
        Auto([])


class _Counted(_Reading):
    """A :class:`_Reading` that counts the proposals it is asked for."""

    def __init__(self, name, shift):
        super().__init__(name, shift)
        self.asked = 0

    def propose(self, pre):
        self.asked += 1
        return super().propose(pre)


def test_auto_asks_each_candidate_once_a_tick_when_it_scores_what_was_made():
    """With ``made``, learn scores the proposals propose already had for the same reading
    (the candidates are pure until they learn): each candidate is asked once a tick, and the
    scores are those of an auto that was never asked to propose; what propose had is not
    used once the candidates learnt, nor for another reading."""
    pre = Sensing(tick=3, r=2.0, theta=0.0)
    settled, target = Sensing(tick=3, r=1.5, theta=0.0), np.array([0.3, 0.0])
    before = Before(pre=pre, moved=None, offset=(0.0, 0.0))
    asked, unasked = (Auto([_Counted("a", [0.0, 0.0]), _Counted("r", [0.1, 0.0])], burn_in=0,
                           made=True) for _ in range(2))
    for tick in range(3):
        asked.propose(pre)
        asked.learn(settled, target, before)
        unasked.learn(settled, target, before)
        assert [c.asked for c in asked.candidates] == [tick + 1] * 2
        assert asked.errors == unasked.errors
    asked.learn(settled, target, before)  # nothing proposed since it learnt: asked anew
    unasked.learn(settled, target, before)
    assert [c.asked for c in asked.candidates] == [4, 4] and asked.errors == unasked.errors
    asked.propose(Sensing(tick=3, r=2.5, theta=0.0))  # another reading: asked anew
    asked.learn(settled, target, before)
    assert [c.asked for c in asked.candidates] == [6, 6]
    assert asked.errors[1][-1] == pytest.approx(2.0 + 0.1 - 0.3, abs=1e-12)


class _Diverging(Stay):
    """A candidate whose arithmetic fails: each propose pops the next of ``script`` (an
    exception to raise, or an offset to propose); ``record`` raises ``learn_error`` if given."""

    def __init__(self, name, script, learn_error=None):
        super().__init__()
        self.name, self.script, self.learn_error = name, list(script), learn_error

    def propose(self, pre):
        step = self.script.pop(0)
        if isinstance(step, BaseException):
            raise step
        return Proposal(np.asarray(step, dtype=float))

    def record(self, settled, target):
        if self.learn_error is not None:
            raise self.learn_error
        return super().record(settled, target)


def test_a_diverged_estimate_is_replaced_by_persist_counted_and_logged_once(caplog):
    from agents.policies.base import FallbackToPersist
    inf, nan = math.inf, math.nan
    policy = FallbackToPersist(_Diverging("wild", [
        OverflowError("(34, 'Numerical result out of range')"), [nan, 0.0], [1.0, inf],
        np.linalg.LinAlgError("Singular matrix"), ZeroDivisionError("float division"),
        [0.25, -0.5]], learn_error=FloatingPointError("overflow")))
    settled = Sensing(tick=0, r=2.0, theta=0.5, rod=(0.1, 0.0))
    with caplog.at_level("WARNING", logger="agents.policies.base"):
        measured = policy.learn(settled, np.zeros(2))  # its learning fails: persist's reading
        proposals = [policy.propose(Sensing(tick=t, r=2.5, theta=0.5)) for t in range(1, 7)]
    assert measured == (2.0, 0.5)
    persist = relative(Sensing(tick=1, r=2.5, theta=0.5)) - relative(settled)
    for proposal in proposals[:5]:  # an overflow, NaN, infinity, a singular system, 1/0
        assert proposal.fallback and proposal.followed == "persist"
        assert np.allclose(proposal.offset, persist)
    assert not proposals[5].fallback and proposals[5].followed == "wild"
    assert np.array_equal(proposals[5].offset, [0.25, -0.5])
    assert policy.diverged == 6  # the learning and five proposals
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and "estimator wild diverged at tick 0" in warned[0], warned


def test_auto_sits_a_diverged_candidate_out_and_survives_overflowing_scores():
    # each record (made=False) and each propose asks the candidates once, in this order
    auto = Auto([_Fixed("a", [0.0, 0.0]),
                 _Diverging("wild", [[1e200, 0.0], [1e200, 0.0], OverflowError("x"),
                                     [math.nan, 0.0], [1e200, 0.0], [0.5, 0.0]])],
                horizon=3, burn_in=0)
    auto.record(_sensing(), np.array([0.1, 0.0]))  # "wild" scored 1e200 away
    assert auto.errors[1][-1] == pytest.approx(1e200)
    # its squared score overflows: it loses and nothing raises (the scores' fsum and the
    # paired test's squares used to raise OverflowError)
    assert math.isinf(auto._mse([0, 1])[1])
    assert auto.propose(_sensing()).followed in ("a", "blend")
    auto.record(_sensing(), np.array([0.1, 0.0]))  # "wild" raised: no proposal, not scored
    auto.record(_sensing(), np.array([0.1, 0.0]))  # it proposed NaN: the same
    assert len(auto.errors[1]) == 1
    auto.record(_sensing(), np.array([0.1, 0.0]))
    assert len(auto.errors[1]) == 2 and not auto._beats(1, 0, None)
    assert auto._beats(0, 1, None)  # a finite candidate beats one whose scores overflowed
    assert auto.propose(_sensing()).followed in ("a", "blend")
    everyone = Auto([_Diverging("x", [[1e200, 0.0]] * 3), _Diverging("y", [[-1e200, 0.0]] * 3)],
                    horizon=2, burn_in=0, blend=False, combine="weights")
    everyone.record(_sensing(), np.array([0.0, 0.0]))
    with pytest.raises(NotReady):  # every score overflowed: persist stands in (flagged)
        everyone.weights(everyone._proposals(_sensing()))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # ekf's overflowing covariance
def test_a_driving_column_that_cannot_keep_up_ends_broken_not_with_a_traceback():
    """--max-accel 0.5 covers a fraction of the leader's travel per tick: the followers fall
    behind without bound; ekf's covariance overflowed and auto's paired test raised
    OverflowError, before estimates that diverge fell back to persist."""
    config = RunConfig(surface="elliptic", followers=3, ticks=60, seed=3, motion="drive",
                       max_accel=0.5, noise_range=0.02, noise_bearing=0.01, estimator="auto")
    summary, _ = run_local(config)
    assert summary["complete"] and summary["formation_broken"]
    assert all(f["broken_ticks"] > 0 for f in summary["followers"].values())


class NaNProposer(Stay):
    """A plug-in whose estimate is NaN from its third tick on."""

    name = "nan-proposer"

    def __init__(self, settings=None):
        super().__init__()

    def propose(self, pre):
        return Proposal(np.array([math.nan, 0.0]) if pre.tick >= 2 else np.zeros(2))


def test_a_plugin_that_proposes_nan_is_replaced_by_persist_not_followed():
    from agents.policies.base import FallbackToPersist
    from agents.policies.plugin import load_estimator
    policy = FallbackToPersist(load_estimator("tests.test_policies:NaNProposer",
                                              AgentSettings.from_config(RunConfig())))
    policy.learn(Sensing(tick=0, r=1.0, theta=0.0, rod=(0.0, 0.0)), np.zeros(2))
    fine, wild = (policy.propose(Sensing(tick=t, r=1.5, theta=0.0)) for t in (1, 2))
    assert not fine.fallback and fine.followed == "nan-proposer"
    assert wild.fallback and wild.followed == "persist" and np.allclose(wild.offset, [0.5, 0.0])


def test_a_driving_edmd_under_noise_follows_only_what_its_pairs_determine():
    """The standalone EDMD a driving follower runs with declared noise (``determined``):
    while its fit would carry more noise into the prediction than one reading holds
    (leverage > 1: two pairs of readings that barely differ, then a reading a noise step
    aside), persist stands in, flagged; once the pairs span that step, the fit is followed.
    Teleporting or noise-free, the paper's Algorithm 1 is followed as published."""
    def settings(**options):
        return AgentSettings.from_config(RunConfig(**options))
    noisy = dict(noise_range=0.02, noise_bearing=0.01)
    assert make_policy(settings(motion="drive", **noisy)).policy.determined
    assert not make_policy(settings(motion="drive")).policy.determined
    assert not make_policy(settings(**noisy)).policy.determined
    policy = make_policy(settings(motion="drive", **noisy))
    for t, (r, theta) in enumerate([(3.50, 1.50), (3.51, 1.501), (3.50, 1.502), (3.52, 1.40)]):
        policy.learn(Sensing(tick=t, r=r, theta=theta, rod=(0.0, 0.0)), np.zeros(2))
    assert policy.policy.edmd.noise_gain() > 1.0
    proposal = policy.propose(Sensing(tick=4, r=3.5, theta=1.4))
    assert proposal.fallback and proposal.followed == "persist"
    for t in range(5, 12):  # the bearing swings on: the pairs span it
        theta = 1.4 + 0.1 * (-1) ** t
        policy.learn(Sensing(tick=t, r=3.5 + 0.05 * (t % 3), theta=theta, rod=(0.0, 0.0)),
                     np.zeros(2))
    assert policy.policy.edmd.noise_gain() < 1.0
    proposal = policy.propose(Sensing(tick=12, r=3.5, theta=1.5))
    assert not proposal.fallback and proposal.followed == "edmd-b"
