"""A run's record as files (design §7): their names, the columns of ``ticks.csv``,
``observations.csv`` and (``--motion drive``) ``controls.csv``, and the one way to read them
back.

The world writes them (:mod:`world.results`); ``swarm plot``, ``swarm replay``, ``swarm
export``, the reports and ``python -m world --resume`` read them through :func:`read_ticks` /
:func:`read_observations` / :func:`read_controls` (or the ``parse_*`` functions on bytes
already read), which accept only a whole, ordered record: every row ends with a newline and has
the header's fields, numbers parse, and ``(tick, agent)`` — ``(tick, agent, step)`` for
controls — increases strictly from row to row. Anything else is refused with
:class:`DamagedRecord`, one line naming the file, the line and the defect.
"""
from __future__ import annotations

import csv
from pathlib import Path

TICK_COLUMNS = (
    "tick", "t", "agent", "estimator", "ideal_x", "ideal_y", "est_x", "est_y", "pos_x", "pos_y",
    "required_range", "stay_range", "persist_range", "lost", "formation_error",
    "persist_range_noise_free", "missed", "floor_range", "heading_x", "heading_y",
    # --motion drive (design §4, §7): the move phase's shortfall, the settled distance to the
    # rod end driven onto, the arc length driven and the steps a limit bound, per tick
    "reach_error", "snap_error", "path_length", "saturated_steps",
)
OBS_COLUMNS = ("tick", "agent", "estimator", "lost", "measurement", "prediction", "followed",
               "fallback")
CONTROL_COLUMNS = ("tick", "t", "agent", "step", "speed", "turn", "achieved_speed",
                   "achieved_turn")
"""``controls.csv`` (``--motion drive``): every control step of every driving follower — its
stamp (``WorldSim.control_time``), the commanded speed and turn rate and those achieved after
actuation noise."""
INT_TICK_COLUMNS = ("tick", "agent", "lost", "missed", "saturated_steps")
INT_CONTROL_COLUMNS = ("tick", "agent", "step")
MIN_COLUMNS = 3  # tick, and t or agent: a header this short is no results file
TICKS_FILE, OBS_FILE, SUMMARY_FILE = "ticks.csv", "observations.csv", "summary.json"
CONTROLS_FILE = "controls.csv"
RESULT_FILES = (TICKS_FILE, OBS_FILE, CONTROLS_FILE, SUMMARY_FILE)


class DamagedRecord(ValueError):
    """A results file that is not a whole, ordered record (a torn or malformed row, rows out of
    order or repeated); the message names the file, the line and the defect."""


def read_observations(path: str | Path) -> list[dict]:
    """Read an ``observations.csv`` back (tick, agent, lost, fallback as int), validated as
    :func:`parse_observations` does (:class:`DamagedRecord` otherwise)."""
    return parse_observations(_read(path), path)


def read_ticks(path: str | Path) -> list[dict]:
    """Read a ``ticks.csv`` back (numbers as float/int, empty cells as None), validated as
    :func:`parse_ticks` does (:class:`DamagedRecord` otherwise)."""
    return parse_ticks(_read(path), path)


def read_controls(path: str | Path) -> list[dict]:
    """Read a ``controls.csv`` back (tick, agent, step as int, the rest as float), validated
    as :func:`parse_controls` does (:class:`DamagedRecord` otherwise)."""
    return parse_controls(_read(path), path)


def _read(path: str | Path) -> bytes:
    with open(path, "rb") as fh:
        return fh.read()


def parse_ticks(raw: bytes, source: str | Path) -> list[dict]:
    """The rows of the ``ticks.csv`` text ``raw`` (read from ``source``), each whole: every line
    ends with a newline and has the header's fields, numbers parse, and ``(tick, agent)``
    increases strictly from row to row (no tick out of order, no agent twice in a tick).
    Files of earlier versions, with fewer of :data:`TICK_COLUMNS`, are read too."""
    rows = []
    for raw_row, line in _records(raw, source, TICK_COLUMNS):
        row = {}
        for key, value in raw_row.items():
            if value == "" or key == "estimator":
                row[key] = value or None
            elif key in INT_TICK_COLUMNS:
                row[key] = _number(int, value, key, source, line)
            else:
                row[key] = _number(float, value, key, source, line)
        rows.append(row)
    _in_order(rows, source)
    return rows


def parse_controls(raw: bytes, source: str | Path) -> list[dict]:
    """The rows of the ``controls.csv`` text ``raw``, validated as :func:`parse_ticks`, with
    every cell a number and ``(tick, agent, step)`` increasing strictly from row to row."""
    rows = []
    for raw_row, line in _records(raw, source, CONTROL_COLUMNS, len(CONTROL_COLUMNS)):
        rows.append({key: _number(int if key in INT_CONTROL_COLUMNS else float, value, key,
                                  source, line) for key, value in raw_row.items()})
    _in_order(rows, source, ("tick", "agent", "step"))
    return rows


def parse_observations(raw: bytes, source: str | Path) -> list[dict]:
    """The rows of the ``observations.csv`` text ``raw``, validated as :func:`parse_ticks`."""
    rows = []
    for raw_row, line in _records(raw, source, OBS_COLUMNS):
        row = {**raw_row, "followed": raw_row.get("followed") or None}
        for key in ("tick", "agent", "lost", "fallback"):
            if raw_row.get(key) not in (None, ""):
                row[key] = _number(int, raw_row[key], key, source, line)
        rows.append(row)
    _in_order(rows, source)
    return rows


def _damaged(source: str | Path, line: int, what: str) -> DamagedRecord:
    return DamagedRecord(f"{source}, line {line}: {what}; the record is damaged (refusing it)")


def _records(raw: bytes, source: str | Path, columns: tuple[str, ...],
             least: int = MIN_COLUMNS) -> list[tuple[dict[str, str], int]]:
    """``(row, line number)`` of every whole CSV row of ``raw`` under a header of ``columns``
    (or a prefix of at least ``least`` of them, from an earlier version)."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DamagedRecord(f"{source}: not UTF-8 text ({exc.reason} at byte {exc.start}); "
                            "the record is damaged (refusing it)") from None
    lines = text.split("\n")
    if lines[-1]:  # the last line has no newline: an append was cut short
        raise _damaged(source, len(lines), "a torn row (no end of line)")
    reader = csv.reader(lines[:-1])
    try:
        header = tuple(next(reader))
    except StopIteration:
        raise DamagedRecord(f"{source}: empty (no header); the record is damaged "
                            "(refusing it)") from None
    if len(header) < least or header != columns[:len(header)]:
        raise _damaged(source, 1, f"the header is not {', '.join(columns)}")
    records = []
    try:
        for fields in reader:
            if len(fields) != len(header):
                raise _damaged(source, reader.line_num, f"{len(fields)} fields, the header has "
                                                        f"{len(header)}")
            records.append((dict(zip(header, fields, strict=True)), reader.line_num))
    except csv.Error as exc:
        raise _damaged(source, reader.line_num, f"not CSV ({exc})") from None
    return records


def _number(kind: type, value: str, key: str, source: str | Path, line: int):
    try:
        return kind(value)
    except ValueError:
        raise _damaged(source, line, f"{key} is {value[:40]!r}, not a number") from None


def _in_order(rows: list[dict], source: str | Path,
              order: tuple[str, ...] = ("tick", "agent")) -> None:
    """Rows come tick by tick, in agent order (then in the order of the rest of ``order``),
    each combination of ``order``'s columns once."""
    def named(values: tuple) -> str:
        return ", ".join(f"{key} {x}" for key, x in zip(order, values, strict=True))

    before: tuple = (-1,) * len(order)
    for number, row in enumerate(rows, start=2):
        now = tuple(row.get(key) for key in order)
        if not all(isinstance(x, int) and x >= 0 for x in now):
            raise _damaged(source, number, f"no {' and '.join(order)}")
        if now <= before:
            raise _damaged(source, number, f"{named(now)} after {named(before)} (out of order "
                                           "or repeated)")
        before = now
