"""Command-line plumbing every process shares: the ``--log-level`` flag, the results-folder
check and the one line that describes a failure (never a traceback, never a Rust source path).
"""
from __future__ import annotations

import argparse
import logging
import os
import re
import tempfile
from pathlib import Path

import zenoh

from protocol.limits import MAX_TEXT

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
EXPECTED_FAILURES = (ValueError, RuntimeError, OSError, zenoh.ZError)
"""What a command reports as one line: bad input, a failed run, a file system or Zenoh error."""

# Zenoh's errors end with the Rust source location they were raised at.
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_ENDPOINT_WRAPPER = re.compile(r"\bSingle\(([^()]*)\)")


def add_log_level_flag(parser: argparse.ArgumentParser) -> None:
    """``--log-level`` (case-insensitive); argparse refuses any other value with usage."""
    parser.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS, default="WARNING",
                        metavar="LEVEL", help=f"one of {', '.join(LOG_LEVELS)} (default WARNING)")


def setup_logging(level: str) -> None:
    """Log to stderr at ``level`` (one of ``LOG_LEVELS``)."""
    logging.basicConfig(level=level, format="%(asctime)s %(name)s: %(message)s")


def describe(exc: BaseException) -> str:
    """One line for an expected failure (see ``EXPECTED_FAILURES``).

    >>> describe(OSError(28, "No space left on device", "runs/x/ticks.csv"))
    'No space left on device: runs/x/ticks.csv'
    >>> describe(zenoh.ZError("Cannot reach [Single(tcp/1.2.3.4:7447)]! at /r/x.rs:9."))
    'Zenoh: Cannot reach [tcp/1.2.3.4:7447]!'
    """
    if isinstance(exc, zenoh.ZError):
        text = _ENDPOINT_WRAPPER.sub(r"\1", _RUST_LOCATION.sub("", str(exc)))
        return "Zenoh: " + _one_line(text)
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror + (f": {exc.filename}" if exc.filename else "")
    return _one_line(str(exc)) or type(exc).__name__


def check_out_dir(path: str | os.PathLike[str], flag: str = "--out") -> Path:
    """Make sure ``path`` is, or can be created as, a folder this process can write into.

    Raises ValueError (naming ``flag`` and the reason) when ``path`` is a file, cannot be
    created (e.g. under ``/proc``), is not writable (read-only or full file system), or is too
    long or unprintable to be announced in the run's ``done`` message.
    """
    path = Path(path)
    text = str(path)
    if len(text) > MAX_TEXT or not text.isprintable():
        raise ValueError(f"{flag} must be a printable path of at most {MAX_TEXT} characters")
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path} is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path, prefix=".write-check.")
        try:
            os.write(fd, b"\n")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise ValueError(f"{flag} {path} cannot hold results: {describe(exc)}") from None
    return path


def _one_line(text: str) -> str:
    return " ".join(text.split())
