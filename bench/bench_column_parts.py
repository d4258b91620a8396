"""Where the error down a noisy column comes from: ``ekf``'s required range split into the
leader's place and the rod.

``python bench/bench_column_parts.py [--surface wavy] [--seeds 0,1,2] [--level 0.02/0.01]``
runs a 10-follower column (in memory, ``ekf``, the candidate ``auto`` follows there) at the
given range/bearing noise and again at a level a hundred times smaller, and ``persist`` at the
given level. A follower's estimate is ``L̂ + ρ̂``: where its leader stands now (read before
the move) plus the rod vector from the leader to the rod end (predicted). Per follower, means
over the estimated ticks and seeds, it prints

- ``leader``: ``|L̂ − L|``, the error of the leader's place at the decision (``L``: where the
  leader really stands, relative to the follower);
- ``rod, predicted``: ``|ρ̂ − ρ|`` at the decision (``ρ``: the true rod vector, from the
  leader's actual place to its rod end, the tick's ideal position);
- ``rod, filtered``: the same once the tick's readings are in (what the readings tell of the
  rod at that tick);
- ``required``: the mean required range (``|L̂ + ρ̂ − L − ρ|``), and persist's;
- ``rod, predicted`` again at the hundredfold smaller noise: what the filter's models foresee
  of a rod whose past is known almost exactly.

Where the predicted rod error stays large with almost no noise, the rod's change over one tick
is what its past does not foresee (on wavy the rods sweep over the waves), and no smoothing of
noisier readings recovers it. The split is read from the filters' mixture from outside (the
bench wraps ``RodTracker`` in its own process); the truth from the run's rows.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.policies import tracker  # noqa: E402
from protocol.config import RunConfig  # noqa: E402
from swarm.local import run_local  # noqa: E402

FOLLOWERS = 10


class _Recorder:
    """Wraps :class:`RodTracker`'s ``propose`` and ``learn`` to keep the mixture's leader
    place ``S + J`` and rod ``ρ`` after each, per tracker in the order they were made (the
    followers', 1 first: the in-memory layout builds them in chain order)."""

    def __init__(self) -> None:
        self.trackers: list = []
        self.proposed: dict[int, list] = {}
        self.learnt: dict[int, list] = {}
        init, propose, learn = (tracker.RodTracker.__init__, tracker.RodTracker.propose,
                                tracker.RodTracker.learn)
        recorder = self

        def mixture(self, mean):
            weights = self.weights()
            leader = mean[:, tracker.S] + mean[:, tracker.J]
            return weights @ leader, weights @ mean[:, tracker.RHO]

        def wrapped_init(self, *args, **kwargs):
            init(self, *args, **kwargs)
            recorder.trackers.append(self)
            recorder.proposed[id(self)], recorder.learnt[id(self)] = [], []

        def wrapped_propose(self, pre):
            proposal = propose(self, pre)
            recorder.proposed[id(self)].append(mixture(self, self._before_move(pre)[0]))
            return proposal

        def wrapped_learn(self, *args, **kwargs):
            out = learn(self, *args, **kwargs)
            recorder.learnt[id(self)].append(mixture(self, self.mean))
            return out

        tracker.RodTracker.__init__ = wrapped_init
        tracker.RodTracker.propose = wrapped_propose
        tracker.RodTracker.learn = wrapped_learn


def parts(recorder: _Recorder, config: RunConfig) -> np.ndarray:
    """One run's means per follower 2..N: leader, rod predicted, rod filtered, required
    (N - 1, 4)."""
    recorder.trackers.clear()
    summary, rows = run_local(config)
    if not summary["complete"]:
        raise RuntimeError(f"{config.surface} seed {config.seed}: {summary['reason']}")
    place = {(r["agent"], r["tick"]): np.array([r["pos_x"], r["pos_y"]]) for r in rows}
    ideal = {(r["agent"], r["tick"]): np.array([r["ideal_x"], r["ideal_y"]])
             for r in rows if r["agent"]}
    if len(recorder.trackers) != config.followers:
        raise RuntimeError("expected one ekf per follower")
    out = []
    for k, filters in enumerate(recorder.trackers, start=1):
        if k == 1:
            continue
        proposed, learnt = recorder.proposed[id(filters)], recorder.learnt[id(filters)]
        first = config.ticks - len(proposed)  # proposals from tick 1 (tick 0 has no filter)
        errors = []
        for tick in range(config.init_ticks, config.ticks):
            leader = place[(k - 1, tick)] - place[(k, tick - 1)]  # from where it stood
            rod = ideal[(k, tick)] - place[(k - 1, tick)]
            l_hat, rho_hat = proposed[tick - first]
            errors.append((np.linalg.norm(l_hat - leader), np.linalg.norm(rho_hat - rod),
                           np.linalg.norm(learnt[tick][1] - rod),
                           np.linalg.norm(l_hat + rho_hat - leader - rod)))
        out.append(np.mean(errors, axis=0))
    return np.array(out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--surface", default="wavy")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated")
    p.add_argument("--level", default="0.02/0.01", help="range/bearing sigma")
    args = p.parse_args()
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
        sigma_r, sigma_theta = (float(v) for v in args.level.split("/"))
    except ValueError:
        p.error("--seeds must be integers and --level R/B")
    recorder = _Recorder()

    def config(seed, estimator, scale=1.0):
        return RunConfig(surface=args.surface, followers=FOLLOWERS, seed=seed,
                         estimator=estimator, noise_range=sigma_r * scale,
                         noise_bearing=sigma_theta * scale)

    noisy = np.mean([parts(recorder, config(s, "ekf")) for s in seeds], axis=0)
    quiet = np.mean([parts(recorder, config(s, "ekf", 0.01)) for s in seeds], axis=0)
    persist = np.zeros(FOLLOWERS)
    for s in seeds:
        summary, _ = run_local(config(s, "persist"))
        persist += [summary["followers"][str(k)]["mean_required_range"] / len(seeds)
                    for k in range(1, FOLLOWERS + 1)]
    print(f"{args.surface}, {FOLLOWERS} followers, sigma {sigma_r}/{sigma_theta}, seeds "
          f"{args.seeds}: ekf's error at the decision, m (followers 2..{FOLLOWERS})")
    rows = (("leader |L^ - L|", noisy[:, 0]), ("rod, predicted", noisy[:, 1]),
            ("rod, filtered", noisy[:, 2]), ("required, ekf", noisy[:, 3]),
            ("required, persist", persist[1:]), ("persist / ekf", persist[1:] / noisy[:, 3]),
            ("rod, predicted, sigma / 100", quiet[:, 1]))
    for name, values in rows:
        print(f"  {name:<28}" + " ".join(f"{v:.4f}" for v in values))


if __name__ == "__main__":
    main()
