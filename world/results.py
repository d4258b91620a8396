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
from pathlib import Path

from protocol.config import RunConfig, write_atomic

VERSION = "0.1.0"
TICK_COLUMNS = (
    "tick", "t", "agent", "estimator", "ideal_x", "ideal_y", "est_x", "est_y", "pos_x", "pos_y",
    "required_range", "stay_range", "persist_range", "lost", "formation_error",
)
OBS_COLUMNS = ("tick", "agent", "estimator", "lost", "measurement", "prediction")


class RunRecorder:
    """Collects ground-truth rows and agents' observations and writes the results folder."""

    def __init__(self, out_dir: str | Path | None, config: RunConfig) -> None:
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.config = config
        self.rows: list[dict] = []
        self.observations: list[dict] = []
        self.missed: dict[int, int] = {}
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)

    @property
    def ticks_done(self) -> int:
        return 1 + max((r["tick"] for r in self.rows), default=-1)

    def add_tick(self, rows: list[dict]) -> None:
        """Append one tick's rows (from ``WorldSim.finish_tick``)."""
        for row in rows:
            if row.get("missed"):
                self.missed[row["agent"]] = self.missed.get(row["agent"], 0) + 1
        self.rows.extend(rows)

    def add_observation(self, agent: int, msg) -> None:
        """Record an agent's published measurement and prediction (an ``Observation``)."""
        self.observations.append({
            "tick": msg.tick, "agent": agent, "estimator": msg.estimator, "lost": int(msg.lost),
            "measurement": " ".join(map(repr, msg.measurement or ())),
            "prediction": " ".join(map(repr, msg.prediction or ())),
        })

    def summary(self, *, complete: bool, reason: str = "", wall_time: float = 0.0) -> dict:
        """The ``summary.json`` content (SPEC §7)."""
        cfg = self.config
        followers = {}
        for k in range(1, cfg.followers + 1):
            mine = [r for r in self.rows if r["agent"] == k]
            est = [r for r in mine if r.get("required_range") is not None]
            followers[str(k)] = {
                "mean_required_range": _mean(r["required_range"] for r in est),
                "rmse": _rms(r["required_range"] for r in est),
                "mean_stay_range": _mean(r["stay_range"] for r in est),
                "mean_persist_range": _mean(r["persist_range"] for r in est),
                "lost_ticks": sum(r["lost"] for r in mine),
                "missed_ticks": self.missed.get(k, 0),
                "estimated_ticks": len(est),
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
        write_atomic(self.out_dir / "ticks.csv", _csv(TICK_COLUMNS, self.rows))
        write_atomic(self.out_dir / "observations.csv", _csv(OBS_COLUMNS, self.observations))
        summary = self.summary(complete=complete, reason=reason, wall_time=wall_time)
        write_atomic(self.out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")


def _csv(columns: tuple[str, ...], rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(float(value))
    return str(value)


def _mean(values) -> float | None:
    values = [float(v) for v in values]
    return math.fsum(values) / len(values) if values else None


def _rms(values) -> float | None:
    values = [float(v) ** 2 for v in values]
    return math.sqrt(math.fsum(values) / len(values)) if values else None


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
