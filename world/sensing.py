"""The world's sensing model (design §5): what a follower's sensors read, in which order, with
which noise draw, and what the floor learns from it (:mod:`world.floor`).

**Sensing is an act the world sequences.** In each tick a follower gets its readings in the
order of design §4, each once: the pre-move sensing (the one ``world/sense`` serves, once, before
any action), then one sensing in reply to each action — after its move (a teleport move, or each
control step of a driving follower) and after it settled (the snap). The world counts them
(:attr:`TickSensing.count`), and the ``n``-th draws its noise from the block keyed by ``n``
(:func:`world.noise.reading_noise`), so no two readings share a draw, whatever an agent asks;
a repeated or out-of-order request is refused before anything is read. A tick redone after a
restart (lockstep) starts the count again, and so draws the same noise at the same poses.

**The rod end is found by looking.** A sensing carries the rod end only when the follower looks
for it: after its move (a driving follower after the move phase's last step, and at every step
of its correction window), when it settles, and before moving if it asks (``look``; always in an
initial tick, where the follower is placed by that reading). Each look before it settles is
counted: the tick's **required range** is the longest distance it looked from
(:attr:`TickSensing.looked`), from tick ``init_ticks`` on. The settled sensing's look is not
counted: it is taken where the snap put the follower, at its rod end up to the snap's landing
error, which no estimator chooses (design §4).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from protocol.config import RunConfig
from world import floor
from world.noise import reading_noise, reading_scalar
from world.surfaces import Surface


@dataclass
class TickSensing:
    """What a follower's sensors did in one tick (world-private).

    Attributes
    ----------
    count : int
        Readings served so far (the next one's noise key).
    looked : float or None
        The longest distance it looked for its rod end from, counted (design §4).
    rod_error : ndarray (2,) or None
        The error of its last rod-end reading, None if its last look found none: a snap moves
        by that reading.
    pre, settled : ndarray (2,) or None
        The leader reading (xy) of its pre-move and of its settled sensing.
    events : list of world.floor.FloorEvent
        What the floor learns of, and suffers, in this tick, in order.
    """

    count: int = 0
    looked: float | None = None
    rod_error: np.ndarray | None = None
    pre: np.ndarray | None = None
    settled: np.ndarray | None = None
    events: list[floor.FloorEvent] = field(default_factory=list)


@dataclass(frozen=True)
class Truth:
    """Where things are when a follower reads (absolute xy; world-private).

    ``rod_end`` is None when the follower does not look for it; ``counted``: whether the look's
    distance counts in the tick's required range; ``heading`` is a driving robot's (compass and
    slope readings), else None; ``oracle`` the oracle velocity's true value when it is sent."""

    own: np.ndarray
    leader: np.ndarray
    rod_end: np.ndarray | None = None
    counted: bool = False
    heading: np.ndarray | None = None
    oracle: np.ndarray | None = None


class Sensors:
    """A follower's range/bearing sensor and its other instruments, as the world applies them.

    Parameters
    ----------
    config : RunConfig
        The run (its σ, seed, sensing range and whether followers have GPS).
    surface : Surface
        The hidden surface (GPS height, the slope under a driving robot).
    """

    def __init__(self, config: RunConfig, surface: Surface) -> None:
        self.config, self.surface = config, surface

    def sees(self, tick: int, distance: float) -> bool:
        """Whether a rod end ``distance`` away is in sensing range (always in initial ticks,
        where the follower is placed by the reading)."""
        return tick < self.config.init_ticks or distance <= self.config.sensing_range

    def read(self, agent: int, tick: int, sensed: TickSensing, truth: Truth,
             role: str = "") -> dict:
        """The next reading of follower ``agent`` in ``tick`` (counted in ``sensed``): the
        :class:`protocol.messages.Sensing` fields it sets — the leader's range and bearing,
        the rod end's offset if the follower looks and it is in range, GPS when the run has
        it, the oracle velocity when sent, a driving robot's compass and slope. Its errors
        go to ``sensed.events`` for the floor; ``role`` (``pre``, ``settled`` or empty) says
        whether the leader reading is kept as the tick's pre-move or settled one (for the
        ``persist`` counterfactual)."""
        cfg, n = self.config, sensed.count
        sensed.count += 1
        offset = truth.leader - truth.own
        dx, dy = float(offset[0]), float(offset[1])
        n_r = reading_scalar(cfg.seed, agent, tick, n, "range", cfg.noise_range)
        n_theta = reading_scalar(cfg.seed, agent, tick, n, "bearing", cfg.noise_bearing)
        r, theta = math.hypot(dx, dy) + n_r, math.atan2(dy, dx) + n_theta
        theta = math.atan2(math.sin(theta), math.cos(theta))
        error = _error(offset, n_r, n_theta)
        if role == "pre":
            sensed.pre = _polar(r, theta)
        elif role == "settled":
            sensed.settled = _polar(r, theta)
        sensed.events.append(floor.range_bearing(error, offset, cfg.noise_range,
                                                 cfg.noise_bearing))
        rod = None
        if truth.rod_end is not None:
            offset = truth.rod_end - truth.own
            distance = math.hypot(float(offset[0]), float(offset[1]))
            if truth.counted and tick >= cfg.init_ticks:
                sensed.looked = max(distance, sensed.looked or 0.0)
            sensed.rod_error = None
            if self.sees(tick, distance):
                sensed.rod_error = self._rod_error(agent, tick, n, offset)
                sensed.events.append(floor.range_bearing(sensed.rod_error, offset,
                                                         cfg.noise_range, cfg.noise_bearing))
                rod = as_pair(offset + sensed.rod_error)
        fields: dict = {"tick": tick, "r": r, "theta": theta, "rod": rod}
        if cfg.gps:
            gps = self._gps(agent, tick, n, "gps", truth.own)
            sensed.events.append(floor.read(truth.own[:2] - np.asarray(gps[:2]),
                                            cfg.noise_gps**2 * np.eye(2)))
            fields.update(gps=gps, leader_gps=self._gps(agent, tick, n, "leader-gps",
                                                        truth.leader))
        if truth.oracle is not None:
            noise = reading_noise(cfg.seed, agent, tick, n, "oracle-velocity",
                                  cfg.noise_velocity, 2)
            fields["oracle_velocity"] = as_pair(truth.oracle + noise)
            sensed.events.append(floor.read(cfg.comm_period * noise,
                                            (cfg.noise_velocity * cfg.comm_period)**2 * np.eye(2)))
        if truth.heading is not None:
            fields["compass"], fields["slope"] = self._attitude(agent, tick, n, truth)
        return fields

    def _rod_error(self, agent: int, tick: int, n: int, offset: np.ndarray) -> np.ndarray:
        """The error of reading ``n``'s rod-end reading at the true local ``offset``: the same
        range/bearing sensor as the leader's, channels of its own."""
        cfg = self.config
        n_r = reading_scalar(cfg.seed, agent, tick, n, "rod-range", cfg.noise_range)
        n_theta = reading_scalar(cfg.seed, agent, tick, n, "rod-bearing", cfg.noise_bearing)
        return _error(offset, n_r, n_theta)

    def _gps(self, agent: int, tick: int, n: int, channel: str,
             pos: np.ndarray) -> tuple[float, float, float]:
        """A GPS reading ``(x, y, z)`` of ``pos`` on ``channel`` (``--noise-gps`` σ each)."""
        cfg = self.config
        exact = np.array([pos[0], pos[1], self.surface.height(pos)], dtype=float)
        reading = exact + reading_noise(cfg.seed, agent, tick, n, channel, cfg.noise_gps, 3)
        return float(reading[0]), float(reading[1]), float(reading[2])

    def _attitude(self, agent: int, tick: int, n: int,
                  truth: Truth) -> tuple[float, tuple[float, float]]:
        """A driving robot's compass and tilt readings: the angle of its heading in the local
        frame, and the slope ``(∂F/∂x, ∂F/∂y)`` under it read as two tilt angles
        (``atan ∂F/∂x``, ``atan ∂F/∂y``); each angle with the bearing sensor's σ (the compass
        is what bearings are referenced to)."""
        cfg, sigma = self.config, self.config.noise_bearing
        angle = math.atan2(truth.heading[1], truth.heading[0]) + reading_scalar(
            cfg.seed, agent, tick, n, "compass", sigma)
        tilt = np.arctan(np.asarray(self.surface.gradient(truth.own), dtype=float))
        tilt = tilt + reading_noise(cfg.seed, agent, tick, n, "slope", sigma, 2)
        return math.atan2(math.sin(angle), math.cos(angle)), as_pair(np.tan(tilt))


def _error(offset: np.ndarray, n_r: float, n_theta: float) -> np.ndarray:
    """The xy error of a range/bearing reading of a point at the true local ``offset`` with
    range and bearing errors ``n_r``, ``n_theta``: ``polar(r + n_r, θ + n_θ) − polar(r, θ)``,
    an exact zero when both are (so every σ = 0 reads the truth bit for bit)."""
    if n_r == 0.0 and n_theta == 0.0:
        return np.zeros(2)
    r, theta = math.hypot(float(offset[0]), float(offset[1])), math.atan2(offset[1], offset[0])
    return _polar(r + n_r, theta + n_theta) - _polar(r, theta)


def _polar(r: float, theta: float) -> np.ndarray:
    return np.array([r * math.cos(theta), r * math.sin(theta)])


def as_pair(v: np.ndarray | None) -> tuple[float, float] | None:
    """The xy vector ``v`` (2,) as a message's pair of floats (None stays None)."""
    return None if v is None else (float(v[0]), float(v[1]))
