"""The run's results folder (SPEC §7), every file written atomically (temporary file + rename).

A run folder holds ``config.toml`` (written by whoever starts the run), ``ticks.csv`` and
``summary.json``. The recorder rewrites ``ticks.csv`` and ``summary.json`` as ticks complete,
so an interrupted run leaves a readable partial result with ``"complete": false``.
"""
from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path

from protocol.config import RunConfig, write_atomic

VERSION = "0.1.0"
TICK_COLUMNS = (
    "tick", "t", "agent", "estimator", "ideal_x", "ideal_y", "est_x", "est_y", "pos_x", "pos_y",
    "required_range", "stay_range", "persist_range", "lost", "formation_error",
)
OBS_COLUMNS = ("tick", "agent", "estimator", "lost", "measurement", "prediction")


class RunRecorder:
    """Collects ground-truth rows and agents' observations and writes the results folder.

    Rows are formatted once, when they arrive, and per-follower metrics are kept as lists,
    so rewriting the folder after every tick costs little more than copying the text.
    """

    def __init__(self, out_dir: str | Path | None, config: RunConfig) -> None:
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.config = config
        self._clear()
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)

    def _clear(self) -> None:
        self.rows: list[dict] = []
        self.observations: list[dict] = []
        self.missed: dict[int, int] = {}
        self.ticks_done = 0
        self._tick_lines: list[str] = []
        self._obs_lines: list[str] = []
        self._metrics = {k: {"required": [], "stay": [], "persist": [], "lost": 0}
                         for k in range(1, self.config.followers + 1)}

    def add_tick(self, rows: list[dict]) -> None:
        """Append one tick's rows (from ``WorldSim.finish_tick``)."""
        for row in rows:
            k = row["agent"]
            if row.get("missed"):
                self.missed[k] = self.missed.get(k, 0) + 1
            if k in self._metrics:
                m = self._metrics[k]
                m["lost"] += row["lost"]
                if row.get("required_range") is not None:
                    m["required"].append(row["required_range"])
                    m["stay"].append(row["stay_range"])
                    m["persist"].append(row["persist_range"])
            self.ticks_done = max(self.ticks_done, row["tick"] + 1)
            self._tick_lines.append(_line(TICK_COLUMNS, row))
        self.rows.extend(rows)

    def add_observation(self, agent: int, msg) -> None:
        """Record an agent's published measurement and prediction (an ``Observation``)."""
        self._add_observation_row({
            "tick": msg.tick, "agent": agent, "estimator": msg.estimator, "lost": int(msg.lost),
            "measurement": " ".join(map(repr, msg.measurement or ())),
            "prediction": " ".join(map(repr, msg.prediction or ())),
        })

    def _add_observation_row(self, row: dict) -> None:
        self.observations.append(row)
        self._obs_lines.append(_line(OBS_COLUMNS, row))

    def restore(self, rows: list[dict], observations: list[dict], missed: dict[int, int]) -> None:
        """Start from rows and observations read back from a results folder (``--resume``)."""
        self._clear()
        for tick in sorted({r["tick"] for r in rows}):
            self.add_tick([{k: v for k, v in r.items() if k != "missed"}
                           for r in rows if r["tick"] == tick])
        for row in observations:
            self._add_observation_row(row)
        self.missed = dict(missed)

    def summary(self, *, complete: bool, reason: str = "", wall_time: float = 0.0) -> dict:
        """The ``summary.json`` content (SPEC §7)."""
        cfg = self.config
        followers = {}
        for k, m in self._metrics.items():
            followers[str(k)] = {
                "mean_required_range": _mean(m["required"]),
                "rmse": _rms(m["required"]),
                "mean_stay_range": _mean(m["stay"]),
                "mean_persist_range": _mean(m["persist"]),
                "lost_ticks": m["lost"],
                "missed_ticks": self.missed.get(k, 0),
                "estimated_ticks": len(m["required"]),
            }
        return {
            "followers": followers,
            "version": VERSION,
            "run_id": cfg.run_id,
            "seed": cfg.seed,
            "surface": cfg.surface,
            "estimator": cfg.estimator,
            "dictionary": cfg.dictionary,
            "comm_period": cfg.comm_period,
            "n_followers": cfg.followers,
            "ticks_completed": self.ticks_done,
            "ticks": cfg.ticks,
            "complete": complete,
            "reason": reason,
            "wall_time": wall_time,
        }

    def write(self, *, complete: bool, reason: str = "", wall_time: float = 0.0) -> None:
        """Write ``ticks.csv``, ``observations.csv`` and ``summary.json`` atomically."""
        if self.out_dir is None:
            raise RuntimeError("this recorder has no results folder")
        write_atomic(self.out_dir / "ticks.csv", _header(TICK_COLUMNS) + "".join(self._tick_lines))
        write_atomic(self.out_dir / "observations.csv",
                     _header(OBS_COLUMNS) + "".join(self._obs_lines))
        summary = self.summary(complete=complete, reason=reason, wall_time=wall_time)
        write_atomic(self.out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")


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


def _mean(values: list[float]) -> float | None:
    return math.fsum(values) / len(values) if values else None


def _rms(values: list[float]) -> float | None:
    return math.sqrt(math.fsum(v * v for v in values) / len(values)) if values else None


def read_observations(path: str | Path) -> list[dict]:
    """Read an ``observations.csv`` back (tick and agent as int, the rest as written)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [{**row, "tick": int(row["tick"]), "agent": int(row["agent"])}
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
                elif key in ("tick", "agent", "lost"):
                    row[key] = int(value)
                else:
                    row[key] = float(value)
            rows.append(row)
    return rows
