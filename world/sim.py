"""The world's physics and bookkeeping, free of any transport (design §3–§5, §7).

:class:`WorldSim` owns the hidden surface and every agent's absolute pose. The Zenoh service
(``world.service``) and the in-memory layout (``swarm.local``) turn requests into calls of
:meth:`sense` and :meth:`act` (:meth:`drive`, :meth:`move`, :meth:`snap`), and tick events
into :meth:`open_tick` (or :meth:`start_tick`) and :meth:`finish_tick`. Agents may be at
different ticks (pipelined lockstep, design §4); each begins a tick with its first request for
it. Requests that break the protocol's rules raise :class:`RequestError` (answered as an
error reply); conditions that end the run (leaving the surface's domain) raise
:class:`RunEnded`, and the run then ends at the earliest tick such a condition met, whatever
the order in which agents got there (:attr:`WorldSim.end_tick`, design §7). Agents are told why
(:attr:`WorldSim.end_reason`), never where: absolute coordinates are the world's
(:attr:`WorldSim.end_detail`, for its log and ``summary.json``).

Sensing is honest (design §5): every reading an agent gets passes through its own noise channel
(:mod:`world.noise`) — the leader's range and bearing, the rod end's range and bearing, odometry,
GPS — and every move, the snap included, through actuation noise. With every σ = 0 each noise
term is an exact zero, so the numbers are the noise-free ones bit for bit, with one exception
that no noise is behind: a driving robot's slope reading is ``tan(arctan ∇F)`` (the tilt
sensor reads angles, :meth:`_attitude`), which can differ from ``∇F`` in the last bit.

With ``motion = "drive"`` (design §4) a follower is a unicycle robot (:mod:`world.motion`): it
sends :meth:`control` steps (speed and turn rate, within the run's limits, with actuation noise
on both) and a final :meth:`snap` that settles it where it stands, with its own heading. Each
step is answered with what its sensors read after it: the range/bearing readings, its compass,
the slope under it and its odometry over the step (see :meth:`control` for the noise).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from protocol.config import RunConfig
from protocol.messages import ActResult, ActSensing, Control, Drive, Message, Move, Sensing, Snap
from world import floor, geometry, motion, noise
from world.noise import gaussian, gaussian_scalar
from world.sensing import Sensors, TickSensing, Truth, as_pair
from world.surfaces import Surface, surface_leader_start

MAX_OFFSET = 1e6


class RequestError(ValueError):
    """An agent's request that the world refuses; the message names the problem."""


class TickMissed(RequestError):
    """A request from an agent that already missed the current tick (realtime mode)."""


class RunEnded(RuntimeError):
    """A condition that ends the run early (the result is written, marked incomplete): the
    run keeps the ticks before the earliest one at which such a condition was met. Its message
    is what agents are told (:attr:`WorldSim.end_reason`: no absolute coordinates)."""


@dataclass(frozen=True)
class TickRecord:
    """What one agent did in one tick, kept until the tick is complete for every agent."""

    estimate: np.ndarray | None
    lost: bool
    missed: bool
    drive: DriveRecord | None = None
    controls: tuple[ControlStep, ...] = ()


@dataclass(frozen=True)
class ControlStep:
    """One control step a driving follower drove (``controls.csv``, design §7): the commanded
    speed and turn rate, and those achieved after actuation noise."""

    step: int
    speed: float
    turn: float
    achieved_speed: float
    achieved_turn: float


@dataclass(frozen=True)
class DriveRecord:
    """What a driving follower's control steps did in one tick (design §7, ``--motion drive``):
    the shortfall of its move phase (None in the initial ticks, which estimate nothing), the
    distance from where it settled to the rod end it drove onto (None when lost), the arc
    length it drove and how many steps a speed or turn limit bound."""

    reach_error: float | None
    snap_error: float | None
    path_length: float
    saturated_steps: int


@dataclass
class DriveTick:
    """A driving follower's control steps in the tick it is in (world-private)."""

    step: int = 0  # the next control step expected
    goal: np.ndarray | None = None  # where the move phase is heading (absolute xy)
    reach_error: float | None = None
    sees_rod: bool = True  # whether the rod end is in range after the move phase
    path_length: float = 0.0
    speed: float = 0.0  # the speed the last step drove (at rest when the tick begins)
    saturated: int = 0
    controls: list[ControlStep] = field(default_factory=list)  # the steps driven so far
    # the errors of the step odometry readings sent so far, summed (xy)
    odometry_error: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass
class AgentState:
    """Absolute pose, the tick it is in, and per-tick records of one agent (world-private).

    In pipelined lockstep agents are at different ticks: everything another agent or a row
    needs is read from the per-tick records (``settled``, ``headings``, ``records``), never
    from the current pose."""

    pos: np.ndarray
    heading: np.ndarray
    tick: int = -1
    settled: dict[int, np.ndarray] = field(default_factory=dict)
    headings: dict[int, np.ndarray] = field(default_factory=dict)
    # what a driving follower told of its heading as it settled at each tick (Snap's heading),
    # relayed to its successor with that tick's readings
    told: dict[int, tuple[float, float]] = field(default_factory=dict)
    records: dict[int, TickRecord] = field(default_factory=dict)
    # a driving follower's: its step odometry readings' errors summed over each settled tick
    odometry_errors: dict[int, np.ndarray] = field(default_factory=dict)
    # what its sensors did in each tick it began (world.sensing), until the tick after is done
    sensed: dict[int, TickSensing] = field(default_factory=dict)
    # the requests of the tick it is in, in order; and per tick, what an undone attempt of it
    # had requested (a rollback, or a world resumed from its checkpoint): a redo must repeat
    # it, since it draws the same noise
    requests: list = field(default_factory=list)
    redo: dict[int, tuple] = field(default_factory=dict)
    begun: tuple = ()  # (pos, heading[, leader velocity, leader time]) when ``tick`` began
    estimate: np.ndarray | None = None
    acted: str = ""
    lost: bool = False
    missed: bool = False
    drive: DriveTick = field(default_factory=DriveTick)

    def reset_tick(self) -> None:
        """Forget what the agent did in the tick it is in."""
        self.estimate, self.acted, self.lost, self.missed = None, "", False, False
        self.drive = DriveTick()
        self.requests = []


def resolve_leader_start(config: RunConfig, surface: Surface) -> tuple[float, float, float, float]:
    """The run's leader start: the config's, else the surface's default (ValueError if none)."""
    if config.leader_start is not None:
        return config.leader_start
    start = surface_leader_start(surface)
    if start is None:
        raise ValueError(
            f"surface {config.surface!r} has no default leader start: give leader_start"
        )
    return tuple(float(x) for x in start)  # type: ignore[return-value]


DEFAULT_SPEED_FACTOR = 2.0
"""``--max-speed``'s default: this many times the leader's speed at its start (design §4)."""


def leader_speed(config: RunConfig, surface: Surface) -> float:
    """The leader's speed along the surface at its start, ``|v|_g`` (m of arc per time unit;
    constant along its geodesic)."""
    start = np.asarray(resolve_leader_start(config, surface), dtype=float)
    velocity = start[2:]
    return float(math.sqrt(velocity @ geometry.metric(surface, start[:2]) @ velocity))


def default_max_speed(config: RunConfig, surface: Surface) -> float:
    """The default top speed of a driving follower: :data:`DEFAULT_SPEED_FACTOR` times the
    leader's speed."""
    return DEFAULT_SPEED_FACTOR * leader_speed(config, surface)


class WorldSim:
    """Ground truth of one run.

    Parameters
    ----------
    config : RunConfig
        The resolved run configuration (``leader_start`` must be set).
    surface : Surface
        The hidden surface.
    """

    def __init__(self, config: RunConfig, surface: Surface) -> None:
        if config.leader_start is None:
            raise ValueError("config.leader_start must be resolved before building the world")
        if config.drives and config.max_speed is None:
            raise ValueError("config.max_speed must be resolved before building a drive world")
        self.config = config
        self.surface = surface
        self.side = config.side_sign
        n = config.followers
        start = np.asarray(config.leader_start, dtype=float)
        # One tick past the end so the oracle velocity exists at the last tick.
        # NaN from where the ideal formation would leave the surface's domain (the run then
        # ends there too, when the agents get to it).
        self.ideal = geometry.ideal_formation(
            surface, start, n, config.spacing, config.comm_period, config.ticks + 1, self.side,
            until_domain_exit=True,
        )
        positions, headings = geometry.column(surface, start[:2], start[2:], n, config.spacing,
                                              self.side)
        self.agents = [AgentState(pos=p.copy(), heading=h.copy())
                       for p, h in zip(positions, headings)]
        # the noise's and the floor's compiled kernels, loaded now (compiled, the first time in
        # a checkout: about a second) rather than in the run's first request, which in realtime
        # has a deadline
        noise.warm_up()
        floor.warm_up()
        self.leader_velocity = start[2:].copy()
        self.leader_time = 0.0
        self._leader_at: dict[int, tuple[np.ndarray, float]] = {}  # (velocity, time) per tick
        self.tick = -1  # the newest tick opened (agents may be behind it)
        self.complete = -1  # the newest tick every agent is through (its rows are out)
        # the earliest tick at which the run met a condition that ends it, why (as agents are
        # told it: no absolute coordinates), and why and where (the world's log and summary)
        self.end_tick: int | None = None
        self.end_reason = ""
        self.end_detail = ""
        self._rod_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.sensors = Sensors(config, surface)
        # each follower's sensing floor through the last complete tick (index 0: the leader's,
        # unused)
        self.floors = [floor.FloorFilter() for _ in self.agents]

    # --- ticks ---------------------------------------------------------------------------------

    @property
    def n_agents(self) -> int:
        return len(self.agents)

    def time_of(self, tick: int) -> float:
        return tick * self.config.comm_period

    def open_tick(self, tick: int) -> None:
        """Let agents begin tick ``tick`` (must follow the previous one); each agent begins it
        with its first request for it, once it has settled at the tick before."""
        if tick != self.tick + 1:
            raise RuntimeError(f"tick {tick} cannot follow tick {self.tick}")
        self.tick = tick

    def start_tick(self, tick: int) -> None:
        """Open tick ``tick`` and begin it for every agent at once (all must be through the
        tick before): the unpipelined order of the in-memory layout and of realtime mode."""
        self.open_tick(tick)
        for agent in range(self.n_agents):
            self._begin(agent, tick)

    def _begin(self, agent: int, tick: int) -> None:
        state = self.agents[agent]
        if state.tick != tick - 1 or (tick > 0 and tick - 1 not in state.settled):
            raise RequestError(f"agent {agent} has not settled at tick {tick - 1}")
        state.tick = tick
        state.reset_tick()
        state.sensed[tick] = TickSensing()
        state.begun = (state.pos.copy(), state.heading.copy())
        if agent == 0:
            state.begun += (self.leader_velocity.copy(), self.leader_time)

    def rollback(self, agent: int, tick: int) -> None:
        """Undo whatever ``agent`` did in tick ``tick`` (its process vanished before the world
        had it through): it will redo the tick from the pose it had when it began it, and draw
        the same noise (its readings are counted again from the first), so the tick's numbers
        are those of an uninterrupted run. Nothing to do if the agent has not begun ``tick``.

        Because the noise is the same, the redo must request what the undone attempt did, in
        the same order (:meth:`_check_redo`): an agent that rejoined mid-tick on purpose and
        acted otherwise would read the same draws from another pose and could cancel them."""
        state = self.agents[agent]
        if state.tick != tick:
            return
        self.expect_redo(agent, tick, state.requests)
        state.pos, state.heading = state.begun[0].copy(), state.begun[1].copy()
        if agent == 0:
            self.leader_velocity, self.leader_time = state.begun[2].copy(), state.begun[3]
            self._leader_at.pop(tick, None)
        for record in (state.settled, state.headings, state.told, state.records,
                       state.odometry_errors, state.sensed):
            record.pop(tick, None)
        state.reset_tick()
        state.tick = tick - 1
        self._rod_cache.pop((agent + 1, tick), None)

    def is_settled(self, agent: int, tick: int) -> bool:
        return tick in self.agents[agent].settled

    def _settle(self, agent: int, tick: int) -> None:
        state = self.agents[agent]
        state.settled[tick] = state.pos.copy()
        state.headings[tick] = state.heading.copy()
        drive = None
        if self.config.drives and agent > 0 and state.drive.step:
            # a tick missed before its first control step drove nothing: its interval's
            # reading is then a teleport follower's (:meth:`_odometry`), never the exact truth
            state.odometry_errors[tick] = state.drive.odometry_error.copy()
        if agent > 0 and not self.config.drives:  # the interval's odometry, for the floor
            cfg = self.config
            error = (cfg.comm_period * self._velocity_noise(agent, tick)
                     if tick - 1 in state.settled else None)
            state.sensed[tick].events.append(
                floor.interval(error, (cfg.noise_velocity * cfg.comm_period) ** 2))
        if self.config.drives and agent > 0 and not state.missed:
            d = state.drive
            snap_error = None if state.lost else _dist(state.pos, self._leader_rod(agent, tick)[0])
            drive = DriveRecord(d.reach_error, snap_error, d.path_length, d.saturated)
        state.records[tick] = TickRecord(state.estimate, state.lost, state.missed, drive,
                                         tuple(state.drive.controls))
        if agent == 0:
            self._leader_at[tick] = (self.leader_velocity.copy(), self.leader_time)

    def mark_missed(self, agent: int) -> None:
        """``agent`` did not settle at the tick it is in (too late in realtime mode, or its
        process vanished): it keeps its pose, and its requests for this tick are refused."""
        state = self.agents[agent]
        state.missed = True
        self._settle(agent, state.tick)

    def finish_tick(self, tick: int) -> list[dict]:
        """Ground-truth rows of tick ``tick`` (the one after the last complete tick; every
        agent must have settled at it), one per agent (design §7 columns)."""
        j, cfg = tick, self.config
        if j != self.complete + 1:
            raise RuntimeError(f"tick {j} cannot be finished after tick {self.complete}")
        rows = []
        for k, state in enumerate(self.agents):
            if j not in state.settled:
                raise RuntimeError(f"agent {k} has not settled at tick {j}")
            pos, record = state.settled[j], state.records[j]
            row = {"tick": j, "t": self.time_of(j), "agent": k, "pos_x": pos[0], "pos_y": pos[1],
                   "missed": int(record.missed), "heading_x": state.headings[j][0],
                   "heading_y": state.headings[j][1]}
            if k > 0:
                ideal = self._leader_rod(k, j)[0]
                prev = state.settled.get(j - 1, pos)
                lead_now = self.agents[k - 1].settled[j]
                lead_prev = self.agents[k - 1].settled.get(j - 1, lead_now)
                persist_noise_free = prev + (lead_now - lead_prev)
                persist = self._persist(k, j, persist_noise_free)
                row.update(
                    estimator=cfg.estimator, ideal_x=ideal[0], ideal_y=ideal[1],
                    stay_range=_dist(prev, ideal),
                    persist_range=_dist(persist, ideal),
                    persist_range_noise_free=_dist(persist_noise_free, ideal),
                    floor_range=self.floors[k].tick(state.sensed[j].events),
                    lost=int(record.lost),
                    formation_error=_finite_or_none(_dist(pos, self.ideal[k, j])),
                )
                if record.estimate is not None:
                    row.update(est_x=record.estimate[0], est_y=record.estimate[1])
                if state.sensed[j].looked is not None:  # design §4: the longest look
                    row["required_range"] = state.sensed[j].looked
                if record.drive is not None:
                    row.update(reach_error=record.drive.reach_error,
                               snap_error=record.drive.snap_error,
                               path_length=record.drive.path_length,
                               saturated_steps=record.drive.saturated_steps)
            rows.append(row)
        self.complete = j
        for state in self.agents:  # keep only what velocities and baselines still need
            _drop_ticks_before(state.settled, j - 1)
            _drop_ticks_before(state.headings, j - 1)
            _drop_ticks_before(state.told, j)
            _drop_ticks_before(state.odometry_errors, j - 1)
            _drop_ticks_before(state.records, j)  # j's: control_rows
            _drop_ticks_before(state.sensed, j)  # j's settled reading: the next persist
            _drop_ticks_before(state.redo, j + 1)  # a complete tick is never redone
        _drop_ticks_before(self._leader_at, j)
        for key in [key for key in self._rod_cache if key[1] < j]:  # the next floor reads j's
            del self._rod_cache[key]
        return rows

    def control_time(self, tick: int, step: int) -> float:
        """The stamp of control step ``step`` of tick ``tick``: when it begins on the world's
        clock, ``t_j`` plus the durations of the tick's steps before it
        (:meth:`protocol.config.RunConfig.step_start`: a tick's steps fill its comm
        interval), so a robot's stamps increase from step to step and tick to tick."""
        return self.time_of(tick) + self.config.step_start(step)

    def control_rows(self, tick: int) -> list[dict]:
        """The ``controls.csv`` rows of tick ``tick``, the tick :meth:`finish_tick` finished
        last: every control step each driving follower drove in it, in agent then step order
        (none in a teleport run)."""
        if tick != self.complete:
            raise RuntimeError(f"tick {tick}'s control steps are read after finish_tick, "
                               f"and only until the next (the last finished is {self.complete})")
        return [{"tick": tick, "t": self.control_time(tick, c.step), "agent": k, "step": c.step,
                 "speed": c.speed, "turn": c.turn, "achieved_speed": c.achieved_speed,
                 "achieved_turn": c.achieved_turn}
                for k, state in enumerate(self.agents) for c in state.records[tick].controls]

    def state(self) -> dict:
        """JSON-ready state after the last complete tick, for :meth:`restore` (what agents
        already did in later ticks is left out: they redo it after a restart)."""
        j = self.complete
        if j < 0:
            velocity, time = self.leader_velocity, self.leader_time
            poses = [(a.pos, a.heading) for a in self.agents]
        else:
            velocity, time = self._leader_at[j]
            poses = [(a.settled[j], a.headings[j]) for a in self.agents]
        return {
            "tick": j,
            "leader_velocity": velocity.tolist(),
            "leader_time": time,
            "floors": [f.state() for f in self.floors],
            "agents": [
                {"pos": pos.tolist(), "heading": heading.tolist(),
                 "settled": {str(t): p.tolist() for t, p in a.settled.items() if t <= j},
                 "settled_reading": _settled_reading(a, j),
                 "odometry_errors": {str(t): e.tolist() for t, e in a.odometry_errors.items()
                                     if t <= j}}
                for a, (pos, heading) in zip(self.agents, poses)
            ],
        }

    def restore(self, state: dict) -> None:
        """Continue from a :meth:`state` snapshot (floats round-trip exactly through JSON)."""
        if len(state["agents"]) != self.n_agents:
            raise ValueError(f"checkpoint has {len(state['agents'])} agents, "
                             f"config {self.n_agents}")
        self.tick = self.complete = int(state["tick"])
        self.leader_velocity = np.array(state["leader_velocity"], dtype=float)
        self.leader_time = float(state["leader_time"])
        self._leader_at = {self.tick: (self.leader_velocity.copy(), self.leader_time)}
        self.floors = [floor.FloorFilter.from_state(f) for f in state["floors"]]
        if len(self.floors) != self.n_agents:
            raise ValueError(f"checkpoint has {len(self.floors)} floors, config {self.n_agents}")
        for agent, saved in zip(self.agents, state["agents"]):
            agent.pos = np.array(saved["pos"], dtype=float)
            agent.heading = np.array(saved["heading"], dtype=float)
            agent.tick = self.tick
            agent.settled = {int(t): np.array(p, dtype=float) for t, p in saved["settled"].items()}
            agent.headings = {self.tick: agent.heading.copy()}
            agent.records = {}
            reading = saved["settled_reading"]
            agent.sensed = {self.tick: TickSensing(
                settled=None if reading is None else np.array(reading, dtype=float))}
            agent.odometry_errors = {int(t): np.array(e, dtype=float)
                                     for t, e in saved["odometry_errors"].items()}

    # --- requests ------------------------------------------------------------------------------

    def expect_redo(self, agent: int, tick: int, requests) -> None:
        """``agent`` will redo tick ``tick``, an attempt of which requested ``requests`` (in
        order; the longest attempt known is kept): :meth:`rollback`, and a world resumed from
        its checkpoint with the requests it had answered (:mod:`world.checkpoint`'s journal)."""
        state = self.agents[agent]
        if len(requests) > len(state.redo.get(tick, ())):
            state.redo[tick] = tuple(requests)

    def _check_redo(self, agent: int, tick: int, request: object) -> None:
        """Refuse a request of a tick redone (:meth:`expect_redo`) that differs from what the
        undone attempt requested at the same place (a deterministic agent redoes it exactly)."""
        if not 0 <= agent < self.n_agents:
            return  # refused by _check_request
        state = self.agents[agent]
        done = len(state.requests) if state.tick == tick else 0
        undone = state.redo.get(tick, ())
        if done < len(undone) and undone[done] != request:
            raise RequestError(f"agent {agent} redoes tick {tick}, undone by a restart: request "
                               f"{done + 1} must repeat what it asked before (the same noise "
                               "is drawn again)")

    def _check_request(self, agent: int, tick: int) -> None:
        """Refuse a request out of turn; an agent's first request for the tick after the one it
        settled at begins that tick for it."""
        if not 0 <= agent < self.n_agents:
            raise RequestError(f"unknown agent id {agent} "
                               f"(this run has agents 0..{self.n_agents - 1})")
        self.check_not_ended(tick)
        state = self.agents[agent]
        if tick < state.tick:
            raise TickMissed(f"tick {tick} is over: the world is at tick {self.tick}")
        if tick > self.tick:
            raise RequestError(f"request for tick {tick}, but the world is at tick {self.tick}")
        if tick > state.tick:
            self._begin(agent, tick)
        if state.missed:
            raise TickMissed(f"agent {agent} missed tick {tick}; wait for the next tick")

    def _check_follower_turn(self, agent: int, tick: int, *, settled_ok: bool = False) -> None:
        if agent == 0:
            raise RequestError("agent 0 is the leader: it has no leader to sense or follow")
        if not self.is_settled(agent - 1, tick):
            raise RequestError(f"agent {agent - 1} has not settled at tick {tick} yet")
        if self.is_settled(agent, tick) and not settled_ok:
            raise RequestError(f"agent {agent} already settled at tick {tick}")

    def drive(self, agent: int, tick: int, t: float) -> None:
        """The leader follows its geodesic to time ``t`` (which must be this tick's time)."""
        self._check_request(agent, tick)
        if agent != 0:
            raise RequestError(f"only the leader (agent 0) may drive, not agent {agent}")
        if self.is_settled(0, tick):
            raise RequestError(f"the leader already drove at tick {tick}")
        target = self.time_of(tick)
        if not math.isclose(t, target, rel_tol=1e-9, abs_tol=1e-9):
            raise RequestError(f"drive time {t} is not tick {tick}'s time {target}")
        leader = self.agents[0]
        if target > self.leader_time:
            try:
                leader.pos, self.leader_velocity = geometry.integrate_geodesic(
                    self.surface, leader.pos, self.leader_velocity, target - self.leader_time
                )
            except geometry.SurfaceDomainError as exc:
                raise self._end(tick, "the leader left the surface's domain", exc) from None
            leader.heading = self.leader_velocity.copy()
            self.leader_time = target
        self._settle(0, tick)

    def _persist(self, agent: int, tick: int, noise_free: np.ndarray) -> np.ndarray:
        """Where ``persist`` would have put follower ``agent`` at ``tick`` from the same noisy
        readings and actuation the follower had (design §6): from where it settled at
        ``tick - 1``, by its pre-move leader reading minus its settled one of ``tick - 1``, with
        its move's actuation noise (none in a drive run, where ``noise_move`` is refused).
        Without both readings (a tick it missed) the noise-free counterfactual stands in."""
        own, sensed = self.agents[agent].settled, self.agents[agent].sensed
        before, now = sensed.get(tick - 1), sensed.get(tick)
        if (tick - 1 not in own or before is None or before.settled is None or now is None
                or now.pre is None):
            return noise_free
        noise = self._move_noise(agent, tick) if tick >= self.config.init_ticks else np.zeros(2)
        return own[tick - 1] + now.pre - before.settled + noise

    def _move_noise(self, agent: int, tick: int) -> np.ndarray:
        """The actuation noise of ``agent``'s move to its estimate at ``tick``."""
        return gaussian(self.config.seed, agent, tick, "move", "act", self.config.noise_move, 2)

    def _velocity_noise(self, agent: int, tick: int) -> np.ndarray:
        """The noise of a teleport follower's odometry over the interval ending at ``tick``
        (one reading, revealed when it settles there: the interval's, not a sensing's)."""
        cfg = self.config
        return gaussian(cfg.seed, agent, tick, "velocity", "settled", cfg.noise_velocity, 2)

    def _read(self, agent: int, tick: int, role: str, look: bool) -> Sensing:
        """Follower ``agent``'s next reading in ``tick`` (:mod:`world.sensing`; counted, its
        noise keyed by the count): ``role`` is ``pre``, ``moved`` or ``settled``; ``look``:
        whether it looks for its rod end (counted in the required range unless settled). With
        the interval's odometry, the oracle velocity in the settled reading when sent, and what
        its leader told of its heading at ``tick`` (a driving leader's :class:`Snap`)."""
        cfg, state = self.config, self.agents[agent]
        oracle = None
        if role == "settled" and self._sends_oracle():
            oracle = (self.ideal[agent, tick + 1] - state.pos) / cfg.comm_period
            oracle = oracle if np.all(np.isfinite(oracle)) else None
        fields = self.sensors.read(agent, tick, state.sensed[tick], self._truth(
            agent, tick, look, counted=role != "settled", oracle=oracle), role)
        # relayed, not sensed: what its leader told of its own heading as it settled at tick
        told = self.agents[agent - 1].told.get(tick)
        return Sensing(**fields, velocity=self._odometry(agent, tick), shared_heading=told)

    def _truth(self, agent: int, tick: int, look: bool, counted: bool = True,
               oracle: np.ndarray | None = None) -> Truth:
        """Where things are as follower ``agent`` reads in ``tick`` (:class:`Truth`)."""
        state = self.agents[agent]
        return Truth(own=state.pos, leader=self.agents[agent - 1].settled[tick],
                     rod_end=self._leader_rod(agent, tick)[0] if look else None,
                     counted=counted, heading=state.heading if self.config.drives else None,
                     oracle=oracle)

    def sense(self, agent: int, tick: int, look: bool = False) -> Sensing:
        """Follower ``agent``'s pre-move sensing at ``tick``, in its local frame (design §5):
        served once, before any action (the later readings are the replies to its actions,
        :meth:`act`). It carries the rod end only if the follower ``look``s for it (then the
        distance counts in the tick's required range, from tick ``init_ticks`` on); a
        follower always looks in an initial tick, where it is placed by that reading."""
        self._check_redo(agent, tick, ("sense", bool(look)))
        self._check_request(agent, tick)
        self._check_follower_turn(agent, tick)
        state, cfg = self.agents[agent], self.config
        sensed = state.sensed[tick]
        if state.acted:
            raise RequestError(f"agent {agent} already acted at tick {tick}: the pre-move "
                               "sensing comes before its move (the later readings are the "
                               "replies to its actions)")
        if sensed.count:
            raise RequestError(f"agent {agent} already read its pre-move sensing at tick {tick}:"
                               " each reading comes once")
        self._leader_rod(agent, tick)  # a rod that leaves the domain ends the run here
        reading = self._read(agent, tick, "pre", look)
        if cfg.drives or tick < cfg.init_ticks:  # the floor decides here (no teleport move)
            sensed.events.append(floor.DECISION)
        state.requests.append(("sense", bool(look)))
        return reading

    def _sends_oracle(self) -> bool:
        """The oracle velocity is sent only to dictionary c's ``oracle`` variant (design §5)."""
        cfg = self.config
        return cfg.estimator == "edmd" and cfg.dictionary == "c" and cfg.velocity == "oracle"

    def move(self, agent: int, tick: int, offset: tuple[float, float]) -> None:
        """Follower moves by the local-frame ``offset`` toward its estimate (with actuation
        noise)."""
        self._check_request(agent, tick)
        self._check_follower_turn(agent, tick)
        state, cfg = self.agents[agent], self.config
        step = np.asarray(offset, dtype=float)
        if step.shape != (2,) or not np.all(np.isfinite(step)) or _norm(step) > MAX_OFFSET:
            raise RequestError(f"move offset must be two finite numbers of size <= {MAX_OFFSET:g}")
        if cfg.drives:
            raise RequestError("this run's motion is 'drive': send Control steps, not a move")
        if tick < cfg.init_ticks:
            raise RequestError(f"tick {tick} is an initial tick: followers only snap")
        if state.acted:
            raise RequestError(f"agent {agent} already moved at tick {tick}")
        noise = self._move_noise(agent, tick)
        self._relocate(agent, state.pos + step + noise)
        state.estimate = state.pos.copy()
        state.acted = "move"
        events = state.sensed[tick].events
        events += [floor.move(noise, cfg.noise_move ** 2, odometered=True), floor.DECISION]

    def snap(self, agent: int, tick: int,
             heading: tuple[float, float] | None = None) -> bool:
        """Follower moves by the rod-end offset it read last (after its move, or before it
        in an initial tick), with actuation noise, if that look found the rod end, and takes
        the heading of design §3 at the true rod end; returns False (lost) if it did not.

        The landing point is ``end + reading error + actuation noise``: the same point as
        ``pos + sensed offset + actuation noise``, written so that with no noise it is the
        rod end exactly. A driving follower settles where it stands instead, and may tell
        its ``heading`` (:class:`protocol.messages.Snap`), which its successor's readings of
        the tick carry as it was told."""
        self._check_request(agent, tick)
        self._check_follower_turn(agent, tick)
        state, cfg = self.agents[agent], self.config
        if heading is not None and not cfg.drives:
            raise RequestError("a teleporting follower takes its heading from its rod end: "
                               "it has none of its own to tell")
        if heading is not None and not (abs(heading[0]) <= math.pi and heading[1] >= 0.0):
            raise RequestError("a told heading must be an angle within [-pi, pi] and a "
                               "variance >= 0")
        if cfg.drives:
            settled = self._settle_driven(agent, tick)
            if heading is not None:
                state.told[tick] = (float(heading[0]), float(heading[1]))
            return settled
        if tick >= cfg.init_ticks and state.acted != "move":
            raise RequestError(f"agent {agent} must move to its estimate before snapping")
        sensed = state.sensed[tick]
        if tick < cfg.init_ticks and sensed.rod_error is None:
            raise RequestError(f"agent {agent} must look for its rod end (its pre-move sensing, "
                               f"look) before it snaps at initial tick {tick}")
        end, u = self._leader_rod(agent, tick)
        seen = sensed.rod_error is not None
        if seen:
            noise = gaussian(cfg.seed, agent, tick, "snap", "act", cfg.noise_move, 2)
            self._relocate(agent, end + sensed.rod_error + noise)
            state.heading = geometry.heading_at_rod_end(self.surface, end, u, self.side)
            sensed.events.append(floor.move(noise, cfg.noise_move ** 2, odometered=True))
        state.lost = not seen
        self._settle(agent, tick)
        return seen

    def _executed(self, agent: int, request: Control) -> tuple[float, float, bool]:
        """The speed and turn rate a control step really drives, and whether a limit bound:
        the command plus actuation noise (σ ``noise_speed``, ``noise_turn``), clipped to the
        robot's limits (design §4): ``|ω| ≤ max_turn``; ``|v| ≤ max_speed``, within
        ``accel_limit · δ`` of the speed of the step before (at rest when the tick begins),
        and at most ``accel_limit`` times the time left to stop before the tick settles
        (:meth:`protocol.config.RunConfig.stop_time`), so the robot is at rest when it
        settles. A step binds when its command is at a limit or what it drove was clipped."""
        cfg, drive = self.config, self.agents[agent].drive
        tick, step = request.tick, request.step
        noise = [gaussian_scalar(cfg.seed, agent, tick, channel, "act", sigma, step)
                 for channel, sigma in (("speed", cfg.noise_speed), ("turn", cfg.noise_turn))]
        accel = cfg.accel_limit
        change, stop = accel * cfg.step_duration(step), accel * cfg.stop_time(step)
        low = max(-cfg.max_speed, drive.speed - change, -stop)
        high = min(cfg.max_speed, drive.speed + change, stop)
        wanted = request.speed + noise[0], request.turn + noise[1]
        v = min(max(wanted[0], low), high)
        omega = min(max(wanted[1], -cfg.max_turn), cfg.max_turn)
        bound = (abs(request.speed) >= cfg.max_speed or abs(request.turn) >= cfg.max_turn
                 or v != wanted[0] or omega != wanted[1])
        return v, omega, bound

    def control(self, agent: int, request: Control) -> Sensing:
        """One control step of a driving follower (design §4 "Motion"): it drives at
        ``request.speed`` turning at ``request.turn`` for the step's duration
        (:meth:`protocol.config.RunConfig.step_duration`: a tick's steps fill its comm
        interval), with actuation noise and within the robot's limits (:meth:`_executed`), on
        the surface (:func:`world.motion.drive`); returns what its sensors read after the step.

        Its odometry reads the step's displacement (local frame) with noise of σ
        ``noise_velocity · √(δ T_c)`` per coordinate (δ the step's duration): a random walk
        whose spread over the tick's steps (one comm interval) is that of the odometry of
        design §5 over one interval (``noise_velocity · T_c``), so the tick's velocity reading,
        these readings summed over ``T_c`` (:meth:`_odometry`), has exactly the declared
        variance ``noise_velocity²``. The first step carries the move phase's goal, which the
        world records as the estimate (from tick ``init_ticks`` on); after the move phase's
        last step the world notes how far the follower is from that goal (``reach_error``)
        and whether the rod end is in range (else the tick is lost; the robot still has the
        correction window's steps to come to rest).
        """
        tick, step = request.tick, request.step
        self._check_request(agent, tick)
        self._check_follower_turn(agent, tick)
        state, cfg = self.agents[agent], self.config
        if not cfg.drives:
            raise RequestError("this run's motion is 'teleport': Control steps need motion "
                               "'drive'")
        drive = state.drive
        if step != drive.step:
            raise RequestError(f"control step {step} out of order: step {drive.step} is next")
        if step >= cfg.tick_steps:
            raise RequestError(f"control step {step} is past the tick's "
                               f"{cfg.tick_steps} steps: settle (snap) now")
        if abs(request.speed) > cfg.max_speed or abs(request.turn) > cfg.max_turn:
            raise RequestError(f"control (speed {request.speed:g}, turn {request.turn:g}) "
                               f"exceeds the limits (max speed {cfg.max_speed:g}, max turn "
                               f"{cfg.max_turn:g})")
        if (request.goal is not None) != (step == 0):
            raise RequestError("the goal is given with the first control step, and only then")
        if step == 0:
            drive.goal = state.pos + np.asarray(request.goal, dtype=float)
            if tick >= cfg.init_ticks:
                state.estimate = drive.goal.copy()
        v, omega, bound = self._executed(agent, request)
        duration = cfg.step_duration(step)
        start = state.pos
        try:
            pos, heading = motion.drive(self.surface, start, state.heading, v, omega, duration)
        except motion.SurfaceDomainError as exc:
            raise self._end(tick, f"agent {agent} drove off the surface's domain",
                            exc) from None
        state.pos, state.heading = pos, heading
        state.acted = "control"
        drive.step += 1
        drive.speed = v
        drive.path_length += abs(v) * duration
        drive.saturated += bound
        drive.controls.append(ControlStep(step, float(request.speed), float(request.turn),
                                          float(v), float(omega)))
        sigma = cfg.noise_velocity * math.sqrt(duration * cfg.comm_period)
        error = gaussian(cfg.seed, agent, tick, "odometry", "moved", sigma, 2, step=step)
        drive.odometry_error = drive.odometry_error + error
        # the floor moves by the step's odometry reading (world.floor); the reply looks for the
        # rod end after the move phase's last step and at each correction step (design §4)
        sensed = state.sensed[tick]
        sensed.events.append(floor.move(-error, sigma ** 2, odometered=False))
        readings = self.sensors.read(agent, tick, sensed,
                                     self._truth(agent, tick, look=step >= cfg.control_steps - 1))
        if drive.step == cfg.control_steps:
            if tick >= cfg.init_ticks:
                drive.reach_error = _dist(pos, drive.goal)
            drive.sees_rod = readings["rod"] is not None
        return Sensing(**readings, odometry=as_pair(pos - start + error))

    def _settle_driven(self, agent: int, tick: int) -> bool:
        """A driving follower ends its tick where its control steps took it, keeping its own
        heading (its rod normal comes from it, design §3); returns False (lost) if the rod end
        was out of range after the move phase."""
        state = self.agents[agent]
        if state.drive.step != self.config.tick_steps:
            raise RequestError(f"agent {agent} has done {state.drive.step} of the tick's "
                               f"{self.config.tick_steps} control steps: it cannot settle yet")
        state.lost = not state.drive.sees_rod
        self._settle(agent, tick)
        return not state.lost

    def act(self, agent: int, request: Message) -> ActResult | ActSensing:
        """Carry out one typed action of ``agent`` and say how it went (design §8): a
        :class:`Drive` is answered with :class:`ActResult`; a :class:`Move` or a
        :class:`Control` step with the sensing after it and a :class:`Snap` with the
        settled sensing, all as :class:`ActSensing`: each a reading of its own (design §5).
        The one dispatch of the Zenoh service and of the in-memory layout."""
        self._check_redo(agent, request.tick, request)
        reply = self._act(agent, request)
        self.agents[agent].requests.append(request)
        return reply

    def _act(self, agent: int, request: Message) -> ActResult | ActSensing:
        if isinstance(request, Drive):
            self.drive(agent, request.tick, request.t)
            return ActResult(tick=request.tick, moved=True)
        if isinstance(request, Control):
            sensing = self.control(agent, request)
            return ActSensing(**{**sensing.__dict__, "moved": True})
        if isinstance(request, Move):
            self.move(agent, request.tick, request.offset)
            sensing = self._read(agent, request.tick, "moved", look=True)
            moved = True
        elif isinstance(request, Snap):
            moved = self.snap(agent, request.tick, request.heading)
            sensing = self._read(agent, request.tick, "settled", look=True)
        else:
            raise RequestError(f"{type(request).__name__} is not an action")
        return ActSensing(**{**sensing.__dict__, "moved": moved})

    # --- helpers -------------------------------------------------------------------------------

    def _leader_rod(self, agent: int, tick: int) -> tuple[np.ndarray, np.ndarray]:
        """End and end tangent of agent ``agent - 1``'s rod where it settled at ``tick``
        (cached)."""
        key = (agent, tick)
        if key not in self._rod_cache:
            leader = self.agents[agent - 1]
            try:
                self._rod_cache[key] = geometry.rod_end(
                    self.surface, leader.settled[tick], leader.headings[tick],
                    self.config.spacing, self.side
                )
            except geometry.SurfaceDomainError as exc:
                raise self._end(tick, f"agent {agent - 1}'s rod leaves the surface's domain",
                                exc) from None
        return self._rod_cache[key]

    def _relocate(self, agent: int, pos: np.ndarray) -> None:
        contains = getattr(self.surface, "contains", None)
        if contains is not None and not contains(pos):
            raise self._end(self.agents[agent].tick,
                            f"agent {agent} would leave the surface's domain",
                            f"position {pos.tolist()}")
        self.agents[agent].pos = np.asarray(pos, dtype=float).copy()

    def _end(self, tick: int, reason: str, where: str | Exception) -> RunEnded:
        """Record that the run meets a condition that ends it at ``tick`` and return the error
        to raise. The earliest such tick wins (an agent behind in a pipelined run may meet one
        after an agent ahead did), so the run keeps the same ticks whatever the order.

        ``reason`` is what agents are told; ``where`` (the error that says where, or the
        position) is added for the world's own record (:attr:`end_detail`)."""
        if self.end_tick is None or tick < self.end_tick:
            self.end_tick, self.end_reason = tick, reason
            self.end_detail = f"{reason}: {where}"
        return RunEnded(reason)

    def ends_before(self, tick: int) -> bool:
        """Whether the run ends before tick ``tick`` (at :attr:`end_tick` or earlier)."""
        return self.end_tick is not None and tick >= self.end_tick

    def check_not_ended(self, tick: int) -> None:
        """Raise RunEnded if the run ends before ``tick`` (:meth:`ends_before`)."""
        if self.ends_before(tick):
            raise RunEnded(self.end_reason)

    @property
    def over(self) -> bool:
        """Every tick before :attr:`end_tick` is complete: the run ends here."""
        return self.end_tick is not None and self.complete + 1 >= self.end_tick

    def _odometry(self, agent: int, tick: int) -> tuple[float, float] | None:
        """The odometry's velocity reading over the last comm interval ``agent`` completed by
        ``tick`` (the one ending at ``tick`` once it settled there, else at ``tick - 1``),
        None before it completed one. Its noise belongs to the interval, not to the request:
        every reading of one interval (``settled`` at its end, ``pre`` and ``moved`` in the
        tick after) is the same reading.

        A teleport follower's is one draw per interval, σ ``noise_velocity`` per coordinate.
        A driving follower has one odometer: its reading is the sum of the step readings it got
        in the interval's tick (:meth:`control`: its control and correction steps) over
        ``T_c``, the true displacement plus their summed errors; an interval in which it drove
        no step (missed at once) gets a teleport follower's draw."""
        cfg, state = self.config, self.agents[agent]
        settled = state.settled
        last = tick if tick in settled else tick - 1
        if last not in settled or last - 1 not in settled:
            return None
        v = (settled[last] - settled[last - 1]) / cfg.comm_period
        if last in state.odometry_errors:  # driven (noise-free: exact zeros)
            v = v + state.odometry_errors[last] / cfg.comm_period
        elif cfg.noise_velocity != 0:
            v = v + self._velocity_noise(agent, last)
        return as_pair(v)


def _settled_reading(state: AgentState, tick: int) -> list[float] | None:
    """The leader reading (xy) of ``state``'s settled sensing at ``tick``, for a checkpoint."""
    sensed = state.sensed.get(tick)
    return None if sensed is None or sensed.settled is None else sensed.settled.tolist()


def _drop_ticks_before(by_tick: dict, first: int) -> None:
    """Delete the entries of ``by_tick`` (keyed by tick) for the ticks before ``first``."""
    for old in [t for t in by_tick if t < first]:
        del by_tick[old]


def _norm(v: np.ndarray) -> float:
    return math.hypot(float(v[0]), float(v[1]))


def _dist(a: np.ndarray, b: np.ndarray) -> float:
    return _norm(np.asarray(a) - np.asarray(b))


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None
