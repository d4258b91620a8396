"""What an observer knows about a run: the map, complete ticks, estimator choices, status.

A :class:`RunStore` is filled from Zenoh (live, :mod:`swarm.live.feed`) or from a run folder
(:func:`load_run`) and read by every open page through :meth:`RunStore.snapshot`; it is safe to
fill from Zenoh's threads while pages read it.
"""
from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

from protocol.health import ColumnHealth
from protocol.record import OBS_FILE, SUMMARY_FILE, TICKS_FILE, read_observations, read_ticks
from protocol.view import MAP_FILE, TICK_COLUMNS, check_map, tick_payloads

WAITING, RUNNING = "waiting for the world", "running"
WORLD_GONE = "the world process disappeared"
STARTING = "world alive, waiting for its first tick"
REPLAY_HINT = "python -m swarm replay RUN_DIR shows a finished run"
"""What to do when no run is there to watch (it may be over)."""
COMPLETE, INCOMPLETE = "complete", "incomplete"
NO_ESTIMATE = "no estimate yet"
"""What a follower followed at a tick where neither its estimator nor the fallback could
propose (it stood still)."""


def choice_label(estimator: str, followed: str | None, fallback: bool, predicted: bool) -> str:
    """What a follower followed at one tick, as its observation tells: the estimate of
    ``followed`` (``auto``'s candidate, or the estimator itself), ``"persist (fallback)"``
    while the estimator was not ready, :data:`NO_ESTIMATE` when nothing proposed. An
    observation without ``followed`` (an older sender or file) names ``estimator`` where it
    ``predicted``."""
    if fallback:
        return f"{followed or 'persist'} (fallback)"
    if followed:
        return followed
    return estimator if predicted else NO_ESTIMATE


@dataclass(frozen=True)
class Frame:
    """One complete tick: ``rows[agent]`` maps :data:`protocol.view.TICK_COLUMNS` to values."""

    tick: int
    t: float
    rows: dict[int, dict]


@dataclass(frozen=True)
class Snapshot:
    """A consistent copy of a store for drawing (``frames`` sorted by tick)."""

    version: int
    map: dict | None
    frames: tuple[Frame, ...]
    choices: MappingProxyType  # (tick, follower) -> what it followed (choice_label)
    status: str
    reason: str


class RunStore:
    """Thread-safe accumulator of one run's view; ``version`` grows with every change."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._map: dict | None = None
        self._frames: dict[int, Frame] = {}
        self._partial: dict[int, dict[int, dict]] = {}  # tick -> rows so far, until complete
        self._choices: dict[tuple[int, int], str] = {}
        self._status, self._reason = WAITING, ""
        self._version = 0

    def set_map(self, body: dict) -> None:
        """The world's map payload, as validated by ``decode_map`` or ``check_map``; the first
        one is kept."""
        with self._lock:
            if self._map is None:
                self._map = body
                self._version += 1

    def add_tick(self, body: dict) -> None:
        """One chunk of a tick's rows, as validated by ``decode_tick`` or made by
        ``tick_payloads``; the tick counts once all its rows are in."""
        rows = {row[0]: dict(zip(TICK_COLUMNS, row)) for row in body["rows"]}
        with self._lock:
            parts = self._partial.setdefault(body["tick"], {})
            parts.update(rows)
            if len(parts) >= body["agents"]:
                del self._partial[body["tick"]]
                self._frames[body["tick"]] = Frame(body["tick"], body["t"], parts)
                if self._status in (WAITING, STARTING):
                    self._status = RUNNING
                self._version += 1

    def add_choice(self, tick: int, follower: int, label: str) -> None:
        """What follower ``follower`` followed at ``tick`` (:func:`choice_label`)."""
        with self._lock:
            self._choices[(tick, follower)] = label
            self._version += 1

    def finish(self, complete: bool, reason: str = "") -> None:
        """The run ended (``world/done`` or the run folder's summary)."""
        with self._lock:
            self._status, self._reason = (COMPLETE, "") if complete else (INCOMPLETE, reason)
            self._version += 1

    def world_seen(self) -> None:
        """The world's liveliness token is there (it is, or was when the observer joined), or
        is back after it vanished: a paused world, or one started again with ``--resume``, goes
        on with the run (its agents wait for it too)."""
        with self._lock:
            if self._status == WAITING:
                self._status = STARTING
                self._version += 1
            elif self._status == INCOMPLETE and self._reason == WORLD_GONE:
                self._status, self._reason = (RUNNING if self._frames else STARTING), ""
                self._version += 1

    def world_gone(self) -> None:
        """The world's liveliness token vanished: an end without ``world/done`` is a failure
        (until the world is back)."""
        with self._lock:
            if self._status in (WAITING, STARTING, RUNNING):
                self._status, self._reason = INCOMPLETE, WORLD_GONE
                self._version += 1

    @property
    def version(self) -> int:
        with self._lock:
            return self._version

    def snapshot(self) -> Snapshot:
        with self._lock:
            return Snapshot(self._version, self._map,
                            tuple(self._frames[j] for j in sorted(self._frames)),
                            MappingProxyType(dict(self._choices)), self._status, self._reason)


def load_run(run_dir: str | Path) -> RunStore:
    """A store holding a finished (or interrupted) run, read from its folder alone.

    Reads ``view_map.json``, ``ticks.csv``, ``observations.csv`` and ``summary.json``
    (ValueError naming what is missing or malformed); each follower's formation health is
    counted from ``ticks.csv`` with ``summary.json``'s tolerance (:mod:`protocol.health`).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ValueError(f"run_dir {run_dir} is not a folder")
    store = RunStore()
    try:
        view_map = check_map(json.loads((run_dir / MAP_FILE).read_text()))
        ticks = read_ticks(run_dir / TICKS_FILE)
        summary = json.loads((run_dir / SUMMARY_FILE).read_text())
        obs_path = run_dir / OBS_FILE
        observations = read_observations(obs_path) if obs_path.exists() else []
        store.set_map(view_map)
        by_tick: dict[int, list[dict]] = {}
        for row in ticks:
            by_tick.setdefault(row["tick"], []).append(_row(row))
        # each follower's formation health so far, counted as the world's recorder counts it
        health = ColumnHealth(view_map["followers"],
                              summary.get("formation_tolerance") or math.inf)
        for rows in by_tick.values():  # in chunks, as the world publishes them
            for chunk in tick_payloads(health.add_tick(rows), view_map["followers"] + 1):
                store.add_tick(chunk)
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot replay {run_dir}: {exc}") from None
    for row in observations:
        store.add_choice(row["tick"], row["agent"], choice_label(
            row["estimator"], row.get("followed"), row.get("fallback") == 1,
            bool(row.get("prediction"))))
    store.finish(bool(summary.get("complete")), str(summary.get("reason", "")))
    return store


def _row(row: dict) -> dict:
    """A row of :func:`protocol.record.read_ticks` with the view's columns, as
    ``WorldSim.finish_tick`` gives it (``missed`` is 0 where the file has no such column;
    the formation health, which the file has not, is counted by
    :class:`protocol.health.ColumnHealth`)."""
    view = {"tick": row["tick"], "t": row["t"]}
    for name in TICK_COLUMNS:
        value = row.get(name)
        view[name] = (value or 0) if name in ("agent", "lost", "missed") else value
    return view
