"""Driving followers at scale (``python bench/bench_drive.py [--followers 50] [--study]``).

1. The bound: a bare zenoh ``get`` round trip (agent process -> world process, median), and a
   drive tick's least cost, ``(control steps + snap steps + 2) x`` that: one round trip per
   control step, plus the ``pre`` sensing and the settling (design §8).
2. A column of ``--followers`` driving follower processes (the paper's default case, 40
   ticks, pipelined lockstep, world as embedded router in this process): ms per tick and per
   follower-tick (first to last completed tick: start-up excluded), and the ratio of the
   per-follower-tick cost to the bound (target <= 2); the same column teleporting, for
   comparison.
3. ``--study``: the wall time of ``python -m swarm experiment drive`` (the full study).

Figures depend on the machine and its load; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_world import sensing_round_trip, tick_wall_time  # noqa: E402
from protocol.config import RunConfig  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--followers", type=int, default=50)
    p.add_argument("--ticks", type=int, default=40)
    p.add_argument("--study", action="store_true", help="also time the full drive study")
    args = p.parse_args()

    drive = RunConfig(motion="drive")
    trips = drive.control_steps + drive.snap_steps + 2
    rtt = sensing_round_trip(1000)
    bound_ms = trips * rtt["bare_us"] / 1e3
    print(f"bare get round trip {rtt['bare_us']:.0f} us; a drive tick's bound "
          f"({drive.control_steps} control + {drive.snap_steps} snap + 2) x get = "
          f"{bound_ms:.2f} ms per follower-tick", flush=True)
    n = args.followers
    for label, options in (("drive", {"motion": "drive"}), ("teleport", {})):
        per_tick = tick_wall_time(n, args.ticks, agent_timeout=60.0, start_timeout=180.0,
                                  **options) * 1e3
        per_follower = per_tick / n
        print(f"{n} {label} followers: {per_tick:.1f} ms per tick, {per_follower:.3f} ms per "
              f"follower-tick, {per_follower / bound_ms:.2f} x the drive bound", flush=True)
    if args.study:
        from swarm.drive_study import run_drive_study

        with tempfile.TemporaryDirectory() as tmp:
            result = run_drive_study(Path(tmp) / "drive")
        print(f"drive study: {result['runs']} runs, {result['wall_time']:.1f} s wall "
              f"({result['runs_time']:.1f} s of runs)")


if __name__ == "__main__":
    main()
