"""bench/replay_auto.py: recorded candidates replayed through the real Auto."""
from __future__ import annotations

import dataclasses

import pytest

from bench.replay_auto import (candidate_errors, oracle_startup_above, record, replay,
                               where_it_loses)
from protocol.config import RunConfig
from swarm.local import run_local

NOISY = dict(surface="wavy", ticks=16, seed=3, noise_range=0.02, noise_bearing=0.01)


@pytest.fixture(scope="module")
def trace():
    return record(RunConfig(**NOISY))


def test_replaying_auto_gives_the_recorded_run(trace):
    """To rounding: the world measures the range in absolute coordinates, replay in the
    follower's frame."""
    assert replay(trace) == pytest.approx(trace.recorded_mean, rel=1e-11)


def test_a_replayed_variant_matches_its_real_run(trace):
    """The follower snaps onto the rod end each tick, so what the candidates see does not
    depend on what auto followed: replaying auto-mix over auto's recording gives auto-mix's
    own run (to rounding)."""
    mix = run_local(RunConfig(estimator="auto-mix", **NOISY))[0]["followers"]["1"]
    assert replay(trace, combine="weights") == pytest.approx(mix["mean_required_range"],
                                                             rel=1e-9)
    assert replay(trace, combine="weights") != trace.recorded_mean  # a different rule


def test_a_variant_that_asks_in_another_order_is_refused(trace):
    cut = dataclasses.replace(trace, answers={**trace.answers,  # a recording cut short
                                               "persist": trace.answers["persist"][:-3]})
    with pytest.raises(RuntimeError, match="replay of 'persist' diverged"):
        replay(cut)


def test_record_refuses_actuation_noise():
    with pytest.raises(ValueError, match="noise_move"):
        record(RunConfig(noise_move=0.01, ticks=6))


@pytest.mark.parametrize("name", ["kalman", "arx", "persist"])
def test_a_candidates_recorded_errors_are_its_own_run(trace, name):
    """A candidate's proposals inside auto are what it proposes on its own (persist standing
    in while it is not ready), tick by tick."""
    errors = candidate_errors(trace, name)
    own = run_local(RunConfig(estimator=name, **NOISY))[0]["followers"]["1"]
    assert sorted(errors) == list(range(trace.config.init_ticks, NOISY["ticks"]))
    assert sum(errors.values()) / len(errors) == pytest.approx(own["mean_required_range"],
                                                               rel=1e-9)
    with pytest.raises(ValueError, match="no candidate 'nope'"):
        candidate_errors(trace, "nope")


def test_where_it_loses_splits_the_excess_and_the_oracle_start_up():
    auto = {4: 3.0, 5: 1.0, 6: 1.0, 7: 2.0}
    best = {4: 1.0, 5: 1.0, 6: 1.0, 7: 1.0}
    assert where_it_loses(auto, best, startup=1) == pytest.approx((0.75, 0.5))
    assert oracle_startup_above(auto, best, 1)  # tick 7's excess remains
    assert not oracle_startup_above(auto, {**best, 7: 2.5}, 1)  # 1+1+1+2 <= 1+1+1+2.5
