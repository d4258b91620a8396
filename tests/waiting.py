"""Test support: bounded waits. Every wait of the tests for something to happen polls with a
deadline, so a test that waits for what never comes fails instead of hanging."""
from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

POLL_S = 0.05


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


def running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (ended, not yet reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


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
