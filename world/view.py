"""What the world publishes for observers: the map to draw and each tick's ground truth.

:func:`map_payload` builds the ``world/view/map`` payload (see :mod:`protocol.view`): a coarse
height grid over the box the ideal column covers, and the few run settings an observer needs.
:class:`ViewPublisher` publishes it (again at most once per :data:`MAP_EVERY_S`, so an observer
that joins late still gets it), publishes each tick's rows on ``world/view/tick``, and writes
the map into the run folder (``view_map.json``) so that a replay reads the folder alone.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import zenoh

from protocol import keys
from protocol.config import RunConfig
from protocol.folder import write_atomic
from protocol.view import (
    MAP_CELLS,
    MAP_FILE,
    MAX_VIEW_TEXT,
    VIEW_VERSION,
    check_map,
    encode_map,
    encode_tick,
    tick_payloads,
    widen_to_aspect,
)
from world.surfaces import DEM_PREFIX, Surface

MAP_EVERY_S = 1.0
MAX_MAP_ASPECT = 2.5  # the map's longer side over its shorter one, at most


def map_box(ideal: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Corners ``low``, ``high`` (2,) of the region to draw: the finite points of ``ideal``
    (any shape ending in 2) grown by a margin of half a rod and 5% of the larger side, the
    shorter side then widened about the centre to at least 1/:data:`MAX_MAP_ASPECT` of the
    longer (a page shows the box whole at true aspect: never a narrow strip)."""
    points = np.asarray(ideal, dtype=float).reshape(-1, 2)
    points = points[np.isfinite(points).all(axis=1)]
    if points.size == 0:
        raise ValueError("ideal must hold at least one finite point")
    low, high = points.min(axis=0), points.max(axis=0)
    margin = 0.5 * spacing + 0.05 * float(np.max(high - low))
    return widen_to_aspect(low - margin, high + margin, MAX_MAP_ASPECT, at_most=True)


def grid_shape(low: np.ndarray, high: np.ndarray, cells: int = MAP_CELLS) -> tuple[int, int]:
    """``(ny, nx)``, at least 2 each, ``ny·nx <= cells``, cells about square over the box."""
    width, height = (float(x) for x in np.asarray(high) - np.asarray(low))
    if not (width > 0 and height > 0):
        raise ValueError(f"the box must have positive width and height, got {width}, {height}")
    nx = int(np.clip(math.sqrt(cells * width / height), 2, cells // 2))
    ny = int(np.clip(cells // nx, 2, cells // 2))
    return ny, nx


def height_grid(surface: Surface, low: np.ndarray, high: np.ndarray,
                shape: tuple[int, int]) -> np.ndarray:
    """Heights (ny, nx) at the grid over ``low``..``high``; NaN outside the surface's domain
    (where ``contains`` says no, or where ``height`` refuses the point with a ValueError such
    as ``SurfaceDomainError``: the map's margin may reach past a surface's edge)."""
    ny, nx = shape
    xs, ys = np.linspace(low[0], high[0], nx), np.linspace(low[1], high[1], ny)
    contains = getattr(surface, "contains", None)
    z = np.full((ny, nx), np.nan)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            p = np.array([x, y])
            if contains is None or contains(p):
                try:
                    z[i, j] = surface.height(p)
                except ValueError:
                    continue
    return z


def shown_surface(name: str) -> str:
    """The surface's name as the view shows it: at most :data:`MAX_VIEW_TEXT` characters, a
    longer one (a DEM deep in a folder tree) keeping its prefix and the end of its path."""
    if len(name) <= MAX_VIEW_TEXT:
        return name
    prefix = DEM_PREFIX if name.startswith(DEM_PREFIX) else ""
    return prefix + "…" + name[len(name) - (MAX_VIEW_TEXT - len(prefix) - 1):]


def map_payload(config: RunConfig, surface: Surface, ideal: np.ndarray) -> dict:
    """The ``world/view/map`` payload of a run (validated).

    Parameters
    ----------
    config : RunConfig
    surface : Surface
    ideal : ndarray, shape (n_agents, n_ticks, 2)
        The ideal formation (``WorldSim.ideal``), NaN past the surface's domain.
    """
    low, high = map_box(ideal, config.spacing)
    shape = grid_shape(low, high)
    z = height_grid(surface, low, high, shape)
    return check_map({
        "v": VIEW_VERSION, "type": "view-map", "run_id": config.run_id,
        "surface": shown_surface(config.surface),
        "relief": "dem" if config.surface.startswith(DEM_PREFIX) else "analytic",
        "estimator": config.estimator, "dictionary": config.dictionary, "mode": config.mode,
        "followers": config.followers, "ticks": config.ticks, "init_ticks": config.init_ticks,
        "comm_period": config.comm_period, "spacing": config.spacing,
        "sensing_range": config.sensing_range if math.isfinite(config.sensing_range) else None,
        "formation_tolerance": (config.formation_tolerance
                                if math.isfinite(config.formation_tolerance) else None),
        "box": [float(low[0]), float(high[0]), float(low[1]), float(high[1])],
        "shape": list(shape),
        # 7 significant digits: what the wire's 32-bit floats carry, and a compact JSON file
        "heights": [float(f"{h:.7g}") if math.isfinite(h) else None for h in z.ravel()],
    })


class ViewPublisher:
    """Publishes a run's view for observers on an open session.

    Parameters
    ----------
    session : zenoh.Session
    config : RunConfig
    surface : Surface
    ideal : ndarray, shape (n_agents, n_ticks, 2)
        The ideal formation; it sets the region the map covers.
    out_dir : path, optional
        Run folder: the map is written there as ``view_map.json``.
    """

    def __init__(self, session: zenoh.Session, config: RunConfig, surface: Surface,
                 ideal: np.ndarray, out_dir: str | Path | None = None) -> None:
        self.map = map_payload(config, surface, ideal)
        self._map_bytes = encode_map(self.map)
        self._n_agents = config.followers + 1
        self._map_pub = session.declare_publisher(keys.view(config.run_id, "map"))
        self._tick_pub = session.declare_publisher(keys.view(config.run_id, "tick"))
        self._map_sent = -math.inf
        if out_dir is not None:
            write_atomic(Path(out_dir) / MAP_FILE, json.dumps(self.map) + "\n")

    def publish_map(self, force: bool = False) -> None:
        """Publish the map, unless it went out less than :data:`MAP_EVERY_S` ago."""
        now = time.monotonic()
        if force or now - self._map_sent >= MAP_EVERY_S:
            self._map_pub.put(self._map_bytes)
            self._map_sent = now

    def publish_tick(self, rows: list[dict]) -> None:
        """Publish one tick's rows (``WorldSim.finish_tick``, with the followers' formation
        health: ``RunRecorder.add_tick``), then the map if it is due."""
        for chunk in tick_payloads(rows, self._n_agents):
            self._tick_pub.put(encode_tick(chunk, check=False))  # built validated
        self.publish_map()

    def undeclare(self) -> None:
        for publisher in (self._tick_pub, self._map_pub):
            publisher.undeclare()
