"""What honest sensing costs: a noisy run's wall time here against another checkout's.

``python bench/bench_noise_cost.py --baseline DIR`` runs the same noisy case (range 0.02,
bearing 0.01, actuation 0.01, 3 followers, 200 ticks, seed 1) with this checkout and with the
checkout in DIR (e.g. ``git worktree add /tmp/before 8d2b9b1``), for each estimator
(``--estimators``, default ``persist,auto``) and layout (``--layouts``, default in-process
and processes, over Zenoh), in ``--repeats`` rounds that alternate the two checkouts run by
run (the machine may be shared: interleaved rounds see the same load), and prints the runs'
own wall times (``summary.json``, start-up excluded), their medians and the ratio here /
baseline; then the same for the CPU time each run took, all its processes together
(start-up included), which a shared machine disturbs less. Both use this interpreter.
``--margin N`` also runs every cell at N ticks and prints the wall time per tick between the
two lengths (what a longer run pays for each tick, without the start and end a 200-tick run's
ratio dilutes).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
TICKS = 200
CASE = ["--followers", "3", "--noise-range", "0.02", "--noise-bearing", "0.01", "--noise-move",
        "0.01", "--seed", "1"]
LAYOUTS = {"in-process": ["--in-process"], "processes": []}


def _cpu() -> float:
    """CPU time (user and system) of this process's finished children so far (s)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_times(checkout: Path, estimator: str, layout: str, out: Path,
              ticks: int = TICKS) -> tuple[float, float]:
    """The wall time ``summary.json`` of one run of the case reports and the CPU time the
    run's processes took (s). A run whose process dies after its summary says it is complete
    counts (older checkouts' in-process runs can abort while the interpreter exits, with an
    agent thread still in Zenoh); one that dies before is run again, twice at most."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    for attempt in range(3):
        before = _cpu()
        died = subprocess.run([sys.executable, "-m", "swarm", "run", *LAYOUTS[layout], *CASE,
                               "--ticks", str(ticks), "--estimator", estimator,
                               "--out", str(out / str(attempt))],
                              cwd=checkout, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, timeout=600).returncode
        summary = out / str(attempt) / "summary.json"
        if summary.is_file() and json.loads(summary.read_text()).get("complete"):
            if died:
                print(f"({checkout.name} {estimator} {layout}: exit {died} after a complete "
                      "run, counted)", file=sys.stderr)
            return json.loads(summary.read_text())["wall_time"], _cpu() - before
    raise RuntimeError(f"{checkout} {estimator} {layout}: three runs failed (exit {died})")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", required=True, type=Path, help="the other checkout")
    p.add_argument("--repeats", type=int, default=5, help="rounds (default 5)")
    p.add_argument("--estimators", default="persist,auto")
    p.add_argument("--layouts", default=",".join(LAYOUTS),
                   help=f"comma-separated, of {', '.join(LAYOUTS)} (default both)")
    p.add_argument("--margin", type=int, default=None, metavar="N",
                   help=f"also run N ticks (> {TICKS}) and print the wall time per tick between")
    args = p.parse_args()
    if args.margin is not None and not TICKS < args.margin <= 100_000:
        p.error(f"--margin must be a tick count above {TICKS} (and at most 100000)")
    if not (args.baseline / "swarm" / "__main__.py").is_file():
        p.error(f"{args.baseline} is not a checkout of this project")
    layouts = args.layouts.split(",")
    if args.repeats < 1 or not set(layouts) <= set(LAYOUTS):
        p.error(f"--repeats must be >= 1 and --layouts of {', '.join(LAYOUTS)}")
    cells = [(e, lay) for lay in layouts for e in args.estimators.split(",")]
    times = {(cell, side): [] for cell in cells for side in ("baseline", "here")}
    cpus = {key: [] for key in times}
    longer = {key: [] for key in times}
    with tempfile.TemporaryDirectory() as scratch:
        for i in range(args.repeats):
            for cell in cells:
                for side, checkout in (("baseline", args.baseline), ("here", HERE)):
                    out = Path(scratch) / f"{side}-{cell[0]}-{cell[1]}-{i}"
                    wall, cpu = run_times(checkout, *cell, out)
                    times[(cell, side)].append(wall)
                    cpus[(cell, side)].append(cpu)
                    if args.margin is not None:
                        wall, _ = run_times(checkout, *cell, out.with_name(out.name + "-long"),
                                            args.margin)
                        longer[(cell, side)].append(wall)
    for what, table in (("wall time", times), ("CPU time", cpus)):
        for estimator, layout in cells:
            got = {side: table[((estimator, layout), side)] for side in ("baseline", "here")}
            medians = {side: statistics.median(v) for side, v in got.items()}
            print(f"{what}, {estimator}, {layout}: baseline "
                  + " ".join(f"{t:.2f}" for t in got["baseline"])
                  + f" s (median {medians['baseline']:.2f}); here "
                  + " ".join(f"{t:.2f}" for t in got["here"])
                  + f" s (median {medians['here']:.2f}); ratio "
                  f"{medians['here'] / medians['baseline']:.3f}")
    if args.margin is not None:
        span = args.margin - TICKS
        for estimator, layout in cells:
            key = (estimator, layout)
            per = {side: (statistics.median(longer[(key, side)])
                          - statistics.median(times[(key, side)])) / span
                   for side in ("baseline", "here")}
            print(f"wall time per tick from {TICKS} to {args.margin} ticks, {estimator}, "
                  f"{layout}: baseline {per['baseline'] * 1e3:.2f} ms, here "
                  f"{per['here'] * 1e3:.2f} ms; ratio {per['here'] / per['baseline']:.3f}")


if __name__ == "__main__":
    main()
