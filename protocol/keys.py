"""Zenoh key expressions of one run (design §8).

Every key lives under ``swarm/<run>/``; agent ids are integers, 0 being the leader.
"""
from __future__ import annotations

import re

from protocol.limits import MAX_RUN_ID

_RUN_ID = re.compile(rf"^[A-Za-z0-9_.-]{{1,{MAX_RUN_ID}}}$")


def check_run_id(run_id: str) -> str:
    """Return ``run_id`` if it is a valid key chunk, else raise ValueError."""
    if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
        raise ValueError(
            f"run_id must be 1-{MAX_RUN_ID} characters of [A-Za-z0-9_.-], got {run_id!r}"
        )
    return run_id


def check_agent_id(agent: int) -> int:
    """Return ``agent`` if it is a non-negative int, else raise ValueError."""
    if isinstance(agent, bool) or not isinstance(agent, int) or agent < 0:
        raise ValueError(f"agent id must be a non-negative integer, got {agent!r}")
    return agent


def _root(run_id: str) -> str:
    return f"swarm/{check_run_id(run_id)}"


def tick(run_id: str) -> str:
    """World publishes: tick j started."""
    return f"{_root(run_id)}/world/tick"


def missed(run_id: str) -> str:
    """World publishes: an agent did not settle in time (realtime) or vanished at tick j."""
    return f"{_root(run_id)}/world/missed"


def done(run_id: str) -> str:
    """World publishes: the run finished."""
    return f"{_root(run_id)}/world/done"


def view(run_id: str, what: str = "**") -> str:
    """World publishes for observers only (live view, recorders): ``view/map`` (what to draw
    the surface with) and ``view/tick`` (one tick's ground-truth rows, absolute coordinates).
    Agents must never subscribe here (the generated access-control rules deny it)."""
    if what != "**" and not re.fullmatch(r"[a-z]{1,16}", what):
        raise ValueError(f"view key chunk must be 1-16 lowercase letters, got {what!r}")
    return f"{_root(run_id)}/world/view/{what}"


def sense(run_id: str, agent: int | str = "*") -> str:
    """World queryable answering agent ``agent``'s local measurements."""
    return f"{_root(run_id)}/world/sense/{_agent_chunk(agent)}"


def act(run_id: str, agent: int | str = "*") -> str:
    """World queryable executing agent ``agent``'s motion."""
    return f"{_root(run_id)}/world/act/{_agent_chunk(agent)}"


def rod(run_id: str, agent: int | str = "*") -> str:
    """Agent publishes: settled at tick j, rod deployed."""
    return f"{_root(run_id)}/agent/{_agent_chunk(agent)}/rod"


def obs(run_id: str, agent: int | str = "*") -> str:
    """Agent publishes: its measurement and prediction for tick j."""
    return f"{_root(run_id)}/agent/{_agent_chunk(agent)}/obs"


def alive(run_id: str, who: int | str) -> str:
    """Liveliness token of the world (``who="world"``) or of an agent id."""
    chunk = who if who in ("world", "*") else f"agent/{check_agent_id(who)}"
    if who == "*":
        return f"{_root(run_id)}/alive/**"
    return f"{_root(run_id)}/alive/{chunk}"


def agent_from_key(key: str, last: bool = False) -> int:
    """Extract the agent id from a ``.../agent/<id>/...`` or ``.../world/<op>/<id>`` key.

    ``last=True``: the id is the key's last chunk (queryable keys; the fast path).
    Raises ValueError (message names the key) if there is none.
    """
    if last:
        chunk = key.rpartition("/")[2]
        if chunk.isdigit() and len(chunk) < 7:
            return int(chunk)
        raise ValueError(f"key {key!r} names no agent id")
    parts = str(key).split("/")
    for marker, offset in (("agent", 1), ("sense", 1), ("act", 1)):
        if marker in parts:
            i = parts.index(marker) + offset
            if i < len(parts) and parts[i].isdigit() and len(parts[i]) < 7:
                return int(parts[i])
    raise ValueError(f"key {key!r} names no agent id")


def _agent_chunk(agent: int | str) -> str:
    return "*" if agent == "*" else str(check_agent_id(agent))
