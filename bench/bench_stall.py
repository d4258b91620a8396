"""How long a stall takes to be noticed and recovered from (design §4: a stall is not a death).

``swarm run --processes`` with two followers; once the run has recorded 30 ticks, follower 1
is paused with SIGSTOP for ``--pause`` seconds (longer than Zenoh's 10 s lease), then
continued with SIGCONT. From the logs' timestamps and the results:

- *missed*: realtime, from SIGSTOP to the world's first line that agent 1 missed a tick (at
  the end of that tick's period);
- *dropped*: from SIGSTOP to the world's line that agent 1 vanished (lockstep: its tick is
  rolled back) or is not live (realtime: missed at once from then on), i.e. Zenoh's lease;
- *rejoined*: from SIGCONT to the follower's line that it joins again;
- *progress*: lockstep, from SIGCONT to the first tick the run records after it (the run
  stands still while the follower is away); realtime, ticks from SIGCONT to the first tick
  follower 1 settles in again, times the period (the run never stands still);
- *identical* (lockstep): whether ``ticks.csv`` equals an undisturbed run's (``run_local``).

Run ``python bench/bench_stall.py [--pause 15] [--repeat 2]``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from protocol.config import load_config  # noqa: E402  (after the path set-up)
from protocol.record import read_ticks  # noqa: E402
from swarm.local import run_local  # noqa: E402
from tests.waiting import children, until  # noqa: E402

STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")
MISSED = "agent 1 missed tick"
DROPPED = {"lockstep": "agent 1 vanished during tick", "realtime": "its process is not live"}
REJOINED = "its session to the world was cut and is back"
PERIOD_S = 1.28 * 0.2  # realtime: the comm period at --time-scale 0.2


def ticks_done(out: Path) -> int:
    try:
        return json.loads((out / "summary.json").read_text())["ticks_completed"]
    except (OSError, ValueError, KeyError):
        return 0


def first_stamp(text: str, needle: str, after: float) -> float | None:
    """Wall-clock time (s since the epoch) of the first log line holding ``needle`` stamped
    at or after ``after``."""
    for line in text.splitlines():
        match = STAMP.match(line)
        if match and needle in line:
            when = datetime.strptime(match[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()
            if when >= after - 0.001:
                return when
    return None


def follower_pid(swarm: subprocess.Popen, agent: int) -> int:
    for pid in children(swarm.pid):
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        if b"agents.follower" in args and args[args.index(b"--id") + 1] == str(agent).encode():
            return pid
    raise RuntimeError(f"no process of follower {agent}")


def one_stall(mode: str, pause: float, out: Path) -> dict[str, float | bool | None]:
    flags = (["--ticks", "3000", "--agent-timeout", "40"] if mode == "lockstep" else
             ["--mode", "realtime", "--time-scale", "0.2", "--ticks",
              str(int(30 + (pause + 15) / PERIOD_S))])
    swarm = subprocess.Popen([sys.executable, "-m", "swarm", "run", "--processes",
                              "--followers", "2", *flags, "--out", str(out)], cwd=REPO_ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        if not until(lambda: ticks_done(out) >= 30, 120):
            raise RuntimeError("the run did not reach tick 30")
        pid = follower_pid(swarm, 1)
        stopped = time.time()
        os.kill(pid, signal.SIGSTOP)
        time.sleep(pause)
        at = ticks_done(out)
        continued = time.time()
        os.kill(pid, signal.SIGCONT)
        until(lambda: ticks_done(out) > at, 120)
        progress = time.time() - continued
        _, err = swarm.communicate(timeout=900)
    finally:
        if swarm.poll() is None:
            swarm.kill()
            swarm.communicate()
    agent_log = (out / "logs" / "agent-1.log").read_text()
    missed = first_stamp(err, MISSED, stopped) if mode == "realtime" else None
    dropped = first_stamp(err, DROPPED[mode], stopped)
    rejoined = first_stamp(agent_log, REJOINED, continued)
    result: dict[str, float | bool | None] = {
        "status": swarm.returncode,
        "missed": None if missed is None else missed - stopped,
        "dropped": None if dropped is None else dropped - stopped,
        "rejoined": None if rejoined is None else rejoined - continued,
        "progress": progress,
    }
    if mode == "realtime":
        back = min(r["tick"] for r in read_ticks(out / "ticks.csv")
                   if r["agent"] == 1 and not r["missed"] and r["tick"] > at)
        result["progress"] = (back - at) * PERIOD_S
    else:
        reference = out.parent / f"{out.name}-reference"
        run_local(load_config(out / "config.toml"), reference)
        result["identical"] = all((out / n).read_bytes() == (reference / n).read_bytes()
                                  for n in ("ticks.csv", "observations.csv"))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pause", type=float, default=15.0, help="seconds paused")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    print(f"follower 1 paused {args.pause:g} s after tick 30 (Zenoh lease 10 s)")
    print(f"{'mode':<10}{'status':>7}{'missed s':>10}{'dropped s':>11}{'rejoined s':>12}"
          f"{'progress s':>12}{'identical':>11}")
    with tempfile.TemporaryDirectory() as scratch:
        for n in range(args.repeat):
            for mode in ("lockstep", "realtime"):
                r = one_stall(mode, args.pause, Path(scratch) / f"{mode}-{n}")
                cells = [f"{r[k]:.2f}" if isinstance(r[k], float) else "-"
                         for k in ("missed", "dropped", "rejoined", "progress")]
                print(f"{mode:<10}{r['status']:>7}{cells[0]:>10}{cells[1]:>11}{cells[2]:>12}"
                      f"{cells[3]:>12}{str(r.get('identical', '-')):>11}")


if __name__ == "__main__":
    main()
