"""A follower's own state as data: a replay log of what its policy learnt from, tick by tick.

Policies change state only in ``learn(settled, target, before)`` and ``skip()`` and are
deterministic functions of that call sequence (``propose`` is a pure read). So instead of saving
estimator internals, a follower appends one line per tick to ``<state_dir>/agent-<id>.state`` —
the settled sensing it recorded, the target, what it sensed and did before settling, and how
many ticks it skipped before — and a
restarted follower rebuilds its policy by replaying the lines. Nothing in the file is code:
it is JSON, every sensing map is validated by the protocol codec, and nothing is ever
unpickled. Replaying also lets the follower roll back to any earlier tick, which is what
transparent recovery needs when the world restarts a tick (design §4).

The file is JSON lines. The first line is the header ``{"schema", "run_id", "agent",
"start"}``; ``start`` is the world's per-start nonce, so a file from another start of the same
run id is refused. Every line carries ``"sum"``, the SHA-256 of its canonical JSON without
that key (:func:`protocol.config.json_checksum`, as for the world's checkpoint). A torn last
line (a crash in the middle of an append: no final newline) is dropped, since its tick was
never reported to anyone; any other defect refuses the whole file with one line naming the
file and the reason (:class:`StateLogError`).
"""
from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents.policies.base import Before
from protocol.config import checked_line, checked_lines
from protocol.folder import AppendFile, write_atomic
from protocol.messages import ProtocolError, Sensing, from_body, to_body

SCHEMA = 2  # 2: each tick also holds what came before the settled sensing
MAX_LINE = 16384  # bytes; a real line is a few hundred


class StateLogError(RuntimeError):
    """A state file this follower refuses to use; the message names the file and why."""


@dataclass(frozen=True)
class Entry:
    """One tick of a follower's history: ``skips`` ticks passed without it before ``tick``;
    at ``tick`` it recorded ``settled`` with ``target`` and ``before`` (:class:`Before`; all
    None: it missed the tick)."""

    tick: int
    skips: int
    settled: Sensing | None
    target: tuple[float, float] | None
    before: Before | None = None

    def body(self) -> dict:
        before = self.before
        return {"tick": self.tick, "skips": self.skips,
                "settled": None if self.settled is None else to_body(self.settled),
                "target": None if self.target is None else [float(x) for x in self.target],
                "before": None if before is None else {
                    "pre": to_body(before.pre),
                    "moved": None if before.moved is None else to_body(before.moved),
                    "offset": [float(x) for x in before.offset]}}


def state_path(state_dir: str | os.PathLike[str], agent: int) -> Path:
    return Path(state_dir) / f"agent-{agent}.state"



class StateLog:
    """The replay log of follower ``agent`` in run ``run_id``, start ``start``.

    Use :meth:`open` (validates an existing file, or starts a new one).
    """

    def __init__(self, path: Path, header: dict) -> None:
        self.path, self.header = path, header

    @classmethod
    def open(cls, state_dir: str | os.PathLike[str], run_id: str, agent: int,
             start: str) -> tuple[StateLog, list[Entry]]:
        """The log and its entries (none for a new file). Raises :class:`StateLogError`."""
        path = state_path(state_dir, agent)
        header = {"schema": SCHEMA, "run_id": run_id, "agent": agent, "start": start}
        log = cls(path, header)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            log.rewrite([])
            return log, []
        except OSError as exc:
            raise StateLogError(f"state file {path}: cannot read it ({exc.strerror})") from None
        return log, log._parse(raw)

    def _refuse(self, why: str) -> StateLogError:
        return StateLogError(f"state file {self.path}: {why}; refusing it (remove the file to "
                          "start this follower afresh, losing its history)")

    def _parse(self, raw: bytes) -> list[Entry]:
        try:  # a torn last append: that tick was never reported, forget it
            bodies = checked_lines(raw, MAX_LINE)
        except ValueError as exc:
            raise self._refuse(str(exc)) from None
        if not bodies:
            raise self._refuse("it is empty (no header)")
        header = bodies[0]
        for key in ("schema", "run_id", "agent", "start"):
            if header.get(key) != self.header[key]:
                raise self._refuse(f"its {key} is {header.get(key)!r}, this follower's is "
                                   f"{self.header[key]!r} (a file of another run, start or agent)")
        entries: list[Entry] = []
        for number, body in enumerate(bodies[1:], start=2):
            try:
                entry = _entry(body)
            except (ProtocolError, ValueError, TypeError) as exc:
                raise self._refuse(f"line {number}: {exc}") from None
            before = entries[-1].tick if entries else -1
            if entry.tick != before + 1 + entry.skips:  # every tick accounted for
                raise self._refuse(f"line {number}: tick {entry.tick} after tick {before} with "
                                   f"{entry.skips} skipped (a line is missing or out of place)")
            entries.append(entry)
        return entries

    def append(self, entry: Entry) -> None:
        """Add one tick (written before the tick is reported to anyone), whole or not at all:
        a failed write is cut back to the previous line before the error is raised."""
        log = AppendFile(self.path)
        try:
            log.append(checked_line(entry.body()).encode("utf-8"))
        finally:
            log.close()

    def rewrite(self, entries: list[Entry]) -> None:
        """Replace the file atomically with the header and ``entries`` (a rollback)."""
        write_atomic(self.path, checked_line(self.header)
                     + "".join(checked_line(e.body()) for e in entries))

    def remove(self) -> None:
        """Delete the log (its run is complete), and its folder if that leaves it empty: the
        last follower to finish removes the folder the first one created."""
        self.path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):  # others' logs still in it, a mount point, gone
            self.path.parent.rmdir()


def _pair(value, name: str) -> tuple[float, float]:
    if (not isinstance(value, list) or len(value) != 2
            or not all(type(x) is float and math.isfinite(x) for x in value)):
        raise ValueError(f"{name} must be two finite floats, got {value!r}")
    return value[0], value[1]


def _before(body) -> Before | None:
    if body is None:
        return None
    if not isinstance(body, dict) or set(body) != {"pre", "moved", "offset"}:
        raise ValueError("before must be a map of pre, moved, offset")
    moved = None if body["moved"] is None else from_body(body["moved"], Sensing)
    return Before(pre=from_body(body["pre"], Sensing), moved=moved,
                  offset=_pair(body["offset"], "offset"))


def _entry(body: dict) -> Entry:
    if set(body) != {"tick", "skips", "settled", "target", "before"}:
        raise ValueError(f"fields {sorted(body)} are not tick, skips, settled, target, before")
    tick, skips = body["tick"], body["skips"]
    for name, value in (("tick", tick), ("skips", skips)):
        if type(value) is not int or not 0 <= value <= 10_000_000:
            raise ValueError(f"{name} must be an integer in 0..1e7, got {value!r}")
    settled = None if body["settled"] is None else from_body(body["settled"], Sensing)
    target = None if body["target"] is None else _pair(body["target"], "target")
    before = _before(body["before"])
    if settled is None and (target is not None or before is not None):
        raise ValueError("a target or earlier readings without a settled sensing")
    return Entry(tick=tick, skips=skips, settled=settled, target=target, before=before)


def replay(policy, entries: list[Entry]) -> None:
    """Feed ``entries`` to a fresh ``policy``: it ends in the state it had after the last one.

    Every tick that passed without the follower settling — the ``skips`` before an entry, and
    the entry's own tick when it missed it (``settled`` None) — is bridged by ``policy.skip()``,
    as the follower's loop did live (:func:`agents.follower.run_follower`): the leader moved on
    in it, so the next reading is two ticks after the last one learnt from, not one."""
    for entry in entries:
        for _ in range(entry.skips):
            policy.skip()
        if entry.settled is None:
            policy.skip()
        else:
            target = None if entry.target is None else np.asarray(entry.target, dtype=float)
            policy.learn(entry.settled, target, entry.before)
