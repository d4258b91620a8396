"""The world's checkpoint: ``world_state.json``, describing only complete ticks (design §4).

After every complete tick the world first appends the tick to ``ticks.csv``,
``observations.csv`` and (a drive run) ``controls.csv``, then replaces this file atomically.
It holds the simulation state after that tick, the CSV files' lengths at that point, the run
id, the run's *start nonce* (random per fresh start, kept across resumes: agents' state files
must carry the same one) and a SHA-256 checksum. A world killed at any moment — even halfway
through appending a tick — resumes from the last tick this file describes, cutting the CSV
files back to the lengths it records. The file is deleted once the run is complete.

**The request journal** (``world_requests.jsonl``) holds what the world answered in the ticks
after the checkpoint. A tick the resumed world runs again draws the same noise, so an agent
redoing it must ask what it asked the first time (design §5): were the world to forget what it
answered, an agent could redo a tick from another pose, read the same draws there and cancel
them. Each sensing and action is appended (one checksummed JSON line, written before the
answer leaves the world) with its agent, tick and place in the tick; the ticks a checkpoint
covers are left out when it is read, and dropped from the file every few hundred lines; a
resumed world reads it back
(:meth:`world.sim.WorldSim.expect_redo`). A torn last line was never answered and is dropped.
The journal goes with the checkpoint: deleted once the run is complete.
"""

from __future__ import annotations

import errno
import json
import secrets
from pathlib import Path

from protocol.cli import Refused
from protocol.config import (
    canonical_json,
    checked_canonical,
    checked_json,
    checked_line,
    checked_lines,
    checked_text,
)
from protocol.folder import AppendFile, write_atomic
from protocol.messages import ACTIONS, ProtocolError, from_body, to_body
from protocol.record import RESULT_FILES, SUMMARY_FILE

STATE_FILE = "world_state.json"
JOURNAL_FILE = "world_requests.jsonl"
MAX_JOURNAL_LINE = 4096  # bytes; a real line is a few hundred
TRIM_LINES = 512  # lines of checkpointed ticks the journal may hold before it is rewritten
SCHEMA = 2  # 2: a driving follower's summed odometry errors are in the sim state


class StateError(Refused):
    """A checkpoint or results folder the world refuses before anything ran (exit status 2);
    the message names the file and why."""


class AlreadyComplete(StateError):
    """``--resume`` of a run that completed: nothing is left to do."""


def new_start() -> str:
    """A fresh start nonce."""
    return secrets.token_hex(8)


def save(out_dir: Path, *, run_id: str, start: str, sim: dict, offsets: dict[str, int],
         wall_time: float) -> None:
    """Replace the checkpoint atomically (after the tick's rows are on disk)."""
    body = {"schema": SCHEMA, "run_id": run_id, "start": start, "sim": sim,
            "offsets": offsets, "wall_time": wall_time}
    write_atomic(out_dir / STATE_FILE, checked_text(body, "sha256") + "\n")


def load(out_dir: Path, run_id: str) -> dict:
    """The checkpoint of run ``run_id`` in ``out_dir``, validated (StateError otherwise)."""
    path = out_dir / STATE_FILE
    if not path.exists():
        if _summary(out_dir).get("complete"):
            raise AlreadyComplete(f"nothing to resume in {out_dir}: the run is complete")
        raise StateError(f"cannot resume {out_dir}: no {STATE_FILE} (nothing to resume from)")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StateError(f"checkpoint {path} is unreadable ({exc}); refusing it") from None
    try:
        body = checked_json(text, "sha256")
    except ValueError as exc:
        raise StateError(f"checkpoint {path} {exc}; refusing it") from None
    if body.get("schema") != SCHEMA:
        raise StateError(f"checkpoint {path} has schema {body.get('schema')!r}, this build "
                         f"reads {SCHEMA}; refusing it")
    if body.get("run_id") != run_id:
        raise StateError(f"checkpoint {path} belongs to run {body.get('run_id')!r}, not "
                         f"{run_id!r}; refusing it")
    for key, kind in (("start", str), ("sim", dict), ("offsets", dict), ("wall_time", float)):
        if not isinstance(body.get(key), kind):
            raise StateError(f"checkpoint {path}: {key!r} missing or not a {kind.__name__}")
    return body


def has_progress(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds a start of a run to resume. A world killed before it wrote its
    first checkpoint recorded nothing, so resuming it is starting it afresh."""
    return (out_dir / STATE_FILE).exists() or (out_dir / SUMMARY_FILE).exists()


def claim(out_dir: Path, force: bool = False) -> None:
    """Make sure a fresh run may write into ``out_dir``: refuse a folder that holds results
    (of any run, this one's earlier start included) unless ``force``, which deletes them."""
    present = [name for name in (*RESULT_FILES, STATE_FILE, JOURNAL_FILE)
               if (out_dir / name).exists()]
    if not present:
        return
    if not force:
        owner = _summary(out_dir).get("run_id", "")
        whose = f"run {owner!r}" if owner else "a run"
        raise StateError(f"{out_dir} already holds results of {whose} ({', '.join(present)}): "
                         "use --resume to continue it, another --out, or --force to replace them")
    for name in present:
        (out_dir / name).unlink()


def _summary(out_dir: Path) -> dict:
    """The results folder's summary, or {} where there is none or it is not a JSON map."""
    try:
        summary = json.loads((out_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return summary if isinstance(summary, dict) else {}


def discard(out_dir: Path) -> None:
    """The run is complete: its checkpoint and journal are no longer needed."""
    (out_dir / STATE_FILE).unlink(missing_ok=True)
    (out_dir / JOURNAL_FILE).unlink(missing_ok=True)


def _request_body(request) -> dict:
    """A request as the world's simulation keeps it (``("sense", look)`` or an action
    message), as JSON."""
    if isinstance(request, tuple):
        return {"sense": request[1]}
    return {"act": to_body(request, check=False)}  # the world decoded it, validated


def _entry_json(agent: int, tick: int, index: int, request) -> str:
    """The canonical JSON (sorted keys, no spaces) of the journal entry ``{"agent", "tick",
    "index", "request": _request_body(request)}``, composed directly: a line per request the
    world answers, so a general encoder's cost counts (ints print as JSON does; an action's
    own map still goes through the encoder)."""
    if isinstance(request, tuple):
        inner = '{"sense":true}' if request[1] else '{"sense":false}'
    else:
        inner = canonical_json(_request_body(request))
    return (f'{{"agent":{int(agent)},"index":{int(index)},"request":{inner},'
            f'"tick":{int(tick)}}}')


def _entry_line(agent: int, tick: int, index: int, request) -> str:
    """One line of the journal: :func:`_entry_json` with its checksum (what
    :func:`protocol.config.checked_lines` reads back)."""
    return checked_canonical(_entry_json(agent, tick, index, request), "sum") + "\n"


def _request(body):
    if isinstance(body, dict) and set(body) == {"sense"} and isinstance(body["sense"], bool):
        return ("sense", body["sense"])
    if isinstance(body, dict) and set(body) == {"act"}:
        return from_body(body["act"], ACTIONS)
    raise ValueError("a request must be a map of sense (a bool) or act (an action)")


class Journal:
    """The request journal of one start of run ``run_id`` in ``out_dir`` (module docstring):
    :meth:`read` it back on a resume, then :meth:`open` it (afresh, with what it kept)."""

    def __init__(self, out_dir: Path, run_id: str, start: str) -> None:
        self.path = Path(out_dir) / JOURNAL_FILE
        self.header = {"schema": SCHEMA, "run_id": run_id, "start": start}
        self._lines: list[tuple[int, str]] = []  # (tick, line) after the last checkpoint
        self._stale = 0  # lines in the file of ticks checkpointed since its last rewrite
        self._file: AppendFile | None = None

    def open(self, kept=()) -> None:
        """Start the file afresh with ``kept`` (agent, tick, index, request) entries."""
        self._lines = [(entry[1], _entry_line(*entry)) for entry in kept]
        self._rewrite()

    def _rewrite(self) -> None:
        """Replace the file with the header and the kept lines; if that fails (a full disk),
        the old file stays, still appended to."""
        lines = "".join(line for _, line in self._lines)
        write_atomic(self.path, checked_line(self.header) + lines)
        self.close()
        self._file, self._stale = AppendFile(self.path), 0

    def add(self, agent: int, tick: int, index: int, request) -> None:
        """Record that the world answers ``agent``'s ``index``-th request of ``tick`` (before
        the answer leaves it)."""
        if self._file is None:  # the world is closing: nothing more is answered
            raise OSError(errno.EBADF, "the journal is closed", str(self.path))
        line = _entry_line(agent, tick, index, request)
        self._file.append(line.encode("utf-8"))
        self._lines.append((tick, line))

    def keep_after(self, tick: int) -> None:
        """Tick ``tick`` is checkpointed: the requests of it and the ticks before are no longer
        needed (:meth:`read` leaves them out). The file is rewritten without them once they
        are the greater part of it and at least :data:`TRIM_LINES`, so its length stays
        bounded at the cost of a rewrite every few hundred requests, not every tick."""
        kept = [(t, line) for t, line in self._lines if t > tick]
        self._stale += len(self._lines) - len(kept)
        self._lines = kept
        if self._stale >= max(TRIM_LINES, len(kept)):
            self._rewrite()

    def read(self, agents: int, after: int) -> list[tuple[int, int, int, object]]:
        """The (agent, tick, index, request) entries of the ticks after ``after``, in the order
        written (none without a file: a world killed before it wrote one). StateError naming
        the file and why if it is damaged, of another run or start, or crafted."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise StateError(f"cannot resume {self.path.parent}: {self.path}: cannot read it "
                             f"({exc.strerror})") from None
        try:
            bodies = checked_lines(raw, MAX_JOURNAL_LINE)
            if not bodies or bodies[0] != self.header:
                raise ValueError("its header is not this run's and start's")
            return [entry for number, body in enumerate(bodies[1:], start=2)
                    if (entry := _entry(body, number, agents))[1] > after]
        except ValueError as exc:
            raise StateError(f"cannot resume {self.path.parent}: {self.path}: {exc}; "
                             "refusing it") from None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def _entry(body: dict, number: int, agents: int) -> tuple[int, int, int, object]:
    if set(body) != {"agent", "tick", "index", "request"} or not all(
            type(body[k]) is int and 0 <= body[k] <= 10_000_000
            for k in ("agent", "tick", "index")) or body["agent"] >= agents:
        raise ValueError(f"line {number} is not an agent's request of a tick")
    try:
        request = _request(body["request"])
    except (ProtocolError, ValueError) as exc:
        raise ValueError(f"line {number}: {exc}") from None
    return body["agent"], body["tick"], body["index"], request


def attempts(entries) -> dict[tuple[int, int], list]:
    """Per (agent, tick), the requests an undone attempt made, in order (a later line at the
    same place, written by a redo, repeats the earlier one)."""
    out: dict[tuple[int, int], dict[int, object]] = {}
    for agent, tick, index, request in entries:
        out.setdefault((agent, tick), {})[index] = request
    return {key: [done[i] for i in sorted(done)] for key, done in out.items()}
