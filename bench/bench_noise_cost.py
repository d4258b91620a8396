"""What honest sensing costs: a noisy run's wall time here against another checkout's.

``python bench/bench_noise_cost.py --baseline DIR`` runs the same noisy case (range 0.02,
bearing 0.01, actuation 0.01, 3 followers, 200 ticks, in-process over Zenoh) with this
checkout and with the checkout in DIR (e.g. ``git worktree add /tmp/before 56e2f0e``),
alternating, ``--repeats`` times each, and prints the runs' own wall times (``summary.json``,
start-up excluded), their medians and the ratio. Both use this interpreter.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
CASE = ["--in-process", "--followers", "3", "--ticks", "200", "--noise-range", "0.02",
        "--noise-bearing", "0.01", "--noise-move", "0.01", "--seed", "1"]


def wall_time(checkout: Path, estimator: str, scratch: Path, index: int) -> float:
    out = scratch / f"{checkout.name}-{estimator}-{index}"
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    subprocess.run([sys.executable, "-m", "swarm", "run", *CASE, "--estimator", estimator,
                    "--out", str(out)], cwd=checkout, env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    return json.loads((out / "summary.json").read_text())["wall_time"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", required=True, type=Path, help="the other checkout")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--estimators", default="persist,auto")
    args = p.parse_args()
    if not (args.baseline / "swarm" / "__main__.py").is_file():
        p.error(f"{args.baseline} is not a checkout of this project")
    with tempfile.TemporaryDirectory() as scratch:
        for estimator in args.estimators.split(","):
            times: dict[str, list[float]] = {"baseline": [], "here": []}
            for i in range(args.repeats):
                times["baseline"].append(wall_time(args.baseline, estimator, Path(scratch), i))
                times["here"].append(wall_time(HERE, estimator, Path(scratch), i))
            medians = {k: statistics.median(v) for k, v in times.items()}
            print(f"{estimator}: baseline " + " ".join(f"{t:.2f}" for t in times["baseline"])
                  + f" s (median {medians['baseline']:.2f}); here "
                  + " ".join(f"{t:.2f}" for t in times["here"])
                  + f" s (median {medians['here']:.2f}); ratio "
                  f"{medians['here'] / medians['baseline']:.3f}")


if __name__ == "__main__":
    main()
