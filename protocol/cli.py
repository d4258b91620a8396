"""Command-line plumbing every process shares: the ``--log-level`` flag, the one line that
describes a failure (never a traceback, never a Rust source path) and
the exit status of every command (design §9: 0 done, 1 failed or incomplete, 2 refused before
anything ran, 130/143 after Ctrl-C/SIGTERM), given in one place (:func:`run_command`).
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import zenoh

from protocol.distribution import MissingExtra

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
EXPECTED_FAILURES = (ValueError, RuntimeError, OSError, zenoh.ZError)
"""What a command reports as one line: bad input, a failed run, a file system or Zenoh error."""

# Zenoh's errors end with the Rust source location they were raised at.
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_ENDPOINT_WRAPPER = re.compile(r"\bSingle\(([^()]*)\)")


DONE, FAILED, REFUSED, INTERRUPTED = 0, 1, 2, 130
"""Exit statuses: done; the run failed or ended incomplete; the command line or configuration
was refused before anything ran; Ctrl-C (SIGTERM gives 143, see :func:`bounded_interrupt`)."""


class CommandError(Exception):
    """Ends a command with one line (``error: <message>``) and ``status``, no traceback."""

    def __init__(self, message: str, status: int) -> None:
        super().__init__(message)
        self.status = status


def refuse(message: str) -> NoReturn:
    """End the command: its command line or configuration is refused (status 2)."""
    raise CommandError(message, REFUSED)


def fail(message: str) -> NoReturn:
    """End the command: what it ran failed or ended incomplete (status 1)."""
    raise CommandError(message, FAILED)


@contextlib.contextmanager
def ends_with(status: int, *kinds: type[BaseException]) -> Iterator[None]:
    """Within the block, an exception of ``kinds`` ends the command with ``status`` and the
    exception's one-line description (:func:`describe`)."""
    try:
        yield
    except kinds as exc:
        raise CommandError(describe(exc), status) from None


def exit_process(status: int) -> NoReturn:
    """End this process with ``status`` once its command is over (every entry point's last
    step), without the interpreter's finalisation: Zenoh's runtime threads outlive the
    sessions a command closed, and one that drops a closed session's Python callback while the
    interpreter finalises takes the GIL too late and aborts the process ("FATAL: exception not
    rethrown", status -6) after the command has reported its result (seen under load after a
    full disk ended an in-process run). By then every file the command wrote is closed and every
    child process ended (each command does so itself); stdio and logging are flushed here."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def run_command(command: Callable[[], int | None]) -> int:
    """Run a command's body and return its exit status: its own (None is 0), or for a
    :class:`CommandError` the error's, printed as one line (a missing extra is refused, 2);
    Ctrl-C gives 130 and SIGTERM 143
    once the cleanup is done (:func:`bounded_interrupt`)."""
    with bounded_interrupt():
        try:
            return command() or DONE
        except CommandError as exc:
            print(f"error: {exc}", file=sys.stderr, flush=True)
            return exc.status
        except MissingExtra as exc:  # a feature whose extra is not installed: refused
            print(f"error: {exc}", file=sys.stderr, flush=True)
            return REFUSED
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr, flush=True)
            return INTERRUPTED


class Refused(ValueError):
    """Input refused before anything ran (exit status 2 in every command): e.g. a results
    folder another run writes into, or a raster larger than the limit."""


@contextlib.contextmanager
def run_failures(out: str | os.PathLike[str]) -> Iterator[None]:
    """Within the block (a run writing its results into ``out``), end the command as a run
    ends: :class:`Refused` input is refused (status 2, nothing was written); an ``OSError``
    is the results disk failing during the run (read-only, full) and any other of
    ``EXPECTED_FAILURES`` a failed run (both status 1)."""
    try:
        yield
    except Refused as exc:
        refuse(describe(exc))
    except OSError as exc:
        fail(f"cannot write the results in {out}: {describe(exc)}")
    except EXPECTED_FAILURES as exc:
        fail(describe(exc))


class NewFolder:
    """The results folder ``path`` of a command that may make it, with whatever missing
    parents: :meth:`discard` removes what the command made, so that a refused command, or a
    run that ended before its first tick, leaves nothing behind (design §9).

    Only what did not exist when the command started is removed: with ``run_id`` (a run's
    folder) the whole folder, once its one-writer lock is taken (a folder another writer holds
    is left alone); without, only its empty folders (a grid's, whose runs are kept). The new
    parents go only if empty (another run may have put its folder beside).
    """

    def __init__(self, path: str | os.PathLike[str], run_id: str | None = None) -> None:
        self.run_id = run_id
        self.path = path = Path(path).absolute()
        self.top: Path | None = None  # the topmost folder that does not exist yet
        while not os.path.lexists(path):
            self.top, path = path, path.parent

    @property
    def made(self) -> bool:
        """Whether the command made (or is to make) the folder."""
        return self.top is not None

    def discard(self) -> None:
        """Remove what the command made (nothing if it found the folder there)."""
        from protocol.folder import FolderLock

        top = self.top
        if top is None or top.is_symlink() or not top.is_dir():
            return
        if self.run_id is not None:
            if not self.path.is_dir() or self.path.is_symlink():
                return
            try:
                with FolderLock(self.path, self.run_id):
                    shutil.rmtree(self.path, ignore_errors=True)
            except (Refused, OSError):  # another writer holds it now: not ours to remove
                return
        else:  # a grid's: its empty folders, deepest first
            for folder, _, _ in sorted(os.walk(self.path), key=lambda entry: -len(entry[0])):
                with contextlib.suppress(OSError):
                    os.rmdir(folder)
        folder = self.path
        while folder != top.parent:  # then the parents it made, while they are empty
            try:
                os.rmdir(folder)
            except FileNotFoundError:  # gone already
                pass
            except OSError:
                return
            folder = folder.parent

    @contextlib.contextmanager
    def undone_if_refused(self) -> Iterator[NewFolder]:
        """Within the block, a refusal (status 2, or a missing extra) discards the folder."""
        try:
            yield self
        except CommandError as exc:
            if exc.status == REFUSED:
                self.discard()
            raise
        except (MissingExtra, Refused):
            self.discard()
            raise


INTERRUPT_GRACE_S = 8.0
"""Seconds a process may spend cleaning up after Ctrl-C or SIGTERM before it exits regardless."""
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Ctrl-C, and the stop a supervisor sends (``docker stop``, systemd, Slurm, ``kill``)."""


@contextlib.contextmanager
def bounded_interrupt(grace: float = INTERRUPT_GRACE_S) -> Iterator[None]:
    """Within the block, Ctrl-C and SIGTERM raise ``KeyboardInterrupt``, so every cleanup runs
    (the partial summary, agents stopped, sessions closed, temporary credentials removed), and
    the process exits at the latest ``grace`` seconds later, whatever a cleanup is still
    waiting on: a Zenoh teardown (undeclaring, closing a session) can wedge, and an operator's
    Ctrl-C or a supervisor's stop must still end the run. Nothing written is lost by that exit:
    results are appended and checkpointed tick by tick.

    The status is the shell's for the signal, ``128 + signum``: after Ctrl-C 130 (as the
    commands return themselves), after SIGTERM 143, once the cleanup is done. A second signal
    acts at once (Ctrl-C raises again, SIGTERM kills). Outside the main thread this does
    nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    deadline: list[threading.Timer] = []
    received: list[int] = []

    def interrupted(signum, frame) -> None:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        received.append(signum)
        timer = threading.Timer(grace, _exit_interrupted, args=(grace, 128 + signum))
        timer.daemon = True
        timer.start()
        deadline.append(timer)
        raise KeyboardInterrupt

    for sig in STOP_SIGNALS:
        signal.signal(sig, interrupted)
    try:
        yield
    finally:
        for timer in deadline:  # the cleanup finished in time
            timer.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if signal.SIGTERM in received:  # terminated, whatever the command made of it
            raise SystemExit(128 + signal.SIGTERM)


@contextlib.contextmanager
def stops_deferred() -> Iterator[None]:
    """Within the block, Ctrl-C and SIGTERM wait: they are delivered, to whatever handles them
    outside, once it is done. For a step that must not be cut in half — spawning a child
    process and keeping its handle, so that the cleanup can end it (a stop arriving between
    the two left an agent running after ``swarm run`` exited). Outside the main thread this
    does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: held.append(signum))
                for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(held):
            signal.raise_signal(sig)


def _exit_interrupted(grace: float, status: int) -> None:
    sys.stderr.write(f"interrupted: cleanup still running after {grace:g} s; exiting\n")
    sys.stderr.flush()
    os._exit(status)


class Parser(argparse.ArgumentParser):
    """An argument parser whose refusal of a command line is one line (design §9: status 2),
    ``PROG: error: MESSAGE (PROG --help lists the options)``, not the usage block first.
    Its subcommands' parsers are of the same class."""

    def error(self, message: str) -> NoReturn:
        self.exit(REFUSED, f"{self.prog}: error: {_one_line(message)} "
                           f"({self.prog} --help lists the options)\n")

    def parse_known_args(self, args=None, namespace=None):
        parsed, extra = super().parse_known_args(args, namespace)
        if not hasattr(parsed, "_page"):  # the deepest subcommand's parser sets it first
            parsed._page = self
        return parsed, extra

    def parse_args(self, args=None, namespace=None):
        """As argparse's, but arguments no parser knows are refused by the page of the
        subcommand they were given to (``python -m swarm experiment paper: error: ...``)."""
        parsed, extra = self.parse_known_args(args, namespace)
        page = vars(parsed).pop("_page", self)
        if extra:
            page.error(f"unrecognized arguments: {' '.join(extra)}")
        return parsed


def program(module: str, script: str) -> str:
    """How a command names itself in its usage and errors: the installed ``script`` (e.g.
    ``swarm-follower``) when started as it, else ``python -m module``."""
    return script if Path(sys.argv[0]).name == script else f"python -m {module}"


def add_log_level_flag(parser: argparse.ArgumentParser) -> None:
    """``--log-level`` (case-insensitive); argparse refuses any other value with usage."""
    parser.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS, default="WARNING",
                        metavar="LEVEL", help=f"one of {', '.join(LOG_LEVELS)} [default WARNING]")


def default_out(run_id: str) -> Path:
    """The results folder of run ``run_id`` when a command is given no ``--out``."""
    return Path("runs") / run_id


def add_results_flags(parser: argparse.ArgumentParser) -> None:
    """``--out`` (default :func:`default_out`) and ``--force`` of a command that runs a run."""
    parser.add_argument("--out", help=f"results folder [default {default_out('<run_id>')}]")
    parser.add_argument("--force", action="store_true",
                        help="replace the results already in --out [default refuse]")


def quantity(value: Any, unit: str) -> str:
    """``value`` and its unit, a counted word in the singular for one.

    >>> quantity(1, "agents"), quantity(3, "followers"), quantity(1.0, "m/s")
    ('1 agent', '3 followers', '1.0 m/s')
    """
    if str(value) == "1" and unit.isalpha() and unit.endswith("s"):
        unit = unit[:-1]
    return f"{value} {unit}" if unit else str(value)


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


def _one_line(text: str) -> str:
    return " ".join(text.split())
