"""Wall time of a run under attack against the same run left alone.

``python bench/bench_attack.py [--repeats 3] [--rounds 8]``.

The attack is the one of ``tests/test_limits.py``: rounds of 8-10 MB and deeply nested msgpack
payloads fired at the world's ``sense``/``act`` queryables and published on the agents' keys
while the run goes on. Clean and attacked runs alternate (same config, in-process agents, so
only the attack differs); the figure is the ratio of the medians. Target (issue 8): at most 1.5.
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
from protocol.session import free_tcp_endpoint  # noqa: E402
from swarm.launch import RunCredentials, launch  # noqa: E402
from tests.test_limits import ATTACK_ROUNDS, attack, attack_counts  # noqa: E402

TARGET = 1.5


def timed_run(config: RunConfig, rounds: int) -> tuple[float, str, dict]:
    """Seconds for one run (``rounds`` of attack, 0 for a clean run), its ticks.csv and what
    the attack tallied (:func:`tests.test_limits.attack_counts`)."""
    endpoint = free_tcp_endpoint()
    stop, counts = threading.Event(), attack_counts()
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryDirectory() as secrets:
        credentials = RunCredentials.create(Path(secrets) / "run", config.followers)
        attacker = threading.Thread(target=attack, args=(
            endpoint, config.run_id, credentials.passwords["follower-1"], rounds, stop, counts))
        if rounds:
            attacker.start()
        start = time.perf_counter()
        try:
            summary = launch(config, tmp, in_process=True, endpoint=endpoint,
                             credentials=credentials)
        finally:
            stop.set()
            if rounds:
                attacker.join(timeout=120)
        elapsed = time.perf_counter() - start
        if not summary["complete"]:
            raise RuntimeError(f"run incomplete: {summary['reason']}")
        return elapsed, (Path(tmp) / "ticks.csv").read_text(), counts


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--ticks", type=int, default=40)
    p.add_argument("--rounds", type=int, default=ATTACK_ROUNDS)
    args = p.parse_args()
    config = RunConfig(run_id="bench-attack", surface="wavy", followers=2, ticks=args.ticks)
    clean, attacked, same, tallies = [], [], True, []
    for _ in range(args.repeats):
        seconds, reference, _ = timed_run(config, 0)
        clean.append(seconds)
        seconds, ticks, counts = timed_run(config, args.rounds)
        attacked.append(seconds)
        same &= ticks == reference
        tallies.append(counts)
    ratio = statistics.median(attacked) / statistics.median(clean)
    print(f"run: wavy, 2 followers, {args.ticks} ticks, in-process; attack: {args.rounds} rounds "
          f"({3 * args.rounds} queries, {4 * args.rounds} samples as follower 1: 512 KiB deep, "
          f"wide and long-string payloads, 4 KiB nests, 9 MB ones)")
    for name, times in (("clean", clean), ("attacked", attacked)):
        print(f"{name:>8} s: {' '.join(f'{x:.2f}' for x in times)}  "
              f"median {statistics.median(times):.2f}")
    print(f"ratio {ratio:.2f} (target <= {TARGET}); ticks.csv identical: {same}")
    # the attacker stops at a query the world no longer answers (the run ended under it)
    print("per attacked run: queries answered / refused / left unanswered, samples sent: "
          + "; ".join(f"{c['answered']} / {len(c['refusals'])} / {len(c['unanswered'])}, "
                      f"{c['samples']}" for c in tallies))


if __name__ == "__main__":
    main()
