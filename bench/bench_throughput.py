"""Throughput at scale, all figures and ratios from one run (``python bench/bench_throughput.py``).

1. The bound: a bare zenoh ``get`` round trip (agent process -> world process), median, and
   ``3 x`` that, the least a follower tick can cost with three round trips.
2. Chains of 10 and 50 follower processes (paper default case, 40 ticks, world as embedded
   router in this process), in four variants: unpipelined or pipelined lockstep (design §4),
   times five round trips per follower tick (the earlier protocol, emulated by
   ``bench/five_trips_follower.py``) or three (``act`` replies carry the sensing). Printed:
   ms per tick and per follower-tick (first to last completed tick: start-up excluded), the
   ratio of the per-follower-tick cost to the ``3 x get`` bound, and each variant's speed-up
   over the earlier order (unpipelined, five round trips) of the same run.
3. ``--grid``: the full paper grid (``swarm experiment paper``) wall time with the default
   2-process pool and on a 2-worker dask ``LocalCluster`` (``--scheduler``).

Figures depend on the machine and its load; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_world import sensing_round_trip  # noqa: E402
from protocol.config import RunConfig  # noqa: E402
from swarm import launch as launch_module  # noqa: E402

FIVE_TRIPS = str(ROOT / "bench" / "five_trips_follower.py")


def chain(followers: int, pipelined: bool, five_trips: bool, ticks: int) -> float:
    """Seconds per tick of one run with ``followers`` follower processes."""
    original = launch_module.agent_commands

    def commands(*args, **kwargs):
        cmds = original(*args, **kwargs)
        if five_trips:  # the followers (not the leader) run the five-round-trip variant
            cmds = [cmds[0]] + [[c[0], FIVE_TRIPS, *c[3:]] for c in cmds[1:]]
        return cmds

    stamps: list[float] = []
    launch_module.agent_commands = commands
    try:
        with tempfile.TemporaryDirectory() as tmp:
            summary = launch_module.launch(
                RunConfig(run_id=f"tp{followers}", followers=followers, ticks=ticks,
                          pipelined=pipelined, agent_timeout=60.0, start_timeout=180.0),
                Path(tmp) / "run", on_tick=lambda j: stamps.append(time.perf_counter()))
    finally:
        launch_module.agent_commands = original
    if not summary["complete"]:
        raise RuntimeError(summary["reason"])
    return (stamps[-1] - stamps[0]) / (len(stamps) - 1)


def grid_wall_time(scheduler: str | None) -> float:
    from swarm.experiment import run_paper_experiment

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        run_paper_experiment(Path(tmp) / "paper", workers=2, progress=False, scheduler=scheduler)
        return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--chains", default="10,50")
    p.add_argument("--ticks", type=int, default=40)
    p.add_argument("--grid", action="store_true", help="also time the full paper grid")
    args = p.parse_args()

    rtt = sensing_round_trip(1000)
    bound_ms = 3 * rtt["bare_us"] / 1e3
    print(f"bare get round trip {rtt['bare_us']:.0f} us (world sensing query "
          f"{rtt['world_us']:.0f} us); bound 3 x get = {bound_ms:.2f} ms per follower-tick\n")
    print(f"{'followers':>9}  {'order':>11}  {'trips':>5}  {'ms/tick':>8}  "
          f"{'ms/follower-tick':>16}  {'/ bound':>7}  {'speed-up':>8}")
    for n in [int(x) for x in args.chains.split(",")]:
        base = None
        for pipelined in (False, True):
            for five in (True, False):
                per_tick = chain(n, pipelined, five, args.ticks) * 1e3
                base = base or per_tick
                per_follower = per_tick / n
                print(f"{n:>9}  {'pipelined' if pipelined else 'unpipelined':>11}  "
                      f"{5 if five else 3:>5}  {per_tick:>8.1f}  {per_follower:>16.3f}  "
                      f"{per_follower / bound_ms:>7.2f}  {base / per_tick:>7.2f}x", flush=True)
    print("\nspeed-up: over the unpipelined five-round-trip order of the same chain, this run")
    if args.grid:
        pool = grid_wall_time(None)
        print(f"\nfull paper grid: {pool:.1f} s in a 2-process pool", flush=True)
        from distributed import LocalCluster

        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster:
            dask = grid_wall_time(cluster.scheduler_address)
        print(f"full paper grid: {dask:.1f} s on a 2-worker dask LocalCluster "
              f"({dask / pool:.2f} x the pool)")


if __name__ == "__main__":
    main()
