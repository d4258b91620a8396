"""ROS 2 benchmarks (``python bench/bench_ros2.py``), all figures from one run.

1. Export: a 10-follower, 400-tick run (agents in-process, as fast as it goes) is exported to a
   rosbag2/MCAP bag; prints the time of ``export_run`` in this process and of the command
   ``python -m swarm export`` end to end (interpreter start-up and imports included). Target:
   under 5 s.
2. Live: the same 10-follower lockstep run with follower processes, with and without ``--ros2``,
   side by side (alternating, ``--pairs`` pairs); prints each run's wall time per tick (first
   to last completed tick, so process start-up is left out) and whole wall time, their
   medians and the ratio with/without (target: at most 1.2×), and the CPU time the world's
   thread spends completing a tick with and without (a figure machine load disturbs less).
"""
from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocol.config import RunConfig  # noqa: E402
from swarm.launch import launch  # noqa: E402
from swarm.ros2_export import export_run  # noqa: E402
from world.service import WorldService  # noqa: E402


def timed_run(config: RunConfig, out: Path, in_process: bool,
              cpu: list[float] | None = None) -> tuple[float, float]:
    """``(seconds per tick, whole wall seconds)`` of one run; with ``cpu``, the CPU seconds
    the world's thread spends completing each tick (``WorldService._complete_tick``: rows,
    files, checkpoint, view and, with --ros2, the ROS 2 messages) are appended to it."""
    stamps: list[float] = []
    original = WorldService._complete_tick

    def complete_tick(service, tick):
        start = time.thread_time()
        rows = original(service, tick)
        if cpu is not None:
            cpu.append(time.thread_time() - start)
        return rows

    WorldService._complete_tick = complete_tick  # measured from outside, restored below
    try:
        start = time.perf_counter()
        summary = launch(config, out, in_process=in_process,
                         on_tick=lambda j: stamps.append(time.perf_counter()))
        wall = time.perf_counter() - start
    finally:
        WorldService._complete_tick = original
    if not summary["complete"]:
        raise RuntimeError(f"the run did not complete: {summary['reason']}")
    return (stamps[-1] - stamps[0]) / (len(stamps) - 1), wall


def export_figures(tmp: Path, followers: int, ticks: int) -> None:
    run = tmp / "export-run"
    timed_run(RunConfig(run_id="bench-export", followers=followers, ticks=ticks), run, True)
    start, cpu = time.perf_counter(), time.process_time()
    bag = export_run(run, tmp / "bag-a")
    inside, inside_cpu = time.perf_counter() - start, time.process_time() - cpu
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "swarm", "export", str(run), "--out",
                    str(tmp / "bag-b")], cwd=ROOT, check=True, capture_output=True, timeout=300)
    command = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    command_cpu = (after.ru_utime + after.ru_stime) - (children.ru_utime + children.ru_stime)
    size = sum(p.stat().st_size for p in bag.iterdir()) / 1e6
    print(f"export of {followers} followers x {ticks} ticks (bag {size:.1f} MB): export_run "
          f"{inside:.2f} s ({inside_cpu:.2f} s CPU); `python -m swarm export` end to end "
          f"{command:.2f} s ({command_cpu:.2f} s CPU); target < 5 s")


def live_figures(tmp: Path, followers: int, ticks: int, pairs: int) -> None:
    results: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    cpu: dict[bool, list[float]] = {False: [], True: []}
    for i in range(pairs):
        for ros in (False, True) if i % 2 == 0 else (True, False):
            config = RunConfig(run_id=f"bench-live-{i}-{int(ros)}", followers=followers,
                               ticks=ticks, ros2=ros)
            per_tick, wall = timed_run(config, tmp / config.run_id, False, cpu[ros])
            results[ros].append((per_tick, wall))
            print(f"  {'with' if ros else 'without'} --ros2: {per_tick * 1e3:.1f} ms per tick, "
                  f"{wall:.2f} s wall")
    tick = {ros: statistics.median(t for t, _ in runs) for ros, runs in results.items()}
    wall = {ros: statistics.median(w for _, w in runs) for ros, runs in results.items()}
    print(f"live, {followers} follower processes x {ticks} ticks, median of {pairs}: "
          f"{tick[False] * 1e3:.1f} -> {tick[True] * 1e3:.1f} ms per tick (ratio "
          f"{tick[True] / tick[False]:.2f}x), wall {wall[False]:.2f} -> {wall[True]:.2f} s "
          f"(ratio {wall[True] / wall[False]:.2f}x; target <= 1.2x)")
    print(f"world thread CPU per completed tick: {statistics.mean(cpu[False]) * 1e3:.2f} -> "
          f"{statistics.mean(cpu[True]) * 1e3:.2f} ms (the ROS 2 messages: "
          f"{(statistics.mean(cpu[True]) - statistics.mean(cpu[False])) * 1e3:.2f} ms a tick)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--followers", type=int, default=10)
    p.add_argument("--export-ticks", type=int, default=400)
    p.add_argument("--live-ticks", type=int, default=200)
    p.add_argument("--pairs", type=int, default=3)
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-ros2-") as tmp:
        export_figures(Path(tmp), args.followers, args.export_ticks)
        live_figures(Path(tmp), args.followers, args.live_ticks, args.pairs)


if __name__ == "__main__":
    main()
