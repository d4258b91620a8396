"""The world process on Zenoh: queryables, the lockstep tick loop, results (SPEC §4, §8).

:class:`WorldService` wraps a :class:`world.sim.WorldSim` behind the ``world/sense/<id>`` and
``world/act/<id>`` queryables, publishes ``world/tick``, collects ``agent/<id>/rod`` and
``agent/<id>/obs`` samples, and writes the results folder as ticks complete.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from protocol import keys
from protocol.config import RunConfig
from protocol.messages import (
    ActRequest, ActResult, Done, Observation, ProtocolError, Rod, SenseRequest, TickStart,
    decode, encode, error_payload,
)
from world.results import RunRecorder
from world.sim import RequestError, RunEnded, WorldSim
from world.surfaces import Surface

log = logging.getLogger(__name__)

WRITE_EVERY_S = 1.0


class WorldService:
    """One run's world on an open Zenoh session.

    Parameters
    ----------
    session : zenoh.Session
        Open session (router, peer or client); closed by the caller.
    config : RunConfig
        Resolved configuration (``leader_start`` set).
    surface : Surface
        The hidden surface.
    out_dir : path
        Results folder (``config.toml`` is written by the caller).
    on_tick : callable, optional
        Called with each completed tick number (progress bars).
    """

    def __init__(self, session: zenoh.Session, config: RunConfig, surface: Surface,
                 out_dir: str | Path, on_tick: Callable[[int], None] | None = None) -> None:
        self.session, self.config = session, config
        self.sim = WorldSim(config, surface)
        self.recorder = RunRecorder(out_dir, config)
        self.on_tick = on_tick
        self._cond = threading.Condition()
        self._rods: set[int] = set()
        self._alive: set[int] = set()
        self._ended: str | None = None
        self._rejected = 0
        run = config.run_id
        self._declared = [
            session.declare_queryable(keys.sense(run), self._on_sense),
            session.declare_queryable(keys.act(run), self._on_act),
            session.declare_subscriber(keys.rod(run), self._on_rod),
            session.declare_subscriber(keys.obs(run), self._on_obs),
            session.liveliness().declare_subscriber(keys.alive(run, "*"), self._on_alive,
                                                    history=True),
        ]
        self._tick_pub = session.declare_publisher(keys.tick(run))
        self._done_pub = session.declare_publisher(keys.done(run))
        self._token = session.liveliness().declare_token(keys.alive(run, "world"))
        self._declared += [self._tick_pub, self._done_pub, self._token]

    def close(self) -> None:
        for handle in reversed(self._declared):
            try:
                handle.undeclare()
            except zenoh.ZError:
                pass
        self._declared.clear()

    @property
    def rejected(self) -> int:
        """How many malformed requests or samples were refused so far."""
        return self._rejected

    # --- queryables ----------------------------------------------------------------------------

    def _answer(self, query: zenoh.Query, handle: Callable[[int, bytes], bytes]) -> None:
        tick = -1
        try:
            agent = keys.agent_from_key(str(query.key_expr))
            payload = query.payload.to_bytes() if query.payload is not None else b""
            query.reply(query.key_expr, handle(agent, payload))
            return
        except (ProtocolError, RequestError, ValueError) as exc:
            problem = str(exc)
        except RunEnded as exc:
            self.abort(str(exc))
            problem = f"run ended: {exc}"
        self._rejected += 1
        log.info("world: refused %s: %s", query.key_expr, problem)
        query.reply_err(error_payload(tick, problem))

    def _on_sense(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, SenseRequest)
            with self._cond:
                return encode(self.sim.sense(agent, req.tick, req.phase))
        self._answer(query, handle)

    def _on_act(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, ActRequest)
            moved = True
            with self._cond:
                if req.action == "drive":
                    if req.t is None:
                        raise RequestError("drive needs the time t")
                    self.sim.drive(agent, req.tick, req.t)
                elif req.action == "move":
                    if req.offset is None:
                        raise RequestError("move needs an offset")
                    self.sim.move(agent, req.tick, req.offset)
                else:
                    moved = self.sim.snap(agent, req.tick)
            return encode(ActResult(tick=req.tick, moved=moved))
        self._answer(query, handle)

    # --- subscribers ---------------------------------------------------------------------------

    def _on_rod(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload.to_bytes(), Rod)
            with self._cond:
                if msg.tick != self.sim.tick:
                    raise ValueError(f"rod for tick {msg.tick} while the world is at {self.sim.tick}")
                if agent >= self.sim.n_agents or not self.sim.is_settled(agent):
                    raise ValueError(f"agent {agent} published a rod without settling")
                if abs(msg.length - self.config.spacing) > 1e-12 or msg.side != self.config.side_sign:
                    raise ValueError(f"agent {agent}'s rod does not match the run's length/side")
                self._rods.add(agent)
                self._cond.notify_all()
        except (ProtocolError, ValueError) as exc:
            self._rejected += 1
            log.warning("world: dropped rod sample on %s: %s", sample.key_expr, exc)

    def _on_obs(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload.to_bytes(), Observation)
            if not 1 <= agent < self.sim.n_agents:
                raise ValueError(f"unknown follower id {agent}")
            with self._cond:
                self.recorder.add_observation(agent, msg)
        except (ProtocolError, ValueError) as exc:
            self._rejected += 1
            log.warning("world: dropped observation on %s: %s", sample.key_expr, exc)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if "/alive/agent/" not in key:
            return
        try:
            agent = keys.agent_from_key(key)
        except ValueError:
            return
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(agent)
            else:
                self._alive.discard(agent)
            self._cond.notify_all()

    # --- the run -------------------------------------------------------------------------------

    def abort(self, reason: str) -> None:
        """End the run early (from any thread): the result is written marked incomplete."""
        with self._cond:
            if self._ended is None:
                self._ended = reason
            self._cond.notify_all()

    def wait_for_agents(self, timeout: float) -> None:
        """Block until the leader and every follower are live (RuntimeError after ``timeout``)."""
        want = set(range(self.sim.n_agents))
        deadline = time.monotonic() + timeout
        with self._cond:
            while not want <= self._alive:
                if self._ended is not None:
                    raise RuntimeError(f"run aborted before it started: {self._ended}")
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = ", ".join(map(str, sorted(want - self._alive)))
                    raise RuntimeError(f"agents {missing} did not come up within {timeout:.0f} s")
                self._cond.wait(left)

    def _run_tick(self, tick: int) -> str | None:
        """Run one lockstep tick; return why the run must end, or None."""
        with self._cond:
            self.sim.start_tick(tick)
            self._rods.clear()
        self._tick_pub.put(encode(TickStart(tick=tick, t=self.sim.time_of(tick))))
        limit = self.config.agent_timeout
        with self._cond:
            seen, deadline = 0, time.monotonic() + limit
            while len(self._rods) < self.sim.n_agents and self._ended is None:
                if len(self._rods) > seen:  # progress: restart the per-agent clock
                    seen, deadline = len(self._rods), time.monotonic() + limit
                left = deadline - time.monotonic()
                if left <= 0:
                    waiting = min(set(range(self.sim.n_agents)) - self._rods)
                    gone = "" if waiting in self._alive else " (it is no longer live)"
                    return f"agent {waiting} did not settle at tick {tick} within {limit:g} s{gone}"
                self._cond.wait(left)
            if self._ended is not None:
                return self._ended
            self.recorder.add_tick(self.sim.finish_tick())
        return None

    def run(self) -> dict:
        """Wait for the agents, run every tick, write the results; return the summary.

        The run ends early (result written with ``complete: false``) when an agent stops
        settling or the swarm leaves the surface's domain.
        """
        started = time.monotonic()
        self.wait_for_agents(self.config.start_timeout)
        reason, last_write = "", time.monotonic()
        try:
            for tick in range(self.recorder.ticks_done, self.config.ticks):
                ended = self._run_tick(tick)
                if ended is not None:
                    reason = ended
                    break
                if self.on_tick is not None:
                    self.on_tick(tick)
                if time.monotonic() - last_write > WRITE_EVERY_S:
                    self.recorder.write(complete=False, reason="running",
                                        wall_time=time.monotonic() - started)
                    last_write = time.monotonic()
        except BaseException:
            self.recorder.write(complete=False, reason="interrupted",
                                wall_time=time.monotonic() - started)
            raise
        complete = not reason
        if reason:
            log.error("world: run ended early: %s", reason)
        with self._cond:
            self.recorder.write(complete=complete, reason=reason,
                                wall_time=time.monotonic() - started)
        self._done_pub.put(encode(Done(tick=max(self.recorder.ticks_done - 1, 0),
                                       results=str(self.recorder.out_dir), complete=complete,
                                       reason=reason)))
        self._wait_agents_gone(timeout=5.0)
        return self.recorder.summary(complete=complete, reason=reason,
                                     wall_time=time.monotonic() - started)

    def _wait_agents_gone(self, timeout: float) -> None:
        """Give agents time to see ``world/done`` and leave before the session closes."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._alive and time.monotonic() < deadline:
                self._cond.wait(deadline - time.monotonic())
