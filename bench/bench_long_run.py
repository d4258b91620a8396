"""Does a long run's tick cost what its first ticks cost? ``python bench/bench_long_run.py``

Runs one noisy case with follower processes over Zenoh (3 followers, σ 0.02/0.01, actuation
0.01, seed 1, ``--estimator``, default ``persist``; ``--ticks`` long) and samples it every
``--every`` seconds from outside: the ticks its ``summary.json`` counts complete, the CPU time
(user and system, from ``/proc``) of the world's process (``swarm run`` hosts it) and of the
agents' processes, and the world's resident memory. Per window it prints the wall time per
tick, the CPU per tick of the world and of the agents, and the world's and the largest agent's
memory; then the last window against the first. With ``--checkout DIR`` it runs another
checkout (``git worktree add /tmp/old COMMIT``), with this interpreter. The run is stopped
after ``--seconds``. Nothing here is asserted: a shared machine's load moves the wall times,
less so the CPU per tick.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(HERE))

from tests.waiting import children, stat_fields, ticks_done  # noqa: E402

CASE = ["--followers", "3", "--noise-range", "0.02", "--noise-bearing", "0.01", "--noise-move",
        "0.01", "--seed", "1"]
TICK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def _cpu(pid: int) -> float:
    """User and system CPU of process ``pid`` so far (s), 0 once it is gone."""
    fields = stat_fields(pid)
    return 0.0 if fields is None else (int(fields[11]) + int(fields[12])) / TICK


def _rss(pid: int) -> float:
    """Resident memory of process ``pid`` (MiB)."""
    try:
        return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE / 2**20
    except OSError:
        return 0.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkout", type=Path, default=HERE, help="the checkout to run")
    p.add_argument("--ticks", type=int, default=40000, help="the run's length (it is stopped "
                   "after --seconds anyway)")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--every", type=float, default=10.0, help="window length (s)")
    p.add_argument("--estimator", default="persist")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        env = {**os.environ, "PYTHONPATH": str(args.checkout)}
        command = [sys.executable, "-m", "swarm", "run", *CASE, "--ticks", str(args.ticks),
                   "--estimator", args.estimator, "--out", str(out)]
        proc = subprocess.Popen(command, cwd=args.checkout, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        agents: set[int] = set()
        try:
            while ticks_done(out) < 10 and proc.poll() is None:
                time.sleep(0.2)
            windows = []
            start = time.monotonic()

            def sample() -> tuple[float, int, float, float, float, float]:
                agents.update(children(proc.pid))
                return (time.monotonic(), ticks_done(out), _cpu(proc.pid),
                        sum(_cpu(a) for a in agents), _rss(proc.pid),
                        max((_rss(a) for a in agents), default=0.0))

            last = sample()
            while time.monotonic() - start < args.seconds and proc.poll() is None:
                time.sleep(args.every)
                now = sample()
                if now[1] > last[1]:
                    windows.append((last, now))
                last = now
        finally:
            agents.update(children(proc.pid))
            proc.kill()
            proc.wait()
            for agent in agents:  # its agents, which would wait for a world that is gone
                try:
                    os.kill(agent, 9)
                except ProcessLookupError:
                    pass
    print(f"checkout {args.checkout}: {CASE[1]} followers, {args.estimator}, σ 0.02/0.01, "
          "processes")
    print("ticks          wall ms/tick  world CPU ms/tick  agents CPU ms/tick  world RSS MiB"
          "  largest agent RSS MiB")
    for a, b in windows:
        n = b[1] - a[1]
        print(f"{a[1]:5d}-{b[1]:<6d}  {1000 * (b[0] - a[0]) / n:12.2f}  "
              f"{1000 * (b[2] - a[2]) / n:17.2f}  {1000 * (b[3] - a[3]) / n:18.2f}  "
              f"{b[4]:13.1f}  {b[5]:21.1f}")
    if len(windows) >= 2:
        (a0, b0), (a1, b1) = windows[0], windows[-1]
        first = (b0[2] - a0[2]) / (b0[1] - a0[1])
        final = (b1[2] - a1[2]) / (b1[1] - a1[1])
        wall0 = (b0[0] - a0[0]) / (b0[1] - a0[1])
        wall1 = (b1[0] - a1[0]) / (b1[1] - a1[1])
        print(f"last window / first: wall per tick {wall1 / wall0:.2f}, world CPU per tick "
              f"{final / first:.2f}, world memory {b1[4] / b0[4]:.2f}, largest agent's memory "
              f"{b1[5] / b0[5]:.2f}")


if __name__ == "__main__":
    main()
