"""world/random_waves.py: surfaces drawn from a seed, for held-out checks nobody chose."""
from __future__ import annotations

import numpy as np
import pytest

from protocol.config import RunConfig
from swarm.local import run_local
from world import random_waves
from world.geometry import integrate_geodesic, metric
from world.random_waves import RandomWaves
from world.surfaces import make_surface


def _params(surface: RandomWaves) -> list[np.ndarray]:
    return [np.atleast_1d(np.asarray(v, dtype=float)) for v in (
        surface.tilt, surface.omega, surface.amplitude, surface.phase, surface.bump_height,
        surface.bump_centre, surface.bump_width, surface.default_leader_start)]


def test_a_seed_names_one_surface_and_seeds_differ():
    again = [np.array_equal(a, b) for a, b in zip(_params(RandomWaves(7)),
                                                  _params(RandomWaves(7)))]
    assert all(again)
    assert not np.array_equal(RandomWaves(7).omega, RandomWaves(8).omega)
    assert {len(RandomWaves(s).amplitude) for s in range(40)} == {2, 3, 4}
    assert {RandomWaves(s).bump_height == 0.0 for s in range(40)} == {True, False}


@pytest.mark.parametrize("seed", [0, 1, 5, 11, 123456])
def test_derivatives_match_finite_differences(seed):
    surface, rng, h = RandomWaves(seed), np.random.default_rng(seed), 1e-5
    for p in rng.uniform(-40.0, 40.0, (6, 2)):
        gradient = [(surface.height(p + h * e) - surface.height(p - h * e)) / (2 * h)
                    for e in np.eye(2)]
        hessian = [(surface.gradient(p + h * e) - surface.gradient(p - h * e)) / (2 * h)
                   for e in np.eye(2)]
        np.testing.assert_allclose(surface.gradient(p), gradient, atol=1e-8)
        np.testing.assert_allclose(surface.hessian(p), np.array(hessian).T, atol=1e-8)
        np.testing.assert_allclose(surface.hessian(p), surface.hessian(p).T, atol=1e-15)


def test_the_world_resolves_a_name_and_a_geodesic_keeps_its_speed():
    surface = make_surface(random_waves.name(3))
    assert isinstance(surface, RandomWaves) and surface.seed == 3
    start = np.array(surface.default_leader_start)
    p, v = integrate_geodesic(surface, start[:2], start[2:], 30.0)
    speed = [float(u @ metric(surface, q) @ u) for q, u in ((start[:2], start[2:]), (p, v))]
    assert speed[1] == pytest.approx(speed[0], rel=1e-9)  # a geodesic's g-speed is constant
    assert np.hypot(*(p - start[:2])) > 10.0  # and it went somewhere


@pytest.mark.parametrize("attr", ["w", "w-1", "w01", "x3", "w1.5", "W3", "w1234567890"])
def test_bad_names_are_refused_clearly(attr):
    with pytest.raises(ValueError, match="has no attribute"):
        make_surface(f"world.random_waves:{attr}")


@pytest.mark.parametrize("seed", [-1, 1.0, True, "3"])
def test_bad_seeds_are_refused(seed):
    with pytest.raises(ValueError, match="non-negative integer"):
        random_waves.name(seed)


def test_a_run_on_a_random_surface_completes():
    summary, rows = run_local(RunConfig(surface=random_waves.name(9), ticks=10,
                                        estimator="auto-mix"))
    follower = summary["followers"]["1"]
    assert summary["complete"] and len(rows) == 10 * 2  # a row per agent and tick
    assert 0.0 <= follower["mean_required_range"] < follower["mean_stay_range"]

