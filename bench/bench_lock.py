"""What the one-writer rule costs a run: taking and giving up a results folder's lock
(``protocol.folder.FolderLock``: open the lock file without following links, ``flock``, the
scan for symbolic links, the holder's note), and how fast a second writer is refused.

A run takes the lock once (``swarm run`` before its folder checks, ``python -m world``
otherwise), so the per-run overhead is one acquire and one release. Timed on an empty folder
and on the folder of a finished run with its logs, state and figures (what a resume or a
refused run scans).

Run ``python bench/bench_lock.py [--repeat N]``.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from protocol.folder import FolderBusy, FolderLock  # noqa: E402  (after the path set-up)

HOLD = ("import sys, time\nfrom protocol.folder import FolderLock\n"
        "lock = FolderLock(sys.argv[1], 'holder').acquire()\nprint('held', flush=True)\n"
        "time.sleep(60)\n")


def finished_run(folder: Path, followers: int = 10) -> None:
    """The files a finished run of ``followers`` followers leaves (sizes do not matter)."""
    for name in ("config.toml", "ticks.csv", "observations.csv", "summary.json",
                 "view_map.json"):
        (folder / name).write_text("x\n")
    for sub, names in (("logs", [f"agent-{k}.log" for k in range(followers + 1)]),
                       ("state", [f"agent-{k}.state" for k in range(1, followers + 1)]),
                       ("figures", ["effectiveness.png", "required_range.png"])):
        (folder / sub).mkdir()
        for name in names:
            (folder / sub / name).write_text("x\n")


def time_cycles(folder: Path, repeat: int) -> list[float]:
    """Seconds of each acquire + release."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        FolderLock(folder, "bench").acquire().release()
        times.append(time.perf_counter() - start)
    return times


def time_refusals(folder: Path, repeat: int) -> list[float]:
    """Seconds until a second writer is refused, with the lock held by another process."""
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], cwd=REPO_ROOT,
                              stdout=subprocess.PIPE, text=True)
    try:
        if holder.stdout.readline() != "held\n":
            raise RuntimeError("the holder did not take the lock")
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            try:
                FolderLock(folder, "second").acquire()
            except FolderBusy:
                times.append(time.perf_counter() - start)
            else:
                raise RuntimeError("the second writer was not refused")
        return times
    finally:
        holder.kill()
        holder.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=2000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        empty, full = Path(scratch) / "empty", Path(scratch) / "finished"
        empty.mkdir()
        full.mkdir()
        finished_run(full)
        print(f"{'case':<42}{'median µs':>10}{'mean µs':>10}{'max µs':>10}")
        for label, times in (
                ("acquire + release, empty folder", time_cycles(empty, args.repeat)),
                ("acquire + release, finished run (10 f.)", time_cycles(full, args.repeat)),
                ("second writer refused (holder alive)",
                 time_refusals(full, max(args.repeat // 10, 10)))):
            us = [t * 1e6 for t in times]
            print(f"{label:<42}{statistics.median(us):>10.0f}{statistics.fmean(us):>10.0f}"
                  f"{max(us):>10.0f}")


if __name__ == "__main__":
    main()
