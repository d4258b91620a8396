"""Pure functions from a run's view (map payload, frames) to the columns the page draws.

Every function returns plain numpy arrays or dicts of lists (Bokeh ``ColumnDataSource`` data);
nothing here touches Bokeh's document, so all of it is tested without a browser.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from protocol.view import widen_to_aspect
from swarm.live.store import Frame

AGENT_COLORS = ("#222222", "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
HEADING_LOOKBACK = 50  # ticks searched back for the last move of an agent that stands still
CONTOUR_LEVELS = 14


def agent_color(agent: int) -> str:
    """The leader black, followers cycling through ten colours."""
    return AGENT_COLORS[0] if agent == 0 else AGENT_COLORS[1 + (agent - 1) % 10]


def height_grid(view_map: Mapping) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``xs`` (nx,), ``ys`` (ny,), heights (ny, nx) of a map payload, NaN outside the domain."""
    ny, nx = view_map["shape"]
    x0, x1, y0, y1 = view_map["box"]
    z = np.array([np.nan if h is None else h for h in view_map["heights"]], dtype=float)
    return np.linspace(x0, x1, nx), np.linspace(y0, y1, ny), z.reshape(ny, nx)


def contour_levels(z: np.ndarray, n: int = CONTOUR_LEVELS) -> np.ndarray:
    """``n`` evenly spaced heights strictly inside the finite range of ``z`` (empty if flat)."""
    finite = z[np.isfinite(z)]
    if finite.size == 0 or finite.max() - finite.min() <= 1e-12 * max(1.0, abs(finite.max())):
        return np.empty(0)
    return np.linspace(finite.min(), finite.max(), n + 2)[1:-1]


def hillshade(view_map: Mapping, azimuth: float = 315.0, altitude: float = 45.0) -> np.ndarray:
    """Shaded relief (ny, nx, 4) uint8 RGBA of the map's heights, light from ``azimuth``
    degrees (clockwise from north) at ``altitude`` degrees (matplotlib's ``LightSource``);
    transparent outside the surface's domain."""
    from matplotlib import colormaps
    from matplotlib.colors import LightSource

    xs, ys, z = height_grid(view_map)
    inside = np.isfinite(z)
    if not inside.any():
        raise ValueError("view_map has no finite height to shade")
    filled = _continued(z)
    light = LightSource(azdeg=azimuth, altdeg=altitude)
    # LightSource takes row 0 as the top (north) edge; our row 0 is the southern one.
    rgb = light.shade(filled[::-1], cmap=colormaps["gist_earth"], blend_mode="soft",
                      dx=float(xs[1] - xs[0]), dy=float(ys[1] - ys[0]))[::-1]
    rgba = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)
    rgba[..., 3] = np.where(inside, 255, 0)
    return rgba


def _continued(z: np.ndarray) -> np.ndarray:
    """``z`` with every NaN cell given the mean of its finite neighbours, ring after ring
    inwards from the domain's edge: the relief goes on flat past the edge (filled with a
    constant it would drop to a cliff there, which the light shades as a dark band)."""
    z = z.copy()
    while np.isnan(z).any():
        padded = np.pad(z, 1, constant_values=np.nan)
        rings = np.stack([padded[1 + dy:padded.shape[0] - 1 + dy, 1 + dx:padded.shape[1] - 1 + dx]
                          for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
        seen = np.isfinite(rings)
        count = seen.sum(axis=0)
        mean = np.where(seen, rings, 0.0).sum(axis=0) / np.maximum(count, 1)
        z = np.where(np.isnan(z) & (count > 0), mean, z)
    return z


def fit_view(box: Sequence[float], points: np.ndarray, margin: float,
             aspect: float) -> tuple[float, float, float, float]:
    """The view ``(x0, x1, y0, y1)`` at width/height ratio ``aspect`` that holds the map's
    ``box`` ``[x0, x1, y0, y1]`` and every point of ``points`` (n, 2) grown by ``margin``,
    about the centre of what it holds (one metre the same on both axes of a frame of
    that ratio)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    low = np.array([box[0], box[2]], dtype=float)
    high = np.array([box[1], box[3]], dtype=float)
    if points.size:
        low = np.minimum(low, points.min(axis=0) - margin)
        high = np.maximum(high, points.max(axis=0) + margin)
    low, high = widen_to_aspect(low, high, aspect)
    return low[0], high[0], low[1], high[1]


def sparse_labels(xs: Sequence[float], ys: Sequence[float], labels: Sequence[str],
                  gap: float) -> list[str]:
    """``labels`` with those of points closer than ``gap`` to an earlier labelled point
    blanked, so that labels never sit on one another: the first point (the leader) keeps its
    label, then each in turn (a column's followers in order) if it is far enough from every
    label kept."""
    kept: list[tuple[float, float]] = []
    out = []
    for x, y, label in zip(xs, ys, labels, strict=True):
        if all(math.hypot(x - kx, y - ky) >= gap for kx, ky in kept):
            kept.append((x, y))
            out.append(label)
        else:
            out.append("")
    return out


def heading(frames: Mapping[int, Frame], tick: int, agent: int) -> float:
    """Heading (rad, from +x) of ``agent`` at ``tick`` (the rows carry none): the direction of
    its last move up to ``tick``, else of its first move after it (a replay knows the future),
    searching :data:`HEADING_LOOKBACK` ticks each way; 0 if there is none."""
    back = range(tick, max(tick - HEADING_LOOKBACK, 0), -1)
    for j in [*back, *range(tick + 1, tick + 1 + HEADING_LOOKBACK)]:
        now, before = frames.get(j), frames.get(j - 1)
        if now is None or before is None or agent not in now.rows or agent not in before.rows:
            continue
        dx = now.rows[agent]["pos_x"] - before.rows[agent]["pos_x"]
        dy = now.rows[agent]["pos_y"] - before.rows[agent]["pos_y"]
        if math.hypot(dx, dy) > 1e-9:
            return math.atan2(dy, dx)
    return 0.0


MAP_COLUMNS = {
    "agents": ("x", "y", "label", "color"),
    "headings": ("x0", "y0", "x1", "y1", "color"),
    "rods": ("x0", "y0", "x1", "y1", "color"),
    "targets": ("x", "y", "color"),
    "estimates": ("x", "y", "color"),
    "ranges": ("x", "y", "radius", "color"),
    "paths": ("xs", "ys", "color", "width"),
}


def empty_map_columns() -> dict[str, dict[str, list]]:
    """Every map source's columns, empty (:data:`MAP_COLUMNS`)."""
    return {name: {c: [] for c in columns} for name, columns in MAP_COLUMNS.items()}


def map_columns(frames: Mapping[int, Frame], tick: int, sensing_range: float | None,
                nose: float) -> dict[str, dict[str, list]]:
    """Source data for the map at ``tick``: ``agents`` (position, label, colour), ``headings``
    (a segment of length ``nose`` along each agent's heading), ``rods`` (agent k−1's position
    to its rod end, i.e. follower k's true target), ``targets`` (true rod ends),
    ``estimates``, ``ranges`` (``R_s`` around each estimate, empty when ``R_s`` is infinite)
    and ``paths`` (every agent's trail up to ``tick``)."""
    frame = frames[tick]
    out = empty_map_columns()
    for k in sorted(frame.rows):
        row = frame.rows[k]
        _append(out["agents"], x=row["pos_x"], y=row["pos_y"], label="L" if k == 0 else str(k),
                color=agent_color(k))
        angle = heading(frames, tick, k)
        _append(out["headings"], x0=row["pos_x"], y0=row["pos_y"],
                x1=row["pos_x"] + nose * math.cos(angle), y1=row["pos_y"] + nose * math.sin(angle),
                color=agent_color(k))
    agents = sorted(frame.rows)
    for k in agents:
        row, holder = frame.rows[k], frame.rows.get(k - 1)
        if k == 0 or row["ideal_x"] is None:
            continue
        color = agent_color(k)
        if holder is not None:
            _append(out["rods"], x0=holder["pos_x"], y0=holder["pos_y"], x1=row["ideal_x"],
                    y1=row["ideal_y"], color=agent_color(k - 1))
        _append(out["targets"], x=row["ideal_x"], y=row["ideal_y"], color=color)
        if row["est_x"] is not None:
            _append(out["estimates"], x=row["est_x"], y=row["est_y"], color=color)
            if sensing_range is not None:
                _append(out["ranges"], x=row["est_x"], y=row["est_y"], radius=sensing_range,
                        color=color)
    trail = [frames[j] for j in sorted(frames) if j <= tick]
    for k in agents:
        _append(out["paths"], xs=[f.rows[k]["pos_x"] for f in trail if k in f.rows],
                ys=[f.rows[k]["pos_y"] for f in trail if k in f.rows], color=agent_color(k),
                width=2.5 if k == 0 else 1.2)
    return out


def _append(columns: dict[str, list], **values) -> None:
    for name, value in values.items():
        columns[name].append(value)


def follower_series(frames: Sequence[Frame], follower: int) -> dict[str, dict[str, list]]:
    """Per tick of ``frames`` (sorted): ``ranges`` (required, stay, persist; NaN where absent
    or not positive, for a log axis), ``lost`` and ``missed`` (tick and the height of the mark:
    the tick's first positive range, else the series' smallest, so that every mark shows)."""
    ranges: dict[str, list] = {"tick": [], "required": [], "stay": [], "persist": []}
    lost: dict[str, list] = {"tick": [], "y": []}
    missed: dict[str, list] = {"tick": [], "y": []}
    for frame in frames:
        row = frame.rows.get(follower)
        if row is None:
            continue
        values = [_positive(row[c]) for c in ("required_range", "stay_range", "persist_range")]
        ranges["tick"].append(frame.tick)
        for name, value in zip(("required", "stay", "persist"), values):
            ranges[name].append(value)
        mark = next((v for v in values if not math.isnan(v)), math.nan)
        for flag, marks in (("lost", lost), ("missed", missed)):
            if row[flag]:
                marks["tick"].append(frame.tick)
                marks["y"].append(mark)
    floor = min((v for name in ("required", "stay", "persist") for v in ranges[name]
                 if not math.isnan(v)), default=1.0)
    for marks in (lost, missed):
        marks["y"] = [floor if math.isnan(y) else y for y in marks["y"]]
    return {"ranges": ranges, "lost": lost, "missed": missed}


def log_span(ranges: Mapping[str, Sequence[float]], default: tuple[float, float] = (1e-3, 1.0),
             pad: float = 1.5) -> tuple[float, float]:
    """The y range of a log axis for :func:`follower_series`'s ``ranges``: the smallest and
    largest positive finite value of its series (``tick`` aside), widened by the factor
    ``pad`` each way; ``default`` when there is none yet."""
    values = [v for name, series in ranges.items() if name != "tick" for v in series
              if v > 0 and math.isfinite(v)]
    if not values:
        return default
    return min(values) / pad, max(values) * pad


def _positive(value: float | None) -> float:
    return value if value is not None and value > 0 else math.nan


def estimated_choices(choices: Mapping[tuple[int, int], str],
                      frames: Sequence[Frame]) -> dict[tuple[int, int], str]:
    """The (tick, follower) choices of ``choices`` at the follower's estimated ticks only:
    those whose row in ``frames`` holds a required range (the world measures it from the first
    estimated tick, ``init_ticks``, on). What a follower followed before is never used, and
    the page's range plots start there too."""
    estimated = {(frame.tick, k) for frame in frames for k, row in frame.rows.items()
                 if row.get("required_range") is not None}
    return {key: label for key, label in choices.items() if key in estimated}


def choice_points(choices: Mapping[tuple[int, int], str], followers: int) -> dict[str, list]:
    """Every (tick, follower) estimator choice as scatter columns, sorted by tick; ``y`` is
    the label with a small offset per follower (``[label, offset]``, a Bokeh categorical
    coordinate) so that followers choosing the same do not hide one another."""
    items = sorted(choices.items())
    step = 0.7 / max(followers, 1)
    return {"tick": [j for (j, _), _ in items], "label": [label for _, label in items],
            "y": [[label, (k - (followers + 1) / 2) * step] for (_, k), label in items],
            "follower": [str(k) for (_, k), _ in items],
            "color": [agent_color(k) for (_, k), _ in items]}
