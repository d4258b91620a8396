"""Formation health of driving columns under noise (issue #30's grid):
``python bench/bench_drive_health.py [--seeds 5] [--surfaces elliptic,hyperbolic,wavy]``.

Every cell (surface × followers × noise level × estimator) is run with ``--motion drive`` and
teleporting, over the seeds, 150 ticks, in memory (:mod:`swarm.local`, the same numbers as a
Zenoh run) in a small process pool. Per cell it prints, in metres, the mean over the seeds of
follower 1's mean formation error, of the last follower's mean formation error, and the worst
tick of any follower over every seed (the largest formation error any follower settled with),
for drive and for teleport, and how many runs broke formation (a follower beyond 0.5 m) or
ended incomplete. Then the issue's criteria per cell: drive's last-follower mean
≤ 2 × teleport's + 0.05 m, and the worst tick ≤ 1 m.

Figures depend on nothing but the configurations and seeds; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_estimator_table import parse_levels  # noqa: E402
from protocol.config import RunConfig, estimator_options  # noqa: E402
from swarm.drive_study import NOISE_LEVELS, WORST_TICK, within_bound  # noqa: E402

BROKEN = 0.5  # a follower this far out of formation: the column broke (issue #30's measure)


def label(level: tuple[float, float]) -> str:
    """A noise level as the table and ``--noise`` name it: ``σ_r/σ_θ``, or ``0`` for none."""
    return f"{level[0]:g}/{level[1]:g}" if any(level) else "0"


NOISE = ",".join(label(level) for level in NOISE_LEVELS.values())
"""The drive study's noise levels (the default of ``--noise``)."""


def _run(job: tuple) -> tuple[tuple, dict]:
    """One run: its cell key and per-follower mean / worst formation error."""
    from swarm.local import run_local
    from world.sim import RequestError

    surface, followers, (sigma_r, sigma_t), estimator, motion, seed, ticks = job
    extra = {"motion": "drive"} if motion == "drive" else {}
    config = RunConfig(run_id="health", surface=surface, followers=followers, ticks=ticks,
                       seed=seed, noise_range=sigma_r, noise_bearing=sigma_t,
                       **estimator_options(estimator), **extra)
    try:
        summary, _ = run_local(config)
    except RequestError:  # a request the world refuses ends a Zenoh run incomplete, as here
        return job, {"first": math.nan, "last": math.nan, "worst": math.inf, "broken": True,
                     "complete": False}
    # each follower's mean and worst as the world counted them (protocol.health), follower 1 first
    followers = [f for k in sorted(summary["followers"], key=int)
                 if (f := summary["followers"][k])["worst_formation_error"] is not None]
    means = [f["mean_formation_error"] for f in followers]
    worst = max(f["worst_formation_error"] for f in followers)
    return job, {"first": means[0], "last": means[-1], "worst": worst,
                 "broken": worst > BROKEN, "complete": bool(summary["complete"])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--ticks", type=int, default=150)
    p.add_argument("--surfaces", default="elliptic,hyperbolic,wavy")
    p.add_argument("--followers", default="3,5")
    p.add_argument("--noise", default=NOISE,
                   help="comma-separated R/B levels (0 for none) [default the drive study's: "
                        "%(default)s]")
    p.add_argument("--estimators", default="edmd-b,persist")
    p.add_argument("--workers", type=int, default=2)
    args = p.parse_args()
    levels = parse_levels(p, ",".join("0/0" if x == "0" else x for x in args.noise.split(",")),
                          "--noise")
    if args.seeds < 1 or args.ticks < 1 or not all(
            n.isdigit() and int(n) >= 1 for n in args.followers.split(",")):
        p.error("--seeds, --ticks and every --followers entry must be >= 1")
    jobs = [(surface, int(n), level, est, motion, seed, args.ticks)
            for surface in args.surfaces.split(",") for n in args.followers.split(",")
            for level in levels for est in args.estimators.split(",")
            for motion in ("drive", "teleport") for seed in range(args.seeds)]
    results: dict[tuple, dict] = {}
    with ProcessPoolExecutor(args.workers,
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        for job, result in pool.map(_run, jobs, chunksize=1):
            results[job] = result
    print("| surface | N | σ_r/σ_θ | estimator | drive: f1 mean / last mean / worst | "
          "teleport: f1 / last / worst | drive broke | incomplete | last ≤ 2·tel+0.05 | "
          "worst ≤ 1 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    failures = 0
    for surface in args.surfaces.split(","):
        for n in args.followers.split(","):
            for level in levels:
                for est in args.estimators.split(","):
                    cell = {}
                    for motion in ("drive", "teleport"):
                        runs = [results[(surface, int(n), level, est, motion, s, args.ticks)]
                                for s in range(args.seeds)]
                        cell[motion] = {
                            "first": sum(r["first"] for r in runs) / len(runs),
                            "last": sum(r["last"] for r in runs) / len(runs),
                            "worst": max(r["worst"] for r in runs),
                            "broken": sum(r["broken"] for r in runs),
                            "incomplete": sum(not r["complete"] for r in runs)}
                    d, t = cell["drive"], cell["teleport"]
                    mean_ok = within_bound(d["last"], t["last"])
                    worst_ok = d["worst"] <= WORST_TICK  # False for NaN and infinity too
                    failures += (not mean_ok) + (not worst_ok)
                    print(f"| {surface} | {n} | {label(level)} | {est} | {d['first']:.3f} / "
                          f"{d['last']:.3f} / {d['worst']:.3f} | {t['first']:.3f} / "
                          f"{t['last']:.3f} / {t['worst']:.3f} | {d['broken']}/{args.seeds} | "
                          f"{d['incomplete']} | {'yes' if mean_ok else 'NO'} | "
                          f"{'yes' if worst_ok else 'NO'} |", flush=True)
    cells = len(jobs) // (2 * args.seeds)
    print(f"\n{len(jobs)} runs; criteria failing: {failures} of {2 * cells} (two per cell) "
          f"(cpu count {os.cpu_count()})")


if __name__ == "__main__":
    main()
