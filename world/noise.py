"""Sensor and actuation noise streams keyed by (seed, agent, tick, channel, phase) (design §5).

Every draw of one agent in one tick comes from one block of standard normals drawn by a
``numpy.random.Generator`` seeded with ``(seed, agent, tick)``; each control step of a driving
follower has a block of its own, seeded with ``(seed, agent, tick, step + 1)`` (numpy seeds
``[s, a, t, 0]`` exactly like ``[s, a, t]``: step 0 keyed by its index would share the tick's
block). Each (channel, phase) pair owns a fixed slot of :data:`SLOT` values in a block. So a
draw depends only on its key, never on the order in which processes ask (any process layout
gives the same run), and a tick's many readings cost one generator (seeding one is most of a
draw's cost) — the block is remembered for the few ticks that still ask for it.
"""
from __future__ import annotations

import functools

import numpy as np

# The leader reading's range and bearing, odometry, the move's actuation; then (added with the
# honest rod-end reading, design §5) the rod end's own range and bearing, the snap's actuation,
# GPS of the follower and of its leader, the oracle velocity. Numbers are part of the streams'
# keys: never renumber one. Then (``--motion drive``, design §4) the actuation noise of a control
# step's speed and turn rate, and the step's odometry, compass and slope (tilt) readings.
CHANNELS = {"range": 1, "bearing": 2, "velocity": 3, "move": 4, "rod-range": 5,
            "rod-bearing": 6, "snap": 7, "gps": 8, "leader-gps": 9, "oracle-velocity": 10,
            "speed": 11, "turn": 12, "odometry": 13, "compass": 14, "slope": 15}
PHASES = {"pre": 0, "moved": 1, "settled": 2, "act": 3}
SLOT = 3  # values per (channel, phase): GPS draws (x, y, z)
BLOCK = (max(CHANNELS.values()) + 1) * len(PHASES) * SLOT


def gaussian_scalar(seed: int, agent: int, tick: int, channel: str, phase: str,
                    sigma: float, step: int | None = None) -> float:
    """One draw of :func:`gaussian` as a float (0.0 without touching a generator if sigma is 0)."""
    if sigma == 0:
        return 0.0
    return float(gaussian(seed, agent, tick, channel, phase, sigma, step=step)[0])


def gaussian(
    seed: int, agent: int, tick: int, channel: str, phase: str, sigma: float, size: int = 1,
    step: int | None = None,
) -> np.ndarray:
    """Draw ``size`` N(0, sigma²) values from the stream named by the key (``step``, a control
    step's index, selects that step's block; None: the tick's block).

    Returns zeros (without touching a generator) when ``sigma`` is 0.

    >>> a = gaussian(7, 1, 5, "range", "pre", 0.1)
    >>> b = gaussian(7, 1, 5, "range", "pre", 0.1)
    >>> bool(a[0] == b[0]) and bool(a[0] != gaussian(7, 2, 5, "range", "pre", 0.1)[0])
    True
    >>> bool(a[0] != gaussian(7, 1, 5, "range", "pre", 0.1, step=0)[0])
    True
    """
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {sorted(CHANNELS)}, got {channel!r}")
    if phase not in PHASES:
        raise ValueError(f"phase must be one of {sorted(PHASES)}, got {phase!r}")
    if sigma < 0:
        raise ValueError(f"sigma must be non-negative, got {sigma}")
    if not 1 <= size <= SLOT:
        raise ValueError(f"size must be in [1, {SLOT}], got {size}")
    if sigma == 0:
        return np.zeros(size)
    if step is not None and step < 0:
        raise ValueError(f"step must be non-negative, got {step}")
    start = (CHANNELS[channel] * len(PHASES) + PHASES[phase]) * SLOT
    key = (seed, agent, tick) if step is None else (seed, agent, tick, step + 1)
    return sigma * _block(key)[start:start + size]


@functools.lru_cache(maxsize=8192)
def _block(key: tuple[int, ...]) -> np.ndarray:
    """The standard normals of one agent in one tick, or one control step of it (read-only;
    remembered for a while)."""
    block = np.random.default_rng(list(key)).standard_normal(BLOCK)
    block.flags.writeable = False
    return block
