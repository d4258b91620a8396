"""Sensor and actuation noise streams (design §5).

Two kinds of stream, both keyed by what the world counts, never by what an agent says:

- **readings** (:func:`reading_noise`): the ``n``-th sensing the world served follower ``agent``
  in ``tick`` (``n`` the world's own count, from 0, :mod:`world.sensing`) draws every channel
  it carries — the leader's range and bearing, the rod end's, GPS, the oracle velocity, a
  driving robot's compass and slope — from one block of its own, seeded with
  ``(seed, agent, tick, 0, n + 1)``. Two readings never share a draw, however they are asked.
- **the world's own** (:func:`gaussian`): actuation (a move, a snap, a control step's speed and
  turn) and odometry, keyed by ``(seed, agent, tick, channel, phase)``; the tick's block is
  seeded with ``(seed, agent, tick)``, control step ``s``'s with ``(seed, agent, tick, s + 1)``
  (numpy seeds ``[s, a, t, 0]`` exactly like ``[s, a, t]``: step 0 keyed by its bare index
  would share the tick's block; for the same reason a reading's key has a 0 before a count
  that starts at 1). The world does each of these once per tick (or control step, in the
  order it enforces), so their keys are its own counts too.

Each (channel, phase) pair, or each channel of a reading, owns a fixed slot of :data:`SLOT`
values in a block. So a draw depends only on its key, never on the order in which processes
ask (any process layout gives the same run), and a block costs one generator (seeding one is
most of a draw's cost) — blocks are remembered for the few ticks that still ask for them.
"""
from __future__ import annotations

import functools
import os
import threading

import numba
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
READING_BLOCK = (max(CHANNELS.values()) + 1) * SLOT


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
    """Draw ``size`` N(0, sigma²) values from the world's own stream named by the key
    (``step``, a control step's index, selects that step's block; None: the tick's block).

    Returns zeros (without touching a generator) when ``sigma`` is 0.

    >>> a = gaussian(7, 1, 5, "move", "act", 0.1)
    >>> b = gaussian(7, 1, 5, "move", "act", 0.1)
    >>> bool(a[0] == b[0]) and bool(a[0] != gaussian(7, 2, 5, "move", "act", 0.1)[0])
    True
    >>> bool(a[0] != gaussian(7, 1, 5, "move", "act", 0.1, step=0)[0])
    True
    """
    _check(channel, sigma, size)
    if phase not in PHASES:
        raise ValueError(f"phase must be one of {sorted(PHASES)}, got {phase!r}")
    if sigma == 0:
        return np.zeros(size)
    if step is not None and step < 0:
        raise ValueError(f"step must be non-negative, got {step}")
    start = (CHANNELS[channel] * len(PHASES) + PHASES[phase]) * SLOT
    key = (seed, agent, tick) if step is None else (seed, agent, tick, step + 1)
    return sigma * _block(key, BLOCK)[start:start + size]


def reading_noise(seed: int, agent: int, tick: int, reading: int, channel: str, sigma: float,
                  size: int = 1) -> np.ndarray:
    """Draw ``size`` N(0, sigma²) values for ``channel`` of the ``reading``-th sensing (the
    world's count, from 0) of ``agent`` in ``tick``; zeros (no generator) when ``sigma`` is 0.

    >>> a = reading_noise(7, 1, 5, 0, "range", 0.1)
    >>> bool(a[0] == reading_noise(7, 1, 5, 0, "range", 0.1)[0])
    True
    >>> bool(a[0] != reading_noise(7, 1, 5, 1, "range", 0.1)[0])
    True
    """
    _check(channel, sigma, size)
    if reading < 0:
        raise ValueError(f"reading must be non-negative, got {reading}")
    if sigma == 0:
        return np.zeros(size)
    start = CHANNELS[channel] * SLOT
    return sigma * _block((seed, agent, tick, 0, reading + 1), READING_BLOCK)[start:start + size]


def reading_scalar(seed: int, agent: int, tick: int, reading: int, channel: str,
                   sigma: float) -> float:
    """One draw of :func:`reading_noise` as a float (0.0 without a generator if sigma is 0)."""
    if sigma == 0:
        return 0.0
    return float(reading_noise(seed, agent, tick, reading, channel, sigma)[0])


def _check(channel: str, sigma: float, size: int) -> None:
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {sorted(CHANNELS)}, got {channel!r}")
    if sigma < 0:
        raise ValueError(f"sigma must be non-negative, got {sigma}")
    if not 1 <= size <= SLOT:
        raise ValueError(f"size must be in [1, {SLOT}], got {size}")


@functools.lru_cache(maxsize=8192)
def _block(key: tuple[int, ...], size: int) -> np.ndarray:
    """``size`` standard normals of one key (read-only; remembered for a while): those of
    ``numpy.random.default_rng(list(key))``. numpy's own path (a ``SeedSequence`` hashing the
    key, a fresh ``PCG64`` seeded from it) costs about 10 µs, most of it in Python-level
    bookkeeping; a block per reading made it the world's largest cost per request. So the
    key's words (:func:`_words`) are hashed by :func:`_seed_words` (``SeedSequence``'s
    algorithm, compiled), the generator's state follows by ``PCG64``'s own seeding rule
    (:func:`_pcg64_state`), and one kept generator draws from it: the same numbers
    (``tests/test_sensing.py`` checks them against numpy's path) at about half the cost."""
    state = _pcg64_state(*(int(w) for w in _seed_words(np.array(_words(key), dtype=np.uint32))))
    with _GENERATOR_LOCK:
        _GENERATOR.bit_generator.state = state
        block = _GENERATOR.standard_normal(size)
    block.flags.writeable = False
    return block


# one generator, re-seeded for every block; a lock, not one per thread: the world's requests are
# answered on Zenoh's threads, whose Python thread state (and so any thread-local) lasts one call
_GENERATOR = np.random.Generator(np.random.PCG64(0))
_GENERATOR_LOCK = threading.Lock()


def _fresh_lock() -> None:  # a child forked while another thread held the lock gets it free
    global _GENERATOR_LOCK
    _GENERATOR_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_fresh_lock)


def warm_up() -> None:
    """Load (or, the first time, compile) the block's compiled hash now, not at a first draw."""
    _seed_words(np.zeros(3, dtype=np.uint32))


# numpy's SeedSequence constants (numpy/random/bit_generator.pyx, after Melissa O'Neill's
# seed_seq_fe): the hash of the entropy into a pool of 4 words, and of the pool into state
_INIT_A, _MULT_A, _INIT_B, _MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R, _XSHIFT = 0xCA01F9DD, 0x4973F715, 16
_PCG_MULTIPLIER = (2549297995355413924 << 64) + 4865540595714422341  # PCG's 128-bit LCG
_M32, _M128 = 0xFFFFFFFF, (1 << 128) - 1


@numba.njit(cache=True)
def _seed_words(entropy: np.ndarray) -> np.ndarray:
    """The 4 uint64 words ``SeedSequence(entropy).generate_state(4, np.uint64)`` gives for
    ``entropy`` (uint32 words, no spawn key): every product taken modulo 2**32."""
    m = np.uint64(_M32)
    shift = np.uint64(_XSHIFT)

    def hashmix(value, const, multiplier):  # the value hashed, and the next constant
        value = (value ^ const) & m
        const = (const * multiplier) & m
        value = (value * const) & m
        return value ^ (value >> shift), const

    def mix(x, y):
        result = (np.uint64(_MIX_L) * x - np.uint64(_MIX_R) * y) & m
        return result ^ (result >> shift)

    mult_a, count = np.uint64(_MULT_A), entropy.shape[0]
    pool, const = np.zeros(4, np.uint64), np.uint64(_INIT_A)
    for i in range(4):
        pool[i], const = hashmix(np.uint64(entropy[i]) if i < count else np.uint64(0), const,
                                 mult_a)
    for source in range(4):
        for target in range(4):
            if source != target:
                hashed, const = hashmix(pool[source], const, mult_a)
                pool[target] = mix(pool[target], hashed)
    for source in range(4, count):
        for target in range(4):
            hashed, const = hashmix(np.uint64(entropy[source]), const, mult_a)
            pool[target] = mix(pool[target], hashed)
    out, const = np.zeros(4, np.uint64), np.uint64(_INIT_B)
    for i in range(8):  # 8 uint32 words, read as 4 little-endian uint64
        value, const = hashmix(pool[i % 4], const, np.uint64(_MULT_B))
        out[i // 2] |= value << np.uint64(32 * (i % 2))
    return out


def _pcg64_state(w0: int, w1: int, w2: int, w3: int) -> dict:
    """The state ``PCG64`` takes from a seed sequence's 4 words: the 128-bit seed
    ``w0·2**64 + w1`` and stream ``w2·2**64 + w3``, set as PCG's ``srandom`` does (the
    increment is the stream shifted left, odd; two LCG steps around adding the seed)."""
    increment = (((w2 << 64 | w3) << 1) | 1) & _M128
    state = ((increment + (w0 << 64 | w1)) * _PCG_MULTIPLIER + increment) & _M128
    return {"bit_generator": "PCG64", "state": {"state": state, "inc": increment},
            "has_uint32": 0, "uinteger": 0}


def _words(key: tuple[int, ...]) -> list[int]:
    """The 32-bit words numpy's ``SeedSequence`` makes of a list of non-negative ints: each
    int's, least significant first, at least one."""
    words = []
    for part in key:
        if part < 0:
            raise ValueError(f"a noise key holds non-negative ints, got {part}")
        words.append(part & 0xFFFFFFFF)
        part >>= 32
        while part:
            words.append(part & 0xFFFFFFFF)
            part >>= 32
    return words
