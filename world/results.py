"""The run's results folder (design §7): append-only CSVs and an atomic summary.

A run folder holds ``config.toml`` (written by whoever starts the run), ``ticks.csv``,
``observations.csv``, with ``--motion drive`` ``controls.csv``, and ``summary.json``. The
recorder appends each complete tick to the CSV files and rewrites ``summary.json`` atomically,
so an interrupted run leaves a readable partial result with ``"complete": false``, and a
tick's write costs the same at tick 100 as at tick 100,000.
"""
from __future__ import annotations

import csv
import io
import itertools
import json
import math
import os
import re
from pathlib import Path

from protocol.config import RunConfig
from protocol.distribution import version
from protocol.folder import AppendFile, write_atomic
from protocol.health import ColumnHealth, ExactSum
from protocol.limits import MAX_TEXT
from protocol.record import (
    CONTROL_COLUMNS,
    CONTROLS_FILE,
    OBS_COLUMNS,
    OBS_FILE,
    SUMMARY_FILE,
    TICK_COLUMNS,
    TICKS_FILE,
    DamagedRecord,
    parse_controls,
    parse_observations,
    parse_ticks,
)

RESERVE_FILE = ".summary.reserve"



def broken_ticks(summary: dict) -> int:
    """The follower-ticks of the run ``summary`` describes that stood beyond the formation
    tolerance, over every follower (missed ticks included, and ticks whose ideal place was off
    the surface's domain: design §7)."""
    return sum(s.get("broken_ticks", 0) for s in summary["followers"].values())


def run_failure(summary: dict) -> str | None:
    """Why the run ``summary`` describes is not a success, in one line, or None if it is: it
    ended incomplete (its reason first), or a follower stood beyond the formation tolerance at
    some tick, settled in time or not (design §7: a broken formation is not success; a
    follower that missed stands where it stood while the formation moves on). The one verdict
    of ``swarm run`` and ``python -m world`` (both print it as their last line and exit 1)."""
    if not summary["complete"]:
        return f"run incomplete: {summary['reason']}"
    if summary.get("formation_broken"):
        missed = sum(s.get("missed_ticks", 0) for s in summary["followers"].values())
        return (f"the formation broke: {broken_ticks(summary)} follower-ticks beyond "
                f"--formation-tolerance {summary['formation_tolerance']:g} m"
                + (f" ({missed} follower-ticks missed)" if missed else ""))
    return None


class _FollowerMetrics:
    """One follower's running totals for ``summary.json``."""

    def __init__(self) -> None:
        self.required, self.squares = ExactSum(), ExactSum()
        self.stay, self.persist, self.persist_noise_free = ExactSum(), ExactSum(), ExactSum()
        self.floor = ExactSum()
        self.reach, self.snap, self.path = ExactSum(), ExactSum(), ExactSum()
        self.lost = self.missed = self.fallback = self.saturated = 0
        self.followed: dict[str, int] = {}

    def add_row(self, row: dict) -> None:
        """Count one row (its formation health is counted by
        :class:`protocol.health.ColumnHealth`, not here)."""
        self.lost += row.get("lost") or 0
        self.missed += row.get("missed") or 0
        self.saturated += row.get("saturated_steps") or 0
        for total, name in ((self.reach, "reach_error"),
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
        }

    def drive_summary(self) -> dict:
        """The ``--motion drive`` metrics (design §7)."""
        return {
            "path_length": self.path.value(),
            "mean_reach_error": self.reach.mean(),
            "mean_snap_error": self.snap.mean(),
            "saturated_steps": self.saturated,
        }


class RunRecorder:
    """Records each complete tick: its ground-truth rows and the followers' observations.

    With a results folder, :meth:`open` it first; each :meth:`add_tick` then appends one tick to
    ``ticks.csv``, ``observations.csv`` and, in a drive run, ``controls.csv``, whole or not at
    all (a failed write is cut back to the previous tick in every file before the error, naming
    the file, is raised). :attr:`offsets` are the files' lengths after the last complete tick:
    the world's checkpoint stores them, and ``open(resume_offsets=...)`` first checks that the
    files hold whole, ordered rows up to them (nothing is changed otherwise), then cuts off
    whatever a crash left past them (a half-written or unconfirmed tick). A spare file of
    :meth:`reserve_bytes` is kept in the folder while the run goes, and given up just before
    the last summary is written, so that even a full disk leaves a summary with the true
    reason.
    Without a folder (``out_dir=None``) only the totals are kept.
    """

    def __init__(self, out_dir: str | Path | None, config: RunConfig) -> None:
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.config = config
        self.ticks_done = 0
        self._metrics = {k: _FollowerMetrics() for k in range(1, config.followers + 1)}
        self.health = ColumnHealth(config.followers, config.formation_tolerance)
        self._files: dict[str, AppendFile] = {}
        self._tables = {TICKS_FILE: TICK_COLUMNS, OBS_FILE: OBS_COLUMNS}
        if config.drives:
            self._tables[CONTROLS_FILE] = CONTROL_COLUMNS

    def open(self, resume_offsets: dict[str, int] | None = None,
             resume_ticks: int | None = None) -> None:
        """Open the CSV files: fresh (headers written) or, to resume, checked to hold whole rows
        of ``resume_ticks`` complete ticks up to ``resume_offsets`` and then cut back to them.

        Raises
        ------
        DamagedRecord
            A file to resume is shorter than its offset, cut mid-row, or its kept rows are
            damaged, or hold another number of ticks (no file was changed).
        """
        if self.out_dir is None:
            raise RuntimeError("this recorder has no results folder")
        if resume_offsets is not None:
            ticks, observations = self._kept_rows(resume_offsets, resume_ticks)
        for name, columns in self._tables.items():
            fresh = resume_offsets is None
            self._files[name] = AppendFile(self.out_dir / name, truncate=fresh)
            if fresh:
                self._files[name].append(_header(columns).encode())
            else:
                self._files[name].cut(resume_offsets[name])
        if resume_offsets is not None:
            for _, tick in itertools.groupby(ticks, key=lambda row: row["tick"]):
                self._count_rows(list(tick))
            for row in observations:
                self._count_observation(row)
        write_atomic(self.out_dir / RESERVE_FILE, bytes(self.reserve_bytes()))

    def _kept_rows(self, offsets: dict[str, int],
                   ticks: int | None) -> tuple[list[dict], list[dict]]:
        """The rows of ``ticks.csv`` and ``observations.csv`` up to ``offsets``, validated
        (whole rows, in order, ``ticks`` complete ticks if given; ``controls.csv``'s too, of
        those ticks only), reading only."""
        kept = {}
        for name in self._tables:
            path, keep = self.out_dir / name, offsets.get(name)
            try:
                with open(path, "rb") as fh:
                    size = os.fstat(fh.fileno()).st_size
                    fits = _offset(keep) and 0 < keep <= size
                    raw = fh.read(keep) if fits else b""
            except FileNotFoundError:
                size, fits = -1, False
            if not fits:
                raise DamagedRecord(f"{path} holds {max(size, 0)} bytes, the checkpoint expects "
                                    f"at least {keep}: the files do not belong together")
            kept[name] = raw
        rows = parse_ticks(kept[TICKS_FILE], self.out_dir / TICKS_FILE)
        observations = parse_observations(kept[OBS_FILE], self.out_dir / OBS_FILE)
        held = rows[-1]["tick"] + 1 if rows else 0
        if ticks is not None and held != ticks:
            raise DamagedRecord(f"{self.out_dir / TICKS_FILE} holds {held} ticks up to the "
                                f"checkpoint's offset, the checkpoint {ticks}")
        if CONTROLS_FILE in kept:
            controls = parse_controls(kept[CONTROLS_FILE], self.out_dir / CONTROLS_FILE)
            if controls and controls[-1]["tick"] >= held:
                raise DamagedRecord(f"{self.out_dir / CONTROLS_FILE} holds tick "
                                    f"{controls[-1]['tick']} up to the checkpoint's offset, "
                                    f"{self.out_dir / TICKS_FILE} {held} ticks")
        return rows, observations

    def reserve_bytes(self) -> int:
        """Size of the spare file: room for two summaries with the longest reason, in pages."""
        longest = json.dumps(self.summary(complete=False, reason="x" * MAX_TEXT), indent=2)
        return -(-2 * len(longest.encode()) // 4096) * 4096

    def close(self) -> None:
        for fh in self._files.values():
            fh.close()
        self._files.clear()

    @property
    def offsets(self) -> dict[str, int]:
        """Byte length of each CSV file after the last complete tick."""
        return {name: fh.size for name, fh in self._files.items()}

    def _count_rows(self, rows: list[dict]) -> list[dict]:
        """Count one tick's rows (in agent order); return them with each follower's formation
        health so far (:meth:`protocol.health.ColumnHealth.add_tick`)."""
        for row in rows:
            if row["agent"] in self._metrics:
                self._metrics[row["agent"]].add_row(row)
            self.ticks_done = max(self.ticks_done, row["tick"] + 1)
        return self.health.add_tick(rows)

    def _count_observation(self, row: dict) -> None:
        m = self._metrics.get(row["agent"])
        if m is not None and row["tick"] >= self.config.init_ticks:
            m.add_observation(row)

    def add_tick(self, rows: list[dict], observations: list[tuple[int, object]] = (),
                 controls: list[dict] = ()) -> list[dict]:
        """Record one complete tick: its rows (``WorldSim.finish_tick``), the followers'
        observations of that tick as ``(agent, Observation)`` pairs, in agent order, and in a
        drive run its control steps (``WorldSim.control_rows``). With a folder the tick is
        written whole to every file before it counts, or not at all. Returns the rows with
        each follower's formation health so far (what the live view and ROS 2 show)."""
        if controls and CONTROLS_FILE not in self._tables:
            raise ValueError("controls are recorded in drive runs only (motion 'drive')")
        obs_rows = [observation_row(agent, msg) for agent, msg in observations]
        if self.out_dir is not None:
            before = self.offsets
            data = {TICKS_FILE: rows, OBS_FILE: obs_rows, CONTROLS_FILE: controls}
            try:
                for name, columns in self._tables.items():
                    text = "".join(_line(columns, row) for row in data[name])
                    self._files[name].append(text.encode("utf-8"))
            except OSError:
                for name, size in before.items():
                    self._files[name].cut(size)
                raise
        shown = self._count_rows(rows)
        for row in obs_rows:
            self._count_observation(row)
        return shown

    def summary(self, *, complete: bool, reason: str = "", wall_time: float = 0.0) -> dict:
        """The ``summary.json`` content (design §7)."""
        cfg = self.config
        drive = cfg.drives
        return {
            "followers": {str(k): {**m.summary(), **self.health.followers[k].values(),
                                   **(m.drive_summary() if drive else {})}
                          for k, m in self._metrics.items()},
            "version": version(),
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
            "formation_tolerance": cfg.formation_tolerance,
            "formation_broken": self.health.broken(),
            "wall_time": wall_time,
        }

    def write_summary(self, *, complete: bool, reason: str = "", wall_time: float = 0.0,
                      final: bool = False) -> None:
        """Write ``summary.json`` atomically; the ``final`` one (the run is over, complete or
        not) first gives up the spare file, so that it finds room on a full disk."""
        if self.out_dir is None:
            raise RuntimeError("this recorder has no results folder")
        if final:
            (self.out_dir / RESERVE_FILE).unlink(missing_ok=True)
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


def _offset(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
