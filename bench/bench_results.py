"""Cost of recording one tick as a run grows: append the rows and observations, write the
world's checkpoint and the summary (what the world does after every tick).

Prints the median cost per tick around tick 100 and around tick 10,000 of one run (3
followers) and their ratio (target: within 1.5x: the write cost is flat, not growing with the
run's length).

    python bench/bench_results.py [--ticks 10000] [--followers 3]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import RunConfig  # noqa: E402
from protocol.messages import Observation  # noqa: E402
from world import checkpoint  # noqa: E402
from world.results import RunRecorder  # noqa: E402

WINDOW = 50  # ticks timed around each point


def fake_tick(j: int, followers: int) -> tuple[list[dict], list[tuple[int, Observation]]]:
    rows = [{"tick": j, "t": 1.28 * j, "agent": 0, "pos_x": 0.1 * j, "pos_y": -0.2 * j,
             "missed": 0}]
    obs = []
    for k in range(1, followers + 1):
        rows.append({"tick": j, "t": 1.28 * j, "agent": k, "estimator": "auto",
                     "ideal_x": 1.0 + j, "ideal_y": 2.0 - j, "est_x": 1.01 + j, "est_y": 2.02 - j,
                     "pos_x": 1.0 + j, "pos_y": 2.0 - j, "required_range": 0.0123 + 1e-6 * j,
                     "stay_range": 2.45, "persist_range": 0.0294, "lost": 0,
                     "formation_error": 1e-12, "persist_range_noise_free": 0.0291, "missed": 0})
        obs.append((k, Observation(tick=j, estimator="auto", measurement=(3.57, 0.1 * j),
                                   prediction=(3.56, 0.1 * j), followed="edmd-bu")))
    return rows, obs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ticks", type=int, default=10_000)
    p.add_argument("--followers", type=int, default=3)
    args = p.parse_args()
    config = RunConfig(followers=args.followers, ticks=args.ticks + WINDOW + 1)
    sim_state = {"tick": 0, "leader_velocity": [1.0, 0.0], "leader_time": 0.0,
                 "agents": [{"pos": [1.0, 2.0], "heading": [1.0, 0.0], "settled": {}}
                            for _ in range(args.followers + 1)]}
    times: dict[int, list[float]] = {}
    points = (100, args.ticks)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        recorder = RunRecorder(out, config)
        recorder.open()
        for j in range(args.ticks + WINDOW):
            rows, obs = fake_tick(j, args.followers)
            start = time.perf_counter()
            recorder.add_tick(rows, obs)
            checkpoint.save(out, run_id=config.run_id, start="bench", sim={**sim_state, "tick": j},
                            offsets=recorder.offsets, wall_time=float(j))
            recorder.write_summary(complete=False, reason="running", wall_time=float(j))
            elapsed = time.perf_counter() - start
            for point in points:
                if point <= j < point + WINDOW:
                    times.setdefault(point, []).append(elapsed)
        recorder.close()
        size = (out / "ticks.csv").stat().st_size
    early, late = (statistics.median(times[p]) * 1e3 for p in points)
    print(f"recording one tick ({args.followers} followers), median over {WINDOW} ticks:")
    print(f"  at tick {points[0]:>6}: {early:.3f} ms")
    print(f"  at tick {points[1]:>6}: {late:.3f} ms")
    print(f"  ratio late/early: {late / early:.2f} (target <= 1.5); ticks.csv {size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
