"""What the world publishes for observers (``world/view/map``, ``world/view/tick``).

Both payloads are plain dicts, validated here on both sides and carried as msgpack on the wire
(and the map also as JSON in the run folder, ``view_map.json``), each at most
:data:`MAX_VIEW_BYTES` and decoded within the bounds of :mod:`protocol.limits` (by the codec
of :mod:`protocol.messages`, whose field checks serve here too). They carry absolute
coordinates: only observers (the live view) may subscribe to them, never agents (the generated
access-control rules deny it).

*map*: the run's few settings an observer needs (``formation_tolerance`` may be absent: a
map written before it, read back by a replay) and a coarse height grid (at most
:data:`MAP_CELLS` cells, row-major, ``None`` outside the surface's domain) over the box
``[x0, x1, y0, y1]`` the ideal column covers. ``relief`` is ``"dem"`` for elevation-model
surfaces (drawn with hillshade) and ``"analytic"`` otherwise.

*tick*: one tick's ground-truth rows (columns :data:`TICK_COLUMNS`, ``None`` where a value does
not apply, e.g. the leader's ranges), split into chunks of at most :data:`ROWS_PER_CHUNK` agents;
``agents`` is the number of rows the whole tick has.

>>> rows = [{"tick": 2, "t": 2.56, "agent": 0, "pos_x": 1.0, "pos_y": 2.0}]
>>> [chunk] = tick_payloads(rows, n_agents=1)
>>> decode_tick(encode_tick(chunk))["rows"][0][:3]
[0, 1.0, 2.0]
"""
from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from protocol.limits import (  # the view's bounds; importers may take them from here too
    MAP_CELLS,
    MAX_VIEW_BYTES,
    MAX_VIEW_DEPTH,
    MAX_VIEW_TEXT,
    ROWS_PER_CHUNK,
    VIEW_MSGPACK_BOUNDS,
)
from protocol.messages import (
    ProtocolError,
    check_count,
    check_finite,
    check_text,
    pack_bounded,
    unpack_bounded,
)

VIEW_VERSION = 1
MAP_FILE = "view_map.json"  # the map, as JSON, in the run folder (for replays)
COUNT_COLUMNS = ("lost", "missed", "broken_ticks")
"""The counts that end a view row (0 where a row has none, e.g. the leader's broken ticks)."""
TICK_COLUMNS = ("agent", "pos_x", "pos_y", "ideal_x", "ideal_y", "est_x", "est_y",
                "required_range", "stay_range", "persist_range", "formation_error",
                "mean_formation_error", "worst_formation_error", *COUNT_COLUMNS)
"""A view row: the agent, its numbers (None where they do not apply), then
:data:`COUNT_COLUMNS`. ``mean_formation_error``, ``worst_formation_error`` and
``broken_ticks`` are a follower's formation health so far (:mod:`protocol.health`)."""
_NUMBER_COLUMNS = TICK_COLUMNS[1:-len(COUNT_COLUMNS)]
RELIEFS = ("analytic", "dem")
_MAP_NUMBERS = ("comm_period", "spacing")
_MAP_OPTIONAL = ("sensing_range", "formation_tolerance")  # None: infinite, or not sent
_MAP_COUNTS = ("followers", "ticks", "init_ticks")
_MAP_TEXTS = ("run_id", "surface", "estimator", "dictionary", "mode")
_FIELD = "view field"  # how the shared field checks (protocol.messages) name a view's field


def _number(name: str, value: Any, *, optional: bool = False) -> float | None:
    if value is None and optional:  # unlike a message's numbers, a view's may be absent (None)
        return None
    return check_finite(name, value, _FIELD)


def _count(name: str, value: Any) -> int:
    return check_count(name, value, _FIELD)


def _text(name: str, value: Any) -> str:
    return check_text(name, value, _FIELD, MAX_VIEW_TEXT)


def _header(body: Any, kind: str) -> dict:
    if not isinstance(body, dict):
        raise ProtocolError(f"view payload must be a map, got {type(body).__name__}")
    if body.get("v") != VIEW_VERSION:
        raise ProtocolError(f"unsupported view version {body.get('v')!r} (want {VIEW_VERSION})")
    if body.get("type") != kind:
        raise ProtocolError(f"view payload type {str(body.get('type'))[:40]!r} is not {kind!r}")
    return body


def check_map(body: Any) -> dict:
    """Validate a map payload (ProtocolError naming the problem); return it normalised."""
    body = _header(body, "view-map")
    out: dict[str, Any] = {"v": VIEW_VERSION, "type": "view-map"}
    for name in _MAP_TEXTS:
        out[name] = _text(name, body.get(name))
    for name in _MAP_NUMBERS:
        out[name] = _number(name, body.get(name))
    for name in _MAP_COUNTS:
        out[name] = _count(name, body.get(name))
    for name in _MAP_OPTIONAL:
        out[name] = _number(name, body.get(name), optional=True)
    if body.get("relief") not in RELIEFS:
        raise ProtocolError(f"view field 'relief' must be one of {RELIEFS}, "
                            f"got {body.get('relief')!r}")
    out["relief"] = body["relief"]
    box, shape, heights = body.get("box"), body.get("shape"), body.get("heights")
    if not isinstance(box, list) or len(box) != 4:
        raise ProtocolError("view field 'box' must be [x0, x1, y0, y1]")
    out["box"] = [_number(f"box[{i}]", x) for i, x in enumerate(box)]
    if not (out["box"][0] < out["box"][1] and out["box"][2] < out["box"][3]):
        raise ProtocolError(f"view field 'box' must have x0 < x1 and y0 < y1, got {out['box']}")
    if not isinstance(shape, list) or len(shape) != 2:
        raise ProtocolError("view field 'shape' must be [ny, nx]")
    ny, nx = (_count(f"shape[{i}]", n) for i, n in enumerate(shape))
    if nx < 2 or ny < 2 or nx * ny > MAP_CELLS:
        raise ProtocolError(f"view field 'shape' must be at least 2x2 and at most {MAP_CELLS} "
                            f"cells, got {shape}")
    out["shape"] = [ny, nx]
    if not isinstance(heights, list) or len(heights) != nx * ny:
        raise ProtocolError(f"view field 'heights' must be a list of {nx * ny} numbers")
    out["heights"] = [_number("heights[]", z, optional=True) for z in heights]
    return out


def check_tick(body: Any) -> dict:
    """Validate one tick chunk (ProtocolError naming the problem); return it normalised."""
    body = _header(body, "view-tick")
    out = {"v": VIEW_VERSION, "type": "view-tick", "tick": _count("tick", body.get("tick")),
           "t": _number("t", body.get("t")), "agents": _count("agents", body.get("agents"))}
    rows = body.get("rows")
    if not isinstance(rows, list) or not 0 < len(rows) <= ROWS_PER_CHUNK:
        raise ProtocolError(f"view field 'rows' must be a list of 1 to {ROWS_PER_CHUNK} rows")
    checked = []
    for i, row in enumerate(rows):
        if not isinstance(row, list) or len(row) != len(TICK_COLUMNS):
            raise ProtocolError(f"view row {i} must have {len(TICK_COLUMNS)} values")
        agent = _count(f"rows[{i}].agent", row[0])
        if agent >= out["agents"]:
            raise ProtocolError(f"view row {i} names agent {agent} of {out['agents']}")
        n = len(COUNT_COLUMNS)
        values = [_number(f"rows[{i}].{name}", x, optional=True)
                  for name, x in zip(_NUMBER_COLUMNS, row[1:-n])]
        flags = [_count(f"rows[{i}].{name}", x) for name, x in zip(COUNT_COLUMNS, row[-n:])]
        if values[0] is None or values[1] is None:
            raise ProtocolError(f"view row {i} has no position")
        checked.append([agent, *values, *flags])
    out["rows"] = checked
    return out


def tick_payloads(rows: list[dict], n_agents: int) -> list[dict]:
    """One tick's ground-truth rows (``WorldSim.finish_tick``) as validated chunks."""
    if not rows:
        raise ValueError("rows must hold at least one agent's row")
    table = [[row["agent"], *(row.get(c) for c in _NUMBER_COLUMNS),
              *(int(row.get(c) or 0) for c in COUNT_COLUMNS)] for row in rows]
    head = {"v": VIEW_VERSION, "type": "view-tick", "tick": rows[0]["tick"], "t": rows[0]["t"],
            "agents": n_agents}
    return [check_tick({**head, "rows": table[i:i + ROWS_PER_CHUNK]})
            for i in range(0, len(table), ROWS_PER_CHUNK)]


def _pack(body: dict) -> bytes:
    return pack_bounded(body, MAX_VIEW_BYTES, body["type"])


def _unpack(data: bytes) -> dict:
    return unpack_bounded(data, MAX_VIEW_BYTES, VIEW_MSGPACK_BOUNDS, MAX_VIEW_DEPTH,
                          "view payload")


def encode_map(body: dict) -> bytes:
    """The map as msgpack; heights travel as little-endian 32-bit floats (plenty for drawing),
    NaN where there is none."""
    body = check_map(body)
    heights = [math.nan if z is None else z for z in body["heights"]]
    return _pack({**body, "heights": struct.pack(f"<{len(heights)}f", *heights)})


def decode_map(data: bytes) -> dict:
    body = _unpack(data)
    if isinstance(body, dict) and isinstance(body.get("heights"), bytes):
        raw = body["heights"]
        if len(raw) % 4:
            raise ProtocolError("view field 'heights' must hold 32-bit floats")
        body["heights"] = [None if math.isnan(z) else z
                           for z in struct.unpack(f"<{len(raw) // 4}f", raw)]
    return check_map(body)


def encode_tick(body: dict, *, check: bool = True) -> bytes:
    """One tick chunk as msgpack; ``check=False`` skips validating a chunk that
    :func:`tick_payloads` built (and so validated) already."""
    return _pack(check_tick(body) if check else body)


def decode_tick(data: bytes) -> dict:
    return check_tick(_unpack(data))


def widen_to_aspect(low: np.ndarray, high: np.ndarray, aspect: float, *,
                    at_most: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Corners (2,), (2,) of the box ``low``..``high`` widened in x or y about its centre to
    the width/height ratio ``aspect`` (never narrowed: a page shows it whole at true aspect).
    The world's map box, the figures' maps and the live page's view (which may not import
    ``world``) all use it.

    With ``at_most``, only as far as brings its longer side down to at most ``aspect`` times
    its shorter (a box of any ratio between ``1 / aspect`` and ``aspect`` is kept).
    """
    if not aspect > 0:
        raise ValueError(f"aspect must be > 0, got {aspect!r}")
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    centre, (width, height) = (low + high) / 2, high - low
    size = np.maximum([width, height],
                      [height / aspect if at_most else height * aspect, width / aspect])
    return centre - size / 2, centre + size / 2
