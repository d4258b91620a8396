"""bench/random_surfaces.py: surfaces drawn from a seed, for held-out checks nobody chose."""
from __future__ import annotations

import numpy as np
import pytest

from bench import random_surfaces
from bench.random_surfaces import RandomWaves
from protocol.config import RunConfig
from swarm.local import run_local
from world.geometry import integrate_geodesic, metric
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
    surface = make_surface(random_surfaces.name(3))
    assert isinstance(surface, RandomWaves) and surface.seed == 3
    start = np.array(surface.default_leader_start)
    p, v = integrate_geodesic(surface, start[:2], start[2:], 30.0)
    speed = [float(u @ metric(surface, q) @ u) for q, u in ((start[:2], start[2:]), (p, v))]
    assert speed[1] == pytest.approx(speed[0], rel=1e-9)  # a geodesic's g-speed is constant
    assert np.hypot(*(p - start[:2])) > 10.0  # and it went somewhere


@pytest.mark.parametrize("attr", ["w", "w-1", "w01", "x3", "w1.5", "W3", "w1234567890"])
def test_bad_names_are_refused_clearly(attr):
    with pytest.raises(ValueError, match="has no attribute"):
        make_surface(f"bench.random_surfaces:{attr}")


@pytest.mark.parametrize("seed", [-1, 1.0, True, "3"])
def test_bad_seeds_are_refused(seed):
    with pytest.raises(ValueError, match="non-negative integer"):
        random_surfaces.name(seed)


def test_a_run_on_a_random_surface_completes():
    summary, rows = run_local(RunConfig(surface=random_surfaces.name(9), ticks=10,
                                        estimator="auto-mix"))
    follower = summary["followers"]["1"]
    assert summary["complete"] and len(rows) == 10 * 2  # a row per agent and tick
    assert 0.0 <= follower["mean_required_range"] < follower["mean_stay_range"]


def test_the_benchmarks_choose_their_surfaces_by_flag(capsys):
    """``--random N --random-seed S`` (bench_estimator_table, replay_auto): N surfaces from
    seed S on, named so the world can load them; ``--surfaces`` yours, checked before any run,
    with ``--leader-start`` for every run; without either the fixed ones."""
    import argparse

    from bench.bench_estimator_table import add_surface_arguments, chosen_surfaces

    parser = argparse.ArgumentParser()
    add_surface_arguments(parser)

    def chosen(*argv):
        return chosen_surfaces(parser, parser.parse_args(list(argv)), fixed)

    fixed = ("elliptic", "wavy")
    assert chosen() == (fixed, {})
    assert chosen("--random", "3", "--random-seed", "40") == (tuple(
        f"bench.random_surfaces:w{s}" for s in (40, 41, 42)), {})
    assert "seeds 40-42" in capsys.readouterr().out
    assert chosen("--surfaces", "hyperbolic, tests.custom_surface:bowl",
                  "--leader-start", "1,2,1,0") == (
        ("hyperbolic", "tests.custom_surface:bowl"), {"leader_start": (1.0, 2.0, 1.0, 0.0)})
    for bad in (["--random", "-1"], ["--random", "2", "--surfaces", "wavy"],
                ["--surfaces", "no-such-preset"], ["--surfaces", "wavy", "--leader-start", "1,2"],
                ["--surfaces", " , "]):
        with pytest.raises(SystemExit):
            chosen(*bad)
    assert "no-such-preset" in capsys.readouterr().err


def test_the_benchmark_takes_noise_levels_as_range_bearing_pairs():
    import argparse

    from bench.bench_estimator_table import parse_levels

    parser = argparse.ArgumentParser()
    assert parse_levels(parser, "0.02/0.01,0.05/0.03") == ((0.02, 0.01), (0.05, 0.03))
    for bad in ("0.02", "0.02/0.01/0", "a/b", "-0.1/0.01", "nan/0.1", ""):
        with pytest.raises(SystemExit):
            parse_levels(parser, bad)
