"""How well could a follower down a noisy column predict its rod end? Bounds per follower.

``python bench/bench_column_bound.py [--surface wavy]`` runs the 10-follower column of
``bench_column_noise.py`` at its middle level (range 0.02, bearing 0.01, seeds 0-2, ``auto``,
in-memory layout) and prints per follower:

1. the mean required range of ``persist`` (its counterfactual in the same runs) and of ``auto``;
2. on the exact rod history of the noise-free ideal column (the rod vector ``rho_j`` from agent
   ``k-1`` to agent ``k`` at tick ``j``, 4 + 36 ticks), the mean one-tick error of predicting
   ``rho_j`` by ``rho_{j-1}`` (persist's model error), by the constant turn-and-stretch rate
   of ``ekf`` (``rho_{j-1}^2 / rho_{j-2}`` as complex numbers), by a constant second
   difference, and by the best fixed linear recurrence of order 2 (2x2 matrices and a
   constant) fitted in hindsight on the same ticks;
3. the best fixed linear predictor of the true offset to the rod end from the follower's own
   readings in those noisy runs — the pre reading plus 2x2 matrices on the last ``m`` rod
   vectors it read (the rod end minus the leader, read from the same place after the move and
   once settled, averaged) plus a constant — fitted in hindsight per follower over the seeds'
   ticks: an optimistic bound for any estimator that predicts linearly from those readings,
   and ``persist / bound``.

Hindsight fits see the answers, so they are bounds, not estimators; an estimator has to learn
the same from its own past. Measured on wavy (#31): the bound is 1.4-2.7x below persist at
every follower, so the information is in the readings; a constant-rate rod model errs on the
exact history by 0.02-0.09 m, as much as the noise it averages, and the fitted recurrence is a
damped swing about a mean, which ``ekf``'s swinging rods model (persist / auto 1.11-2.42 with
them, 0.96-1.91 without; docs/estimators.md).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.policies import Policy, make_policy, relative  # noqa: E402
from protocol.config import RunConfig  # noqa: E402
from swarm.drive_study import NOISE_LEVELS  # noqa: E402
from swarm.local import run_local  # noqa: E402
from world import ideal_formation  # noqa: E402
from world.surfaces import make_surface  # noqa: E402

FOLLOWERS, SEEDS, LEVEL, LAGS = 10, (0, 1, 2), NOISE_LEVELS["mid"], (1, 2, 3)
_DEFAULTS = RunConfig()  # the paper's ticks, spacing and comm period, as the runs use them
TICKS, SPACING, COMM_PERIOD = _DEFAULTS.ticks, _DEFAULTS.spacing, _DEFAULTS.comm_period


class Recorded(Policy):
    """The policy the settings name, keeping what each tick's ``learn`` was given."""

    def __init__(self, settings) -> None:
        self.policy, self.ticks = make_policy(settings), {}
        self.name = self.policy.name

    def propose(self, pre):
        return self.policy.propose(pre)

    def learn(self, settled, target, before=None):
        self.ticks[settled.tick] = (settled, target, before)
        return self.policy.learn(settled, target, before)

    def skip(self) -> None:
        self.policy.skip()


def rod_readings(ticks: dict) -> dict[int, np.ndarray]:
    """Per tick, the rod vector the follower read: rod end minus leader from the same place,
    after the move and settled, averaged."""
    out = {}
    for j, (settled, _, before) in ticks.items():
        seen = [np.asarray(s.rod) - relative(s) for s in (
            None if before is None else before.moved, settled) if s is not None and s.rod]
        if seen:
            out[j] = np.mean(seen, axis=0)
    return out


def exact_errors(rho: np.ndarray) -> list[float]:
    """Mean one-tick errors on the exact rod history ``rho`` (ticks, 2): persist, constant
    rate, constant second difference, order-2 recurrence fitted in hindsight."""
    c = rho[:, 0] + 1j * rho[:, 1]
    j = np.arange(4, len(c))
    x = np.hstack([rho[j - 1], rho[j - 2], np.ones((len(j), 1))])
    coef, *_ = np.linalg.lstsq(x, rho[j], rcond=None)
    return [float(np.abs(c[j] - c[j - 1]).mean()),
            float(np.abs(c[j] - c[j - 1] ** 2 / c[j - 2]).mean()),
            float(np.abs(c[j] - 3 * c[j - 1] + 3 * c[j - 2] - c[j - 3]).mean()),
            float(np.hypot(*(rho[j] - x @ coef).T).mean())]


def hindsight_bound(samples: list[tuple[np.ndarray, list[np.ndarray], np.ndarray]],
                    lags: int) -> float:
    """Mean error of the least-squares fit of ``truth - pre`` on the last ``lags`` rod
    readings and a constant (``samples``: pre reading, rod readings newest first, truth)."""
    pre = np.array([s[0] for s in samples])
    truth = np.array([s[2] for s in samples])
    x = np.hstack([np.array([s[1][i] for s in samples]) for i in range(lags)]
                  + [np.ones((len(samples), 1))])
    coef, *_ = np.linalg.lstsq(x, truth - pre, rcond=None)
    return float(np.hypot(*(truth - pre - x @ coef).T).mean())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--surface", default="wavy")
    args = p.parse_args()
    ideal = ideal_formation(make_surface(args.surface), None, FOLLOWERS, SPACING, COMM_PERIOD,
                            TICKS)
    required = {name: np.zeros(FOLLOWERS) for name in ("persist", "auto")}
    samples: dict[int, list] = {k: [] for k in range(1, FOLLOWERS + 1)}
    for seed in SEEDS:
        policies: list[Recorded] = []

        def factory(settings, into=policies):
            into.append(Recorded(settings))
            return into[-1]

        summary, rows = run_local(RunConfig(surface=args.surface, followers=FOLLOWERS, seed=seed,
                                            estimator="auto", noise_range=LEVEL[0],
                                            noise_bearing=LEVEL[1]), policy_factory=factory)
        where = {(r["tick"], r["agent"]): r for r in rows}
        for k in range(1, FOLLOWERS + 1):
            mine = summary["followers"][str(k)]
            required["persist"][k - 1] += mine["mean_persist_range"] / len(SEEDS)
            required["auto"][k - 1] += mine["mean_required_range"] / len(SEEDS)
            rods = rod_readings(policies[k - 1].ticks)
            for j, (_, target, before) in policies[k - 1].ticks.items():
                if target is None or before is None or any(j - i not in rods for i in LAGS):
                    continue
                row, stood = where[(j, k)], where[(j - 1, k)]
                truth = np.array([row["ideal_x"] - stood["pos_x"], row["ideal_y"] - stood["pos_y"]])
                samples[k].append((relative(before.pre), [rods[j - i] for i in LAGS], truth))
    print(f"{args.surface}, 10 followers, range sigma {LEVEL[0]}, bearing sigma {LEVEL[1]}, "
          f"seeds {SEEDS[0]}-{SEEDS[-1]}")
    print("follower | required range: persist auto | exact rod history, one-tick error: "
          "persist const-rate 2nd-diff fitted-AR2 | hindsight bound m=1 m=2 m=3 | persist/bound")
    for k in range(1, FOLLOWERS + 1):
        exact = exact_errors(ideal[k] - ideal[k - 1])
        bounds = [hindsight_bound(samples[k], m) for m in LAGS]
        print(f"{k:8d} | {required['persist'][k - 1]:.4f} {required['auto'][k - 1]:.4f} | "
              + " ".join(f"{e:.3f}" for e in exact) + " | "
              + " ".join(f"{b:.4f}" for b in bounds)
              + f" | {required['persist'][k - 1] / min(bounds):.2f}")


if __name__ == "__main__":
    main()
