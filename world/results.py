"""The run's results folder (SPEC §7): append-only CSVs and an atomic summary.

A run folder holds ``config.toml`` (written by whoever starts the run), ``ticks.csv``,
``observations.csv`` and ``summary.json``. The recorder appends each complete tick to the two
CSV files and rewrites ``summary.json`` atomically, so an interrupted run leaves a readable
partial result with ``"complete": false``, and a tick's write costs the same at tick 100 as at
tick 100,000.
"""
from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path

from protocol.config import RunConfig, write_atomic

VERSION = "0.2.0"
TICK_COLUMNS = (
    "tick", "t", "agent", "estimator", "ideal_x", "ideal_y", "est_x", "est_y", "pos_x", "pos_y",
    "required_range", "stay_range", "persist_range", "lost", "formation_error",
    "persist_range_noise_free", "missed", "floor_range",
    # --motion drive (SPEC §4, §7): the move phase's shortfall, the settled distance to the
    # rod end driven onto, the arc length driven and the steps a limit bound, per tick
    "reach_error", "snap_error", "path_length", "saturated_steps",
)
OBS_COLUMNS = ("tick", "agent", "estimator", "lost", "measurement", "prediction", "followed",
               "fallback")
TICKS_FILE, OBS_FILE, SUMMARY_FILE = "ticks.csv", "observations.csv", "summary.json"
RESULT_FILES = (TICKS_FILE, OBS_FILE, SUMMARY_FILE)


class ExactSum:
    """Running sum of floats, rounded exactly like ``math.fsum`` over every value added so far
    (Shewchuk's partials): the summary, rewritten after every tick, costs O(1) per tick.

    >>> s = ExactSum()
    >>> for x in (1e100, 1.0, -1e100, 0.1):
    ...     s.add(x)
    >>> s.value() == math.fsum([1e100, 1.0, -1e100, 0.1])
    True
    """

    def __init__(self) -> None:
        self._partials: list[float] = []
        self.count = 0

    def add(self, x: float) -> None:
        partials, i = self._partials, 0
        for y in partials:
            if abs(x) < abs(y):
                x, y = y, x
            hi = x + y
            lo = y - (hi - x)
            if lo:
                partials[i] = lo
                i += 1
            x = hi
        partials[i:] = [x]
        self.count += 1

    def value(self) -> float:
        return math.fsum(self._partials)

    def mean(self) -> float | None:
        return self.value() / self.count if self.count else None


class _FollowerMetrics:
    """One follower's running totals for ``summary.json``."""

    def __init__(self) -> None:
        self.required, self.squares = ExactSum(), ExactSum()
        self.stay, self.persist, self.persist_noise_free = ExactSum(), ExactSum(), ExactSum()
        self.floor, self.formation = ExactSum(), ExactSum()
        self.reach, self.snap, self.path = ExactSum(), ExactSum(), ExactSum()
        self.lost = self.missed = self.fallback = self.saturated = 0
        self.followed: dict[str, int] = {}

    def add_row(self, row: dict) -> None:
        self.lost += row.get("lost") or 0
        self.missed += row.get("missed") or 0
        self.saturated += row.get("saturated_steps") or 0
        for total, name in ((self.formation, "formation_error"), (self.reach, "reach_error"),
                            (self.snap, "snap_error"), (self.path, "path_length")):
            if row.get(name) is not None:
                total.add(row[name])
        if row.get("required_range") is not None:
            self.required.add(row["required_range"])
            self.squares.add(row["required_range"] ** 2)
            self.stay.add(row["stay_range"])
            self.persist.add(row["persist_range"])
            self.persist_noise_free.add(row["persist_range_noise_free"])
            self.floor.add(row["floor_range"])

    def add_observation(self, row: dict) -> None:
        self.fallback += int(row.get("fallback") or 0)
        if row.get("followed"):
            self.followed[row["followed"]] = self.followed.get(row["followed"], 0) + 1

    def summary(self) -> dict:
        n = self.required.count
        return {
            "mean_required_range": self.required.mean(),
            "rmse": math.sqrt(self.squares.value() / n) if n else None,
            "mean_stay_range": self.stay.mean(),
            "mean_persist_range": self.persist.mean(),
            "mean_persist_range_noise_free": self.persist_noise_free.mean(),
            "mean_floor_range": self.floor.mean(),
            "lost_ticks": self.lost,
            "missed_ticks": self.missed,
            "estimated_ticks": n - self.fallback,
            "fallback_ticks": self.fallback,
            "followed": _shares(self.followed),
            "mean_formation_error": self.formation.mean(),
        }

    def drive_summary(self) -> dict:
        """The ``--motion drive`` metrics (SPEC §7)."""
        return {
            "path_length": self.path.value(),
            "mean_reach_error": self.reach.mean(),
            "mean_snap_error": self.snap.mean(),
            "saturated_steps": self.saturated,
        }


class RunRecorder:
    """Records each complete tick: its ground-truth rows and the followers' observations.

    With a results folder, :meth:`open` it first; each :meth:`add_tick` then appends one tick to
    ``ticks.csv`` and ``observations.csv`` and flushes them. :attr:`offsets` are the two files'
    lengths after the last complete tick: the world's checkpoint stores them, and
    ``open(resume_offsets=...)`` cuts off whatever a crash left past them (a half-written or
    unconfirmed tick), then reads the kept rows back for the summary's totals. Without a folder
    (``out_dir=None``) only the totals are kept.
    """

    def __init__(self, out_dir: str | Path | None, config: RunConfig) -> None:
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.config = config
        self.ticks_done = 0
        self._metrics = {k: _FollowerMetrics() for k in range(1, config.followers + 1)}
        self._files: dict[str, io.TextIOBase] = {}

    def open(self, resume_offsets: dict[str, int] | None = None) -> None:
        """Open the CSV files: fresh (headers written) or cut back to ``resume_offsets``."""
        if self.out_dir is None:
            raise RuntimeError("this recorder has no results folder")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for name, columns in ((TICKS_FILE, TICK_COLUMNS), (OBS_FILE, OBS_COLUMNS)):
            path = self.out_dir / name
            if resume_offsets is None:
                fh = open(path, "w", encoding="utf-8", newline="")
                fh.write(_header(columns))
                fh.flush()
            else:
                size = path.stat().st_size if path.exists() else -1
                keep = resume_offsets.get(name)
                if not isinstance(keep, int) or isinstance(keep, bool) or not 0 < keep <= size:
                    raise ValueError(f"{path} holds {max(size, 0)} bytes, the checkpoint expects "
                                     f"at least {keep}: the files do not belong together")
                with open(path, "r+b") as raw:
                    raw.truncate(keep)
                fh = open(path, "a", encoding="utf-8", newline="")
            self._files[name] = fh
        if resume_offsets is not None:
            for row in read_ticks(self.out_dir / TICKS_FILE):
                self._count_row(row)
            for row in read_observations(self.out_dir / OBS_FILE):
                self._count_observation(row)

    def close(self) -> None:
        for fh in self._files.values():
            fh.close()
        self._files.clear()

    @property
    def offsets(self) -> dict[str, int]:
        """Byte length of each CSV file after the last complete tick."""
        return {name: fh.tell() for name, fh in self._files.items()}

    def _count_row(self, row: dict) -> None:
        if row["agent"] in self._metrics:
            self._metrics[row["agent"]].add_row(row)
        self.ticks_done = max(self.ticks_done, row["tick"] + 1)

    def _count_observation(self, row: dict) -> None:
        m = self._metrics.get(row["agent"])
        if m is not None and row["tick"] >= self.config.init_ticks:
            m.add_observation(row)

    def add_tick(self, rows: list[dict], observations: list[tuple[int, object]] = ()) -> None:
        """Record one complete tick: its rows (``WorldSim.finish_tick``) and the followers'
        observations of that tick as ``(agent, Observation)`` pairs, in agent order."""
        obs_rows = [observation_row(agent, msg) for agent, msg in observations]
        for row in rows:
            self._count_row(row)
        for row in obs_rows:
            self._count_observation(row)
        if self.out_dir is None:
            return
        ticks, obs = self._files[TICKS_FILE], self._files[OBS_FILE]
        ticks.write("".join(_line(TICK_COLUMNS, row) for row in rows))
        obs.write("".join(_line(OBS_COLUMNS, row) for row in obs_rows))
        ticks.flush()
        obs.flush()

    def summary(self, *, complete: bool, reason: str = "", wall_time: float = 0.0) -> dict:
        """The ``summary.json`` content (SPEC §7)."""
        cfg = self.config
        drive = cfg.motion == "drive"
        return {
            "followers": {str(k): {**m.summary(), **(m.drive_summary() if drive else {})}
                          for k, m in self._metrics.items()},
            "version": VERSION,
            "run_id": cfg.run_id,
            "seed": cfg.seed,
            "surface": cfg.surface,
            "estimator": cfg.estimator,
            "dictionary": cfg.dictionary,
            "comm_period": cfg.comm_period,
            "motion": cfg.motion,
            "n_followers": cfg.followers,
            "ticks_completed": self.ticks_done,
            "ticks": cfg.ticks,
            "complete": complete,
            "reason": reason,
            "wall_time": wall_time,
        }

    def write_summary(self, *, complete: bool, reason: str = "", wall_time: float = 0.0) -> None:
        """Write ``summary.json`` atomically."""
        if self.out_dir is None:
            raise RuntimeError("this recorder has no results folder")
        summary = self.summary(complete=complete, reason=reason, wall_time=wall_time)
        write_atomic(self.out_dir / SUMMARY_FILE, json.dumps(summary, indent=2) + "\n")


def observation_row(agent: int, msg) -> dict:
    """The ``observations.csv`` row of follower ``agent``'s ``Observation``."""
    return {
        "tick": msg.tick, "agent": agent, "estimator": msg.estimator, "lost": int(msg.lost),
        "measurement": " ".join(map(repr, msg.measurement or ())),
        "prediction": " ".join(map(repr, msg.prediction or ())),
        "followed": msg.followed, "fallback": int(msg.fallback),
    }


def _header(columns: tuple[str, ...]) -> str:
    return ",".join(columns) + "\n"


def _line(columns: tuple[str, ...], row: dict) -> str:
    """One CSV line (quoted where needed) of ``row``'s ``columns``."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?inf|nan")


def _cell(value) -> str:
    """The text of one CSV cell. A cell that a spreadsheet would read as a formula (starting
    with ``= + - @``, tab or CR) and is not a number, or numbers separated by spaces, is
    prefixed with ``'`` so it stays text."""
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(float(value))
    text = str(value)
    if text.startswith(_FORMULA_START) and not all(map(_NUMBER.fullmatch, text.split(" "))):
        return "'" + text
    return text


def _shares(counts: dict[str, int]) -> dict[str, float]:
    """Each name's share of the counted ticks, largest first."""
    total = sum(counts.values())
    return {name: n / total for name, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))}


def read_observations(path: str | Path) -> list[dict]:
    """Read an ``observations.csv`` back (tick, agent, lost, fallback as int)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [{**row, **{k: int(row[k]) for k in ("tick", "agent", "lost", "fallback")
                           if row.get(k) not in (None, "")},
                 "followed": row.get("followed") or None}
                for row in csv.DictReader(fh)]


def read_ticks(path: str | Path) -> list[dict]:
    """Read a ``ticks.csv`` back (numbers as float/int, empty cells as None)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = []
        for raw in csv.DictReader(fh):
            row = {}
            for key, value in raw.items():
                if value == "" or key == "estimator":
                    row[key] = value or None
                elif key in ("tick", "agent", "lost", "missed", "saturated_steps"):
                    row[key] = int(value)
                else:
                    row[key] = float(value)
            rows.append(row)
    return rows
