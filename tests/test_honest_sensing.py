"""Honest sensing (design §5): under noise nothing an agent receives is exact, the snap is a move
by the sensed offset, and with every σ = 0 the numbers are the noise-free ones bit for bit."""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from agents.follower import follower_tick
from agents.policies import make_policy
from protocol.config import AgentSettings, RunConfig
from protocol.messages import Move, Snap
from swarm.local import LocalLink, run_local
from world.main import resolve_with_surface
from world.sim import WorldSim

EVERY_SIGMA = dict(noise_range=0.02, noise_bearing=0.01, noise_velocity=0.01, noise_move=0.01,
                   noise_gps=0.05, gps=True)
DIGESTS = Path(__file__).parent / "data" / "noise_free_digests.json"
ROW_FIELDS = ("tick", "agent", "pos_x", "pos_y", "est_x", "est_y", "ideal_x", "ideal_y",
              "required_range", "stay_range", "persist_range", "persist_range_noise_free",
              "formation_error", "lost")


class TruthLink(LocalLink):
    """A follower's link that also notes, beside every sensing the world sends, what an exact
    sensor would have read at that moment (from the world's ground truth)."""

    def __init__(self, sim: WorldSim, agent: int, seen: list) -> None:
        super().__init__(sim, agent)
        self.seen = seen

    def _truth(self, tick: int) -> dict:
        sim, state = self.sim, self.sim.agents[self.agent]
        leader = sim.agents[self.agent - 1].settled[tick]
        rel = leader - state.pos
        truth = {"r": math.hypot(*rel), "theta": math.atan2(rel[1], rel[0]),
                 "rod": tuple(sim._leader_rod(self.agent, tick)[0] - state.pos)}
        settled = state.settled
        if tick in settled and tick - 1 in settled:
            truth["velocity"] = tuple((settled[tick] - settled[tick - 1]) / sim.config.comm_period)
        elif tick - 1 in settled and tick - 2 in settled:
            truth["velocity"] = tuple((settled[tick - 1] - settled[tick - 2])
                                      / sim.config.comm_period)
        if tick in settled:
            truth["oracle_velocity"] = tuple((sim.ideal[self.agent, tick + 1] - state.pos)
                                             / sim.config.comm_period)
        truth["gps"] = (*state.pos, sim.surface.height(state.pos))
        truth["leader_gps"] = (*leader, sim.surface.height(leader))
        return truth

    def sense(self, tick, look=False):
        reply = super().sense(tick, look)
        truth = self._truth(tick)
        if not look:  # the rod end is read only by looking (design §4)
            del truth["rod"]
        self.seen.append((reply, truth))
        return reply

    def act(self, request):
        reply = super().act(request)
        self.seen.append((reply.sensing, self._truth(request.tick)))
        return reply


def _run_recording(config: RunConfig) -> list:
    """Run ``config`` unpipelined in memory; every (sensing, truth) pair a follower got."""
    config, surface = resolve_with_surface(config)
    sim, settings = WorldSim(config, surface), AgentSettings.from_config(config)
    seen: list = []
    links = [TruthLink(sim, k, seen) for k in range(1, config.followers + 1)]
    policies = [make_policy(settings) for _ in links]
    for tick in range(config.ticks):
        sim.start_tick(tick)
        sim.drive(0, tick, sim.time_of(tick))
        outcomes = [follower_tick(link, policy, settings, tick)
                    for link, policy in zip(links, policies)]
        sim.finish_tick(tick)
        assert len(outcomes) == config.followers
    return seen


@pytest.mark.parametrize("options", [dict(dictionary="d"), dict(estimator="auto"),
                                     dict(dictionary="c", velocity="oracle")])
def test_with_every_sigma_positive_no_sensed_quantity_is_exact(options):
    config = RunConfig(surface="wavy", followers=2, ticks=12, seed=5, **EVERY_SIGMA, **options)
    seen = _run_recording(config)
    assert len(seen) > 12 * 2 * 2
    compared = 0
    for sensing, truth in seen:
        for name, exact in truth.items():
            value = getattr(sensing, name)
            if value is None:
                continue
            compared += 1
            assert np.all(np.asarray(value, dtype=float) != np.asarray(exact, dtype=float)), (
                f"{name} at tick {sensing.tick} reached the agent exactly: {value}")
        if "rod" in truth:  # looked for
            assert sensing.rod is not None, "the rod end is in range here (R_s = inf)"
        else:
            assert sensing.rod is None, "the pre-move sensing carries no rod end unless asked"
    assert compared >= 5 * len(seen)  # r, theta, rod, gps, leader_gps always; velocity mostly


def test_oracle_velocity_is_sent_only_to_dictionary_c_oracle():
    def oracles(**options):
        seen = _run_recording(RunConfig(surface="elliptic", ticks=8, **options))
        return [s.oracle_velocity for s, _ in seen if s.oracle_velocity is not None]

    assert oracles(dictionary="c", velocity="oracle")
    assert not oracles(dictionary="c", velocity="lagged")
    assert not oracles(estimator="persist")


def test_gps_readings_carry_the_declared_noise():
    seen = _run_recording(RunConfig(surface="elliptic", ticks=40, followers=2, dictionary="d",
                                    gps=True, noise_gps=0.5, seed=2))
    errors = np.array([np.subtract(s.gps, t["gps"]) for s, t in seen]
                      + [np.subtract(s.leader_gps, t["leader_gps"]) for s, t in seen])
    assert errors.shape[0] > 400
    # N(0, 0.5) per coordinate: the sample std within 15 %, the mean within 4 standard errors
    assert np.all(np.abs(errors.std(axis=0) / 0.5 - 1) < 0.15)
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * 0.5 / math.sqrt(errors.shape[0]))


def test_a_snap_lands_on_the_rod_end_only_without_noise():
    def formation_errors(**noise):
        _, rows = run_local(RunConfig(surface="elliptic", ticks=12, seed=3, estimator="persist",
                                      **noise))
        return [r["formation_error"] for r in rows if r["agent"] == 1]

    assert max(formation_errors()) < 1e-9
    # range and bearing noise alone: the snap moves by the sensed offset and lands off
    noisy = formation_errors(noise_range=0.02, noise_bearing=0.01)
    assert min(noisy) > 1e-6 and np.mean(noisy) > 0.003
    # actuation noise alone: the snap is a move like any other
    assert min(formation_errors(noise_move=0.01)) > 1e-6


def test_errors_travel_down_the_column():
    """A snapped follower's own rod starts where it really stands: follower 2's formation
    error is larger than follower 1's under noise (its rod end is read from a misplaced rod)."""
    means = {1: [], 2: []}
    for seed in range(4):
        _, rows = run_local(RunConfig(surface="wavy", followers=2, ticks=20, seed=seed,
                                      estimator="persist", noise_range=0.02, noise_bearing=0.01))
        for k in means:
            means[k] += [r["formation_error"] for r in rows if r["agent"] == k]
    assert np.mean(means[2]) > 1.2 * np.mean(means[1])


def test_the_readings_of_one_interval_are_one_odometry_reading():
    """The odometry's noise belongs to the interval it measures: the settled reading of tick
    ``j`` and the pre and moved readings of tick ``j + 1`` read one displacement, and are the
    same (noisy) reading, so averaging them gains nothing."""
    config, surface = resolve_with_surface(RunConfig(surface="wavy", ticks=10, seed=5,
                                                     **EVERY_SIGMA))
    sim = WorldSim(config, surface)
    readings, positions = {}, {}
    for tick in range(config.ticks):
        sim.start_tick(tick)
        sim.drive(0, tick, sim.time_of(tick))
        readings[tick, "pre"] = sim.sense(1, tick, look=tick < config.init_ticks).velocity
        if tick >= config.init_ticks:
            readings[tick, "moved"] = sim.act(1, Move(tick=tick, offset=(0.01, 0.0))).velocity
        readings[tick, "settled"] = sim.act(1, Snap(tick=tick)).velocity
        positions[tick] = sim.agents[1].pos.copy()
        sim.finish_tick(tick)
    for j in range(1, config.ticks - 1):
        reading = readings[j, "settled"]
        assert reading == readings[j + 1, "pre"]
        if j + 1 >= config.init_ticks:
            assert reading == readings[j + 1, "moved"]
        exact = (positions[j] - positions[j - 1]) / config.comm_period
        assert np.all(np.asarray(reading) != exact)
        assert reading != readings[j + 1, "settled"]


def test_a_drive_tick_missed_before_any_step_still_reads_a_noisy_velocity():
    """A driving follower marked missed before its first control step drove nothing: its
    odometry has no step to sum, and the interval's reading is a noisy draw, not the exact
    (zero) displacement."""
    from agents.drive import Limits

    noise = {k: v for k, v in EVERY_SIGMA.items() if k != "noise_move"}  # teleport only
    config, surface = resolve_with_surface(RunConfig(surface="wavy", ticks=6, seed=5,
                                                     motion="drive", **noise))
    sim, settings = WorldSim(config, surface), AgentSettings.from_config(config)
    link, policy, limits = LocalLink(sim, 1), make_policy(settings), Limits.from_settings(settings)
    for tick in range(4):
        sim.start_tick(tick)
        sim.drive(0, tick, sim.time_of(tick))
        if tick == 3:  # too late: missed before any step
            sim.sense(1, tick)
            sim.mark_missed(1)
        else:
            follower_tick(link, policy, settings, tick, limits=limits)
        sim.finish_tick(tick)
    sim.start_tick(4)
    sim.drive(0, 4, sim.time_of(4))
    settled = sim.agents[1].settled
    exact = (settled[3] - settled[2]) / config.comm_period
    assert np.all(np.asarray(sim.sense(1, 4).velocity) != exact)


def test_every_sigma_zero_gives_the_noise_free_numbers_bit_for_bit():
    """The numbers of the noise-free runs recorded before sensing became honest (digests of
    every row's positions, estimates and ranges): the σ = 0 model is the old one exactly."""
    digests = json.loads(DIGESTS.read_text())
    assert len(digests) >= 20
    for key, digest in digests.items():
        options = json.loads(key)
        config = RunConfig(run_id="r", **options)
        _, rows = run_local(config)
        table = [[row.get(name) for name in ROW_FIELDS] for row in rows]
        got = hashlib.sha256(json.dumps(table).encode()).hexdigest()
        assert got == digest, f"noise-free numbers moved for {options}"


def test_the_sensing_floor_is_below_persist_and_zero_without_noise():
    """The floor column: an estimator that knows the formation's true motion and suffers only
    the readings' noise (and its move's); zero to rounding without noise."""
    clean, _ = run_local(RunConfig(surface="wavy", estimator="persist"))
    assert clean["followers"]["1"]["mean_floor_range"] < 1e-12
    floors, persists = [], []
    for seed in range(3):
        summary, _ = run_local(RunConfig(surface="wavy", estimator="persist", seed=seed,
                                         noise_range=0.02, noise_bearing=0.01))
        floors.append(summary["followers"]["1"]["mean_floor_range"])
        persists.append(summary["followers"]["1"]["mean_persist_range"])
    assert 0 < np.mean(floors) < 0.5 * np.mean(persists)
