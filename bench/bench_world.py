"""World service benchmarks, all figures from one run (``python bench/bench_world.py``).

1. A sensing query's round trip through the world (decode, sim, encode) against a bare zenoh
   ``get`` to a queryable that answers a fixed payload of the same size, same sessions.
2. Wall time per tick of a lockstep run with 1, 3 and 10 followers as separate processes
   (measured between the first and the last completed tick, so process start-up is excluded).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol import keys  # noqa: E402
from protocol.config import RunConfig  # noqa: E402
from protocol.messages import Rod, encode  # noqa: E402
from protocol.session import free_tcp_endpoint, zenoh_config  # noqa: E402
from swarm.launch import launch  # noqa: E402
from world.main import resolve  # noqa: E402
from world.sensing import TickSensing  # noqa: E402
from world.service import WorldService  # noqa: E402
from world.surfaces import make_surface  # noqa: E402

_CLIENT = r"""
import statistics, sys, time, zenoh
from protocol.messages import Sensing, SenseRequest, decode, encode
from protocol.session import zenoh_config
endpoint, sense_key, bare_key, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
request = encode(SenseRequest(tick=0))

def median_us(key, count):
    times = []
    for i in range(count + 50):
        t0 = time.perf_counter()
        for r in session.get(key, payload=request, timeout=5.0):
            decode(r.ok.payload.to_bytes(), Sensing)
        if i >= 50:
            times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6

with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
    world, bare = [], []
    for _ in range(5):  # interleaved, so both see the same machine noise
        world.append(median_us(sense_key, n // 5))
        bare.append(median_us(bare_key, n // 5))
    print(statistics.median(world), statistics.median(bare))
"""


def sensing_round_trip(n: int = 2000) -> dict:
    """Median round trip (µs) of a sensing query through the world and of a bare get.

    The world (embedded router) runs here; the querying agent is a separate process, as in a
    real run. The bare queryable answers a pre-encoded reply of the same size.
    """
    config = resolve(RunConfig(run_id="bench"))
    endpoint = free_tcp_endpoint()
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp, \
            zenoh.open(zenoh_config("router", listen=[endpoint])) as world_session:
        service = WorldService(world_session, config, make_surface(config.surface), tmp)
        service.sim.start_tick(0)
        service.sim.drive(0, 0, 0.0)
        # the leader's rod, as the leader would publish it: then follower 1 may sense
        world_session.put(keys.rod(config.run_id, 0),
                          encode(Rod(tick=0, length=config.spacing, side=config.side_sign)))
        deadline = time.monotonic() + 10.0
        while service._through[0] < 0:
            if time.monotonic() > deadline:
                raise RuntimeError("the world never counted the leader's rod")
            time.sleep(0.01)
        reply = encode(service.sim.sense(1, 0))
        # the world serves the pre-move sensing once per tick (design §5); to time that same
        # work over and over, each query here finds the tick's readings not yet begun
        sense, sensed = service.sim.sense, service.sim.agents[1].sensed

        def sense_afresh(agent: int, tick: int, look: bool = False):
            sensed[tick] = TickSensing()
            return sense(agent, tick, look)

        service.sim.sense = sense_afresh
        bare = world_session.declare_queryable("bench/bare/1", lambda q: q.reply(q.key_expr, reply))
        out = subprocess.run(
            [sys.executable, "-c", _CLIENT, endpoint, keys.sense(config.run_id, 1), "bench/bare/1",
             str(n)], cwd=root, capture_output=True, text=True, timeout=300, check=True)
        bare.undeclare()
        service.close()
    w, b = (float(x) for x in out.stdout.split())
    return {"world_us": w, "bare_us": b, "ratio": w / b}


def tick_wall_time(followers: int, ticks: int = 40, **options) -> float:
    """Seconds per lockstep tick with ``followers`` follower processes (first to last
    completed tick: start-up excluded); ``options`` are further :class:`RunConfig` fields
    (``motion="drive"``, longer timeouts for a big column)."""
    stamps: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        summary = launch(RunConfig(run_id=f"bench{followers}", followers=followers, ticks=ticks,
                                   **options),
                         Path(tmp) / "run", on_tick=lambda j: stamps.append(time.perf_counter()))
    if not summary["complete"]:
        raise RuntimeError(summary["reason"])
    return (stamps[-1] - stamps[0]) / (len(stamps) - 1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--queries", type=int, default=2000)
    p.add_argument("--chains", default="1,3,10")
    args = p.parse_args()
    rt = sensing_round_trip(args.queries)
    print(f"sensing query through the world: {rt['world_us']:.0f} µs median; bare zenoh get: "
          f"{rt['bare_us']:.0f} µs; ratio {rt['ratio']:.2f}x (target <= 1.5x)")
    for n in [int(x) for x in args.chains.split(",")]:
        per_tick = tick_wall_time(n)
        print(f"{n:>3} follower processes: {per_tick * 1e3:.1f} ms per tick "
              f"({per_tick * 1e3 / n:.1f} ms per follower)")


if __name__ == "__main__":
    main()
