"""Long chains as separate processes: wall time per tick and peak memory per agent process.

``python bench/bench_chain.py [--chains 10,20,50] [--ticks 40]`` runs the paper's default
case with N follower processes (lockstep, world as embedded router in this process), samples
every agent's peak resident set (``VmHWM`` in ``/proc/<pid>/status``) while the run goes, and
prints per chain: ms per tick (first to last completed tick, start-up excluded), ms per tick
per follower, and the largest and median peak RSS of the agent processes (target <= 80 MB).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import RunConfig  # noqa: E402
from swarm import launch as launch_module  # noqa: E402

SAMPLE_S = 0.1


def _peak_rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


class _Sampler:
    """Polls the peak RSS of the agent processes the launcher starts."""

    def __init__(self) -> None:
        self.peaks: dict[int, float] = {}
        self.stop = threading.Event()
        self.procs: list = []

    def run(self) -> None:
        while not self.stop.wait(SAMPLE_S):
            for proc in list(self.procs):
                mb = _peak_rss_mb(proc.pid)
                if mb is not None:
                    self.peaks[proc.pid] = max(self.peaks.get(proc.pid, 0.0), mb)


def chain(followers: int, ticks: int) -> dict:
    sampler = _Sampler()
    original_start = launch_module._ProcessAgents.start

    def start(self, service):  # let the sampler see the agent processes
        original_start(self, service)
        sampler.procs = self.procs

    stamps: list[float] = []
    thread = threading.Thread(target=sampler.run, daemon=True)
    thread.start()
    launch_module._ProcessAgents.start = start
    try:
        with tempfile.TemporaryDirectory() as tmp:
            summary = launch_module.launch(
                RunConfig(run_id=f"chain{followers}", followers=followers, ticks=ticks,
                          agent_timeout=60.0, start_timeout=120.0),
                Path(tmp) / "run", on_tick=lambda j: stamps.append(time.perf_counter()))
    finally:
        launch_module._ProcessAgents.start = original_start
        sampler.stop.set()
        thread.join()
    if not summary["complete"]:
        raise RuntimeError(summary["reason"])
    per_tick = (stamps[-1] - stamps[0]) / (len(stamps) - 1)
    peaks = list(sampler.peaks.values())
    return {"followers": followers, "ms_per_tick": per_tick * 1e3,
            "ms_per_tick_per_follower": per_tick * 1e3 / followers,
            "peak_rss_max_mb": max(peaks), "peak_rss_median_mb": statistics.median(peaks),
            "processes": len(peaks)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--chains", default="10,20,50")
    p.add_argument("--ticks", type=int, default=40)
    args = p.parse_args()
    print(f"{'followers':>9}  {'ms/tick':>8}  {'ms/tick/follower':>16}  "
          f"{'peak RSS max (MB)':>17}  {'median (MB)':>11}")
    for n in [int(x) for x in args.chains.split(",")]:
        r = chain(n, args.ticks)
        print(f"{r['followers']:>9}  {r['ms_per_tick']:>8.1f}  "
              f"{r['ms_per_tick_per_follower']:>16.2f}  "
              f"{r['peak_rss_max_mb']:>17.1f}  {r['peak_rss_median_mb']:>11.1f}"
              f"   ({r['processes']} agent processes; target <= 80 MB each)")


if __name__ == "__main__":
    main()
