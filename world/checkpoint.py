"""The world's checkpoint: ``world_state.json``, describing only complete ticks (design §4).

After every complete tick the world first appends the tick to ``ticks.csv``,
``observations.csv`` and (a drive run) ``controls.csv``, then replaces this file atomically.
It holds the simulation state after that tick, the CSV files' lengths at that point, the run
id, the run's *start nonce* (random per fresh start, kept across resumes: agents' state files
must carry the same one) and a SHA-256 checksum. A world killed at any moment — even halfway
through appending a tick — resumes from the last tick this file describes, cutting the CSV
files back to the lengths it records. The file is deleted once the run is complete.
"""
from __future__ import annotations

import json
import secrets
from pathlib import Path

from protocol.cli import Refused
from protocol.config import checked_json, json_checksum
from protocol.folder import write_atomic
from protocol.record import RESULT_FILES, SUMMARY_FILE

STATE_FILE = "world_state.json"
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
    write_atomic(out_dir / STATE_FILE, json.dumps({**body, "sha256": json_checksum(body)}) + "\n")


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
    present = [name for name in (*RESULT_FILES, STATE_FILE) if (out_dir / name).exists()]
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
    """The run is complete: its checkpoint is no longer needed."""
    (out_dir / STATE_FILE).unlink(missing_ok=True)
