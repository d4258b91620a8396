"""A follower's own checkpoint of its estimator state, so a killed process loses no history.

After every tick the follower pickles its policy (all estimator history) with the run id, its
id and the tick, to ``<state_dir>/agent-<id>.ckpt`` via a temporary file and a rename. A
restarted follower with the same id loads it and goes on. The file is the agent's own: it is
never read from anywhere else (pickle must not load untrusted files).
"""
from __future__ import annotations

import os
import pickle
import tempfile
from dataclasses import dataclass
from pathlib import Path

from agents.policies import Policy


@dataclass
class Checkpoint:
    run_id: str
    agent: int
    tick: int
    policy: Policy


def checkpoint_path(state_dir: str | os.PathLike[str], agent: int) -> Path:
    return Path(state_dir) / f"agent-{agent}.ckpt"


def save(state_dir: str | os.PathLike[str], ckpt: Checkpoint) -> None:
    """Write ``ckpt`` atomically."""
    path = checkpoint_path(state_dir, ckpt.agent)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            pickle.dump(ckpt, fh, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(state_dir: str | os.PathLike[str], run_id: str, agent: int) -> Checkpoint | None:
    """The agent's checkpoint for this run, or None (none yet, or another run's)."""
    path = checkpoint_path(state_dir, agent)
    try:
        with path.open("rb") as fh:
            ckpt = pickle.load(fh)
    except FileNotFoundError:
        return None
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError) as exc:
        raise RuntimeError(f"checkpoint {path} is unreadable ({exc}); remove it to start afresh") from None
    if not isinstance(ckpt, Checkpoint) or ckpt.run_id != run_id or ckpt.agent != agent:
        return None
    return ckpt


def remove(state_dir: str | os.PathLike[str], agent: int) -> None:
    checkpoint_path(state_dir, agent).unlink(missing_ok=True)
