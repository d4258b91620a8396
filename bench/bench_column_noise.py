"""Errors travelling down a noisy column: formation error and required range per follower.

``python bench/bench_column_noise.py [--out docs]`` runs a 10-follower column on the paper's
three surfaces at three range/bearing noise levels, with ``persist`` and ``auto`` (mean over
seeds 0-2, in-memory layout; ``--surfaces``, ``--levels`` and ``--seeds`` choose others, e.g.
``--surfaces gaussian-hill,ripple --levels mid --seeds 0,1``, and then write nothing unless
``--out`` is given), prints per follower the mean formation error (distance from
where it settled to its place in the ideal formation), the mean required sensing range and
persist / auto of the required range (the issue's target at the middle level: >= 1.25 at
every follower), and writes ``OUT/tables/column_noise.csv`` and ``OUT/figures/column_noise.png``
(:func:`swarm.plots.plot_column_noise`, which redraws it from the table alone).

Under honest sensing a snapped follower stands near, not on, its rod end, and its own rod
starts where it really stands, so each follower inherits its predecessors' placement errors:
the formation error grows down the column; the required range (measured against the rod end
of the predecessor's actual pose) need not.
"""
from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import RunConfig  # noqa: E402
from swarm.local import run_local  # noqa: E402
from swarm.plots import plot_column_noise  # noqa: E402

SURFACES = ("elliptic", "hyperbolic", "wavy")
LEVELS = ((0.005, 0.002), (0.02, 0.01), (0.05, 0.03))
ESTIMATORS = ("persist", "auto")
FOLLOWERS = 10
SEEDS = (0, 1, 2)


LEVEL_NAMES = dict(zip(("low", "mid", "high"), LEVELS))


def column(surface: str, level: tuple[float, float], estimator: str,
           seeds: tuple[int, ...] = SEEDS) -> dict[int, dict]:
    """Per follower, means over the seeds of its formation error and required range."""
    out = {k: {"formation": 0.0, "required": 0.0} for k in range(1, FOLLOWERS + 1)}
    for seed in seeds:
        summary, rows = run_local(RunConfig(surface=surface, followers=FOLLOWERS, seed=seed,
                                            estimator=estimator, noise_range=level[0],
                                            noise_bearing=level[1]))
        if not summary["complete"]:
            raise RuntimeError(f"{surface} {level} {estimator} seed {seed}: {summary['reason']}")
        for k in out:
            errors = [r["formation_error"] for r in rows if r["agent"] == k]
            out[k]["formation"] += sum(errors) / len(errors) / len(seeds)
            out[k]["required"] += (summary["followers"][str(k)]["mean_required_range"]
                                   / len(seeds))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="folder for tables/ and figures/ (default: docs, when "
                                 "the surfaces, levels and seeds are the defaults)")
    p.add_argument("--surfaces", default=",".join(SURFACES), help="comma-separated")
    p.add_argument("--levels", default=",".join(LEVEL_NAMES),
                   help="comma-separated, of " + ", ".join(LEVEL_NAMES))
    p.add_argument("--seeds", default=",".join(map(str, SEEDS)), help="comma-separated")
    args = p.parse_args()
    surfaces = tuple(args.surfaces.split(","))
    try:
        levels = tuple(LEVEL_NAMES[name] for name in args.levels.split(","))
        seeds = tuple(int(seed) for seed in args.seeds.split(","))
    except (KeyError, ValueError):
        p.error(f"--levels must name {', '.join(LEVEL_NAMES)}; --seeds must be integers")
    default = (surfaces, levels, seeds) == (SURFACES, LEVELS, SEEDS)
    out = args.out or ("docs" if default else None)
    started = time.monotonic()
    results = {(s, lv, e): column(s, lv, e, seeds) for s in surfaces for lv in levels
               for e in ESTIMATORS}
    rows = []
    for (s, lv, e), by_follower in results.items():
        for k, m in by_follower.items():
            rows.append({"surface": s, "noise_range": lv[0], "noise_bearing": lv[1],
                         "estimator": e, "follower": k,
                         "mean_formation_error": m["formation"],
                         "mean_required_range": m["required"]})
    for s in surfaces:
        for lv in levels:
            print(f"\n{s}, range sigma {lv[0]}, bearing sigma {lv[1]}: per follower 1..{FOLLOWERS}")
            for e in ESTIMATORS:
                m = results[(s, lv, e)]
                print(f"  {e:<8} formation " + " ".join(f"{m[k]['formation']:.3f}" for k in m))
                print(f"  {e:<8} required  " + " ".join(f"{m[k]['required']:.3f}" for k in m))
            persist, auto = results[(s, lv, "persist")], results[(s, lv, "auto")]
            print("  persist / auto, required range " + " ".join(
                f"{persist[k]['required'] / auto[k]['required']:.2f}" for k in persist))
            growth = {e: results[(s, lv, e)][FOLLOWERS]["formation"]
                      / results[(s, lv, e)][1]["formation"] for e in ESTIMATORS}
            print("  formation error, follower 10 / follower 1: "
                  + ", ".join(f"{e} {g:.2f}" for e, g in growth.items()))
    if out is None:
        print(f"\nwall time {time.monotonic() - started:.0f} s (nothing written: --out)")
        return
    out = Path(out)
    for sub in ("tables", "figures"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    with open(out / "tables" / "column_noise.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot_column_noise(rows, out / "figures" / "column_noise.png")
    print(f"\ntable: {out / 'tables' / 'column_noise.csv'}\nfigure: "
          f"{out / 'figures' / 'column_noise.png'}\nwall time {time.monotonic() - started:.0f} s")


if __name__ == "__main__":
    main()
