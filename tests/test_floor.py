"""The sensing floor is a bound (design §6, world/floor.py): the minimum-mean-square estimator
that knows the formation's true motion and has every reading the follower has had."""
from __future__ import annotations

import math

import numpy as np
import pytest

from agents.policies import NotReady, Policy, Proposal, relative
from protocol.config import RunConfig
from protocol.messages import Sensing
from protocol.sensing import reading_covariance
from swarm.local import LocalLink, run_local
from world import floor

NOISY = dict(noise_range=0.02, noise_bearing=0.01)


def test_a_static_state_read_again_and_again_is_their_mean():
    """Flat prior, isotropic readings of one unknown: the filter's error is the readings'
    mean error (to rounding), its variance the reading's over their number."""
    rng = np.random.default_rng(4)
    errors = rng.normal(0.0, 0.1, size=(30, 2))
    f = floor.FloorFilter()
    f.tick([floor.read(e, 0.01 * np.eye(2)) for e in errors])
    assert np.allclose(f.error[:2], errors.mean(axis=0), atol=1e-9)
    assert np.allclose(f.covariance[:2, :2], 0.01 / 30 * np.eye(2), rtol=1e-6)


def test_a_move_adds_its_noise_and_odometry_reads_it_back():
    """A move's noise enters the error whole; the interval's odometry, reading the summed
    actuation noise exactly, takes it out again."""
    f = floor.FloorFilter()
    f.tick([floor.read(np.zeros(2), 1e-4 * np.eye(2))])
    eta = np.array([0.03, -0.02])
    assert f.tick([floor.move(eta, 1e-4, odometered=True), floor.DECISION]) == pytest.approx(
        math.hypot(*eta), rel=1e-3)
    f.tick([floor.interval(np.zeros(2), 1e-12)])
    assert np.abs(f.error[:2]).max() < 1e-6


def test_the_compiled_update_is_the_kalman_update_in_joseph_form():
    """``floor._joseph`` (the written-out update) against the textbook matrices: gain
    ``K = P Hᵀ S⁻¹``, error ``e + K (y − H e)``, covariance ``(I − K H) P (I − K H)ᵀ + K R Kᵀ``,
    for readings of s and of w, on random covariances (seed printed)."""
    seed = int(np.random.SeedSequence().entropy % 2**32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    for _ in range(200):
        a, b = rng.normal(size=(4, 4)), rng.normal(size=(2, 2))
        p, r = a @ a.T, b @ b.T * 0.1
        e, y = rng.normal(size=4), rng.normal(size=2)
        start = int(rng.integers(0, 2)) * 2
        h = np.zeros((2, 4))
        h[0, start], h[1, start + 1] = 1.0, 1.0
        gain = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
        keep = np.eye(4) - gain @ h
        f = floor.FloorFilter()
        f.covariance, f.error = p.copy(), e.copy()
        f._update(slice(start, start + 2), y, r)
        assert np.allclose(f.error, e + gain @ (y - h @ e), rtol=1e-9, atol=1e-12)
        assert np.allclose(f.covariance, keep @ p @ keep.T + gain @ r @ gain.T,
                           rtol=1e-8, atol=1e-12)


def test_without_noise_the_floor_is_exactly_zero():
    summary, rows = run_local(RunConfig(surface="wavy", estimator="persist", followers=2))
    assert all(r["floor_range"] == 0.0 for r in rows if r["agent"] > 0)
    summary, rows = run_local(RunConfig(surface="wavy", motion="drive", ticks=8))
    assert all(r["floor_range"] == 0.0 for r in rows if r["agent"] > 0)


class Oracle(Policy):
    """A test-only plug-in given the formation's true motion (the leader's and the ideal
    position's true positions, read from the in-memory world by the test): with exact moves
    (no actuation noise) the ideal position relative to where it stands is
    ``c_j + U − Σ targets``, ``U`` one unknown constant (minus its starting position), which
    every pre-move and settled reading it gets measures; it estimates ``U`` by their
    precision-weighted mean (each reading's declared covariance at what it measured, its range
    widened by ``σ_r`` as the floor's: near the rod end a reading is precise across the line of
    sight)."""

    name = "oracle"

    def __init__(self, world: dict, agent: int) -> None:
        self.world, self.agent = world, agent
        self.moved = np.zeros(2)  # Σ targets: its own displacement since tick 0 (exact)
        self.weighted, self.weight = np.zeros(2), np.zeros((2, 2))
        self.sigmas = (NOISY["noise_range"], NOISY["noise_bearing"])

    def _truth(self, tick: int) -> tuple[np.ndarray, np.ndarray]:
        sim = self.world["sim"]
        return sim.agents[self.agent - 1].settled[tick], sim._leader_rod(self.agent, tick)[0]

    def _precision(self, seen: np.ndarray) -> np.ndarray:
        r = math.hypot(float(np.hypot(*seen)), self.sigmas[0])
        return np.linalg.inv(reading_covariance(r, math.atan2(seen[1], seen[0]), *self.sigmas))

    def _sample(self, seen: np.ndarray, at: np.ndarray) -> None:
        """A reading ``seen`` of the absolute point ``at`` from the current start position."""
        w = self._precision(seen)
        self.weighted += w @ (seen - at + self.moved)
        self.weight += w

    def propose(self, pre: Sensing) -> Proposal:
        leader, end = self._truth(pre.tick)
        if not self.weight.any():
            raise NotReady("no reading yet")
        seen = relative(pre)
        w = self._precision(seen)
        u = np.linalg.solve(self.weight + w, self.weighted + w @ (seen - leader + self.moved))
        return Proposal(end + u - self.moved)

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        leader, end = self._truth(settled.tick)
        self.moved = self.moved + np.asarray(target)  # exact moves: the displacement is known
        self._sample(relative(settled), leader)
        self._sample(np.asarray(settled.rod), end)
        return ()


def _oracle_and_floor(seed: int, surface: str) -> tuple[float, float]:
    world: dict = {}
    made = iter(range(1, 10))

    def link(sim, k):
        world["sim"] = sim
        return LocalLink(sim, k)

    summary, _ = run_local(RunConfig(surface=surface, seed=seed, **NOISY),
                           policy_factory=lambda settings: Oracle(world, next(made)),
                           link_factory=link)
    one = summary["followers"]["1"]
    return one["mean_required_range"], one["mean_floor_range"]


def test_an_oracle_given_the_true_motion_does_not_beat_the_floor():
    """Means over seeds: the oracle uses the whole history too (its pre-move and settled
    readings), so it comes close, but the floor, which has every reading, stays below."""
    pairs = np.array([_oracle_and_floor(seed, surface) for seed in range(3)
                      for surface in ("elliptic", "wavy")])
    oracle, bound = pairs.mean(axis=0)
    print(f"oracle {oracle:.6f}, floor {bound:.6f}")
    assert 0 < bound <= oracle < 3 * bound


@pytest.mark.parametrize("surface", ["hyperbolic", "wavy"])
def test_the_floor_is_below_every_estimator(surface):
    """Means over seeds, follower 1, at the middle noise level: the floor is below each
    estimator (bench/bench_estimator_table.py checks every table)."""
    for estimator in ("persist", "kalman", "auto"):
        required, bound = [], []
        for seed in range(2):
            summary, _ = run_local(RunConfig(surface=surface, seed=seed, estimator=estimator,
                                             **NOISY))
            required.append(summary["followers"]["1"]["mean_required_range"])
            bound.append(summary["followers"]["1"]["mean_floor_range"])
        assert np.mean(bound) < np.mean(required), estimator


def test_the_floor_with_actuation_noise_is_at_least_the_moves_own():
    """With noisy moves the floor decides, then moves as the follower did: its error is at
    least about the move's actuation noise (mean norm of a 2-D N(0, σ²): σ √(π/2))."""
    sigma = 0.01
    summary, _ = run_local(RunConfig(surface="wavy", seed=1, noise_move=sigma,
                                     noise_velocity=0.01, **NOISY))
    one = summary["followers"]["1"]
    assert 0.9 * sigma * math.sqrt(math.pi / 2) < one["mean_floor_range"]
    assert one["mean_floor_range"] < one["mean_required_range"]


@pytest.mark.parametrize("sigma_r, sigma_theta", [(0.1, 0.0), (0.0, 0.05)])
def test_a_sensor_exact_on_one_axis_keeps_the_floor_finite(sigma_r, sigma_theta):
    """Readings exact along one direction (range or bearing σ zero, the other not) at two
    bearings pin ``s`` along both, to first order: the floor's covariance becomes singular up
    to rounding, and the filter must go on, finite, instead of dividing by a determinant
    rounding made zero or negative (the world crashed at the first such tick of every run
    with ``--noise-range 0.1 --noise-bearing 0``). Its error is then far below one reading's:
    zero with an exact bearing, the bearing's second-order shortening of the range with an
    exact range."""
    rng = np.random.default_rng(2)
    f, r = floor.FloorFilter(), 3.57
    for tick in range(40):
        events = []
        for theta in (0.3 + 0.01 * tick, 2.0 - 0.01 * tick):  # the leader's and the rod end's
            offset = r * np.array([math.cos(theta), math.sin(theta)])
            n_r, n_theta = rng.normal(0.0, sigma_r or 1.0) * (sigma_r > 0), (
                rng.normal(0.0, sigma_theta or 1.0) * (sigma_theta > 0))
            read = (r + n_r) * np.array([math.cos(theta + n_theta), math.sin(theta + n_theta)])
            events.append(floor.range_bearing(read - offset, offset, sigma_r, sigma_theta))
        events.append(floor.DECISION)
        assert math.isfinite(f.tick(events))
        assert np.isfinite(f.covariance).all()
    # what the floor's first-order model does not see: r σ_θ² (an exact range; 0.009 m here,
    # one reading errs r σ_θ = 0.18 m across), nothing (an exact bearing)
    assert f.tick([]) < (1e-6 * sigma_r if sigma_theta == 0 else 5.0 * r * sigma_theta**2)


@pytest.mark.parametrize("motion", ["teleport", "drive"])
def test_a_run_with_one_exact_sensor_axis_completes(motion):
    """Runs that crashed the world's floor before (every surface and estimator tried) complete."""
    extra = {"motion": "drive"} if motion == "drive" else {}
    for sigma_r, sigma_theta in ((0.1, 0.0), (0.0, 0.05)):
        summary, rows = run_local(RunConfig(surface="elliptic", followers=2, ticks=20, seed=1,
                                            noise_range=sigma_r, noise_bearing=sigma_theta,
                                            **extra))
        assert summary["complete"]
        assert all(math.isfinite(r["floor_range"]) for r in rows if r["agent"] > 0)
