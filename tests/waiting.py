"""Test support: bounded waits, and the processes they watch. Every wait of the tests for
something to happen polls with a deadline, so a test that waits for what never comes fails
instead of hanging."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

POLL_S = 0.05
ROOT = Path(__file__).resolve().parents[1]


def until(condition: Callable[[], object], timeout: float) -> bool:
    """Poll ``condition`` until it holds (True) or ``timeout`` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(POLL_S)
    return False


def wait_for(condition: Callable[[], object], timeout: float, what: str) -> None:
    """:func:`until`, failing the test (naming ``what``) when ``timeout`` passes first."""
    if not until(condition, timeout):
        raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def ticks_done(out: Path) -> int:
    """The ticks the summary in results folder ``out`` says are complete (0 while it is
    missing or being written)."""
    try:
        return json.loads((out / "summary.json").read_text())["ticks_completed"]
    except (OSError, ValueError, KeyError):
        return 0


def stat_fields(pid: int) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the command name (state, parent, ...); None if
    there is no such process."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


STARTED = 19  # the start time's place in stat_fields: with the pid, it names one process


def running(pid: int, started: str | None = None) -> bool:
    """Whether process ``pid`` exists and is not a zombie (ended, not yet reaped) — and, given
    its ``started`` time (:func:`identified`), is still that process: on a busy machine the
    kernel hands an ended process's number to a new process or thread within seconds."""
    fields = stat_fields(pid)
    return fields is not None and fields[0] != "Z" and started in (None, fields[STARTED])


def identified(pids: list[int]) -> dict[int, str]:
    """Each process of ``pids`` that exists, with its start time (for :func:`running`)."""
    return {pid: fields[STARTED] for pid in pids if (fields := stat_fields(pid)) is not None}


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    return [int(entry.name) for entry in Path("/proc").iterdir() if entry.name.isdigit()
            and (fields := stat_fields(int(entry.name))) is not None and int(fields[1]) == pid]


def signalled(proc: subprocess.Popen, signum: int, timeout: float) -> tuple[int, str, str]:
    """Send ``signum`` to ``proc``, wait up to ``timeout`` s for it to end and return its
    status and output; a process that outlives the wait is killed (and the test fails)."""
    try:
        proc.send_signal(signum)
        code = proc.wait(timeout=timeout)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    return code, out, err


class Procs:
    """Processes a test starts (from the repository's root, output captured as text); on
    :meth:`close` whatever still runs is killed and reaped."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, cmd: list[str], **kwargs) -> subprocess.Popen:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, **kwargs)
        self.procs.append(proc)
        return proc

    def python(self, *args: str, **kwargs) -> subprocess.Popen:
        """``python ARGS`` with this interpreter."""
        return self.start([sys.executable, *args], **kwargs)

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=10)
