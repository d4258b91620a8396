"""Driving columns beyond issue #30's grid: ``python bench/bench_drive_sweep.py [--seed 4603]
[--runs 20]``.

Draws ``--runs`` cases at random (from ``--seed``): a surface among the paper's, the held-out
ones (:mod:`world.held_out`) and four random wave fields (:mod:`world.random_waves`, names drawn
too), 3 or 5 followers, persist, EDMD or ``auto``, and a sensor noise level σ_r/σ_θ among
0.005/0.002 … 0.05/0.03 (one with the bearing noisier than the range), a run seed; 150 ticks,
``T_c`` 1.28, the default robot. Each case runs driving and teleporting, in memory
(:mod:`swarm.local`, the same numbers as a Zenoh run), two at a time, and prints the last
follower's mean formation error driving, issue #30's bound on it (2 × teleport's + 0.05 m), every
follower's worst tick driving, and whether both bounds hold (worst ≤ 1 m). The cases are drawn
in the same order whatever ``--runs``, so a longer sweep extends a shorter one.

Figures depend on nothing but the seed; nothing here is asserted. docs/drive.md (*Stop 46*,
*Stop 47*) quotes ``--seed 4603 --runs 20``.
"""
from __future__ import annotations

import argparse
import random
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import RunConfig  # noqa: E402
from swarm.drive_study import WORST_TICK, drive_bound, within_bound  # noqa: E402
from swarm.local import run_local  # noqa: E402

SURFACES = ["wavy", "elliptic", "hyperbolic", "gaussian-hill", "ripple",
            "world.held_out:egg_crate", "world.held_out:twin_hills", "world.held_out:dunes",
            "world.held_out:long_waves", "world.held_out:twisted_saddle"]
LEVELS = [(0.005, 0.002), (0.01, 0.005), (0.02, 0.01), (0.035, 0.02), (0.05, 0.03),
          (0.015, 0.04), (0.03, 0.015)]
ESTIMATORS = ["persist", "auto", "edmd"]


def draw(seed: int, runs: int) -> list[dict]:
    """The sweep's cases, as :class:`RunConfig` keywords (without the motion)."""
    rng = random.Random(seed)
    surfaces = SURFACES + [f"world.random_waves:w{rng.randint(1000, 9999)}" for _ in range(4)]
    cases = []
    for _ in range(runs):
        level = rng.choice(LEVELS)
        surface, followers = rng.choice(surfaces), rng.choice([3, 5])
        estimator, run_seed = rng.choice(ESTIMATORS), rng.randint(0, 999)
        cases.append(dict(surface=surface, followers=followers, estimator=estimator,
                          noise_range=level[0], noise_bearing=level[1], seed=run_seed,
                          ticks=150))
    return cases


def measure(case: dict) -> tuple[float, float, float]:
    """The last follower's mean formation error driving and teleporting, and the worst tick
    of any follower driving (m)."""
    drive, _ = run_local(RunConfig(motion="drive", **case))
    teleport, _ = run_local(RunConfig(**case))
    last = str(case["followers"])
    worst = max(f["worst_formation_error"] for f in drive["followers"].values())
    return (drive["followers"][last]["mean_formation_error"],
            teleport["followers"][last]["mean_formation_error"], worst)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=4603)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    if args.runs < 1 or args.workers < 1:
        parser.error("--runs and --workers must be at least 1")
    cases = draw(args.seed, args.runs)
    missed = 0
    print("| case | last, drive | bound | worst, drive | both bounds |\n|---|---|---|---|---|")
    with ProcessPoolExecutor(args.workers) as pool:
        for case, (last, teleport, worst) in zip(cases, pool.map(measure, cases)):
            held = within_bound(last, teleport) and worst <= WORST_TICK
            missed += not held
            print(f"| {case['surface']}, {case['followers']} followers, σ "
                  f"{case['noise_range']}/{case['noise_bearing']}, {case['estimator']}, seed "
                  f"{case['seed']} | {last:.3f} | {drive_bound(teleport):.3f} | {worst:.3f} | "
                  f"{'yes' if held else 'NO'} |", flush=True)
    print(f"\n{len(cases)} runs; {missed} miss a bound")


if __name__ == "__main__":
    main()
