"""Test support: bounded waits. Every wait of the tests for something to happen polls with a
deadline, so a test that waits for what never comes fails instead of hanging."""
from __future__ import annotations

import time
from collections.abc import Callable

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
