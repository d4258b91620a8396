"""The world process on Zenoh: queryables, the lockstep tick loop, results (SPEC §4, §8).

:class:`WorldService` wraps a :class:`world.sim.WorldSim` behind the ``world/sense/<id>`` and
``world/act/<id>`` queryables, publishes ``world/tick``, collects ``agent/<id>/rod`` and
``agent/<id>/obs`` samples, and writes the results folder as ticks complete.
"""
from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from protocol import keys
from protocol.config import RunConfig
from protocol.messages import (
    ActRequest, ActResult, Done, Missed, Observation, ProtocolError, Rod, SenseRequest, TickStart,
    decode, encode, error_payload,
)
from protocol.config import write_atomic
from world.results import RunRecorder, read_observations, read_ticks
from world.sim import RequestError, RunEnded, TickMissed, WorldSim
from world.surfaces import Surface

log = logging.getLogger(__name__)

STATE_FILE = "world_state.json"
CRASH_EXIT = 70


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
                 out_dir: str | Path, on_tick: Callable[[int], None] | None = None,
                 resume: bool = False, crash_after_tick: int | None = None) -> None:
        self.session, self.config = session, config
        self.sim = WorldSim(config, surface)
        self.recorder = RunRecorder(out_dir, config)
        if resume:
            self._resume()
        self.on_tick = on_tick
        self.crash_after_tick = crash_after_tick
        self._cond = threading.Condition()
        self._done: set[int] = set()  # agents through the current tick: settled or missed
        self._settled_at: dict[int, float] = {}  # when each of them got through
        self._tick_started = 0.0
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
        # BLOCK: a tick, miss or done is never dropped when a link is congested (a peer may
        # flood it with data); the agents would wait for it in vain.
        self._tick_pub = session.declare_publisher(
            keys.tick(run), congestion_control=zenoh.CongestionControl.BLOCK)
        self._missed_pub = session.declare_publisher(
            keys.missed(run), congestion_control=zenoh.CongestionControl.BLOCK)
        self._done_pub = session.declare_publisher(
            keys.done(run), congestion_control=zenoh.CongestionControl.BLOCK)
        self._token = session.liveliness().declare_token(keys.alive(run, "world"))
        self._declared += [self._tick_pub, self._missed_pub, self._done_pub, self._token]

    def _resume(self) -> None:
        """Continue from the results folder's checkpoint (the last complete tick)."""
        out = self.recorder.out_dir
        try:
            state = json.loads((out / STATE_FILE).read_text())
            rows = read_ticks(out / "ticks.csv")
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"cannot resume from {out}: {exc}") from None
        self.sim.restore(state)
        done = self.sim.tick + 1
        self.recorder.restore(
            [r for r in rows if r["tick"] < done],
            [o for o in read_observations(out / "observations.csv") if o["tick"] < done],
            {int(k): v for k, v in state.get("missed_counts", {}).items()})
        if self.recorder.ticks_done != done:
            raise ValueError(f"cannot resume from {out}: ticks.csv has {self.recorder.ticks_done} "
                             f"complete ticks but the checkpoint {done}")

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
        code = "bad-request"
        try:
            agent = keys.agent_from_key(str(query.key_expr), last=True)
            payload = query.payload if query.payload is not None else b""
            query.reply(query.key_expr, handle(agent, payload))
            return
        except TickMissed as exc:
            problem, code = str(exc), "missed"
        except (ProtocolError, RequestError, ValueError) as exc:
            problem = str(exc)
        except RunEnded as exc:
            self.abort(str(exc))
            problem, code = f"run ended: {exc}", "ended"
        self._rejected += 1
        log.info("world: refused %s: %s", query.key_expr, problem)
        query.reply_err(error_payload(self.sim.tick, problem, code))

    def _on_sense(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, SenseRequest)
            with self._cond:
                # the agent validates it on decode; its numbers are the world's own
                return encode(self.sim.sense(agent, req.tick, req.phase), check=False)
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
            msg = decode(sample.payload, Rod)
            with self._cond:
                if msg.tick != self.sim.tick:
                    raise ValueError(f"rod for tick {msg.tick} while the world is at {self.sim.tick}")
                if agent >= self.sim.n_agents or not self.sim.is_settled(agent):
                    raise ValueError(f"agent {agent} published a rod without settling")
                if abs(msg.length - self.config.spacing) > 1e-12 or msg.side != self.config.side_sign:
                    raise ValueError(f"agent {agent}'s rod does not match the run's length/side")
                self._done.add(agent)
                self._settled_at[agent] = time.monotonic()
                self._cond.notify_all()
        except (ProtocolError, ValueError) as exc:
            self._drop("rod sample", sample, exc)

    def _on_obs(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload, Observation)
            if not 1 <= agent < self.sim.n_agents:
                raise ValueError(f"unknown follower id {agent}")
            with self._cond:
                self.recorder.add_observation(agent, msg)
        except (ProtocolError, ValueError) as exc:
            self._drop("observation", sample, exc)

    def _drop(self, what: str, sample: zenoh.Sample, exc: Exception) -> None:
        """Count, log and otherwise ignore a malformed or out-of-turn sample."""
        self._rejected += 1
        log.warning("world: dropped %s on %s: %s", what, sample.key_expr, exc)

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
                if 0 <= self.sim.tick and agent < self.sim.n_agents and agent not in self._done:
                    self._mark_missed(agent, "its process vanished")
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

    def _mark_missed(self, agent: int, why: str) -> None:
        """(Lock held.) ``agent`` did not settle this tick: it keeps its pose; tell the chain."""
        log.warning("world: agent %d missed tick %d: %s", agent, self.sim.tick, why)
        self.sim.mark_missed(agent)
        self._done.add(agent)
        self._settled_at[agent] = time.monotonic()
        self._missed_pub.put(encode(Missed(tick=self.sim.tick, agent=agent)))
        self._cond.notify_all()

    def _first_pending(self) -> int | None:
        pending = set(range(self.sim.n_agents)) - self._done
        return min(pending) if pending else None

    def _wait_rejoin(self, tick: int) -> str | None:
        """(Lock held.) Before a tick, every agent must be live (a restarted one rejoins here)."""
        deadline = time.monotonic() + self.config.agent_timeout
        while self._ended is None:
            gone = set(range(self.sim.n_agents)) - self._alive
            if not gone:
                return None
            left = deadline - time.monotonic()
            if left <= 0:
                names = ", ".join(map(str, sorted(gone)))
                return (f"agent(s) {names} gone before tick {tick} and not back within "
                        f"{self.config.agent_timeout:g} s")
            self._cond.wait(left)
        return self._ended

    def _run_tick(self, tick: int) -> str | None:
        """Run one tick (lockstep or realtime); return why the run must end, or None."""
        realtime = self.config.mode == "realtime"
        with self._cond:
            if not realtime:
                reason = self._wait_rejoin(tick)
                if reason is not None:
                    return reason
            self.sim.start_tick(tick)
            self._done.clear()
            self._settled_at = {}
            self._tick_started = time.monotonic()
        self._tick_pub.put(encode(TickStart(tick=tick, t=self.sim.time_of(tick))))
        limit = self.config.agent_timeout
        with self._cond:
            while (waiting := self._first_pending()) is not None and self._ended is None:
                # the clock restarts whenever some agent gets through the tick
                deadline = max(self._settled_at.values(), default=self._tick_started) + limit
                if realtime:
                    deadline = min(deadline, self._tick_started + self.period)
                left = deadline - time.monotonic()
                if left <= 0:
                    if realtime:
                        self._mark_missed(waiting, "did not settle in time")
                        continue
                    gone = "" if waiting in self._alive else " (it is no longer live)"
                    return f"agent {waiting} did not settle at tick {tick} within {limit:g} s{gone}"
                self._cond.wait(left)
            if self._ended is not None:
                return self._ended
            self.recorder.add_tick(self.sim.finish_tick())
            if realtime:  # pace by the wall clock
                next_start = self._tick_started + self.period
                while self._ended is None and (left := next_start - time.monotonic()) > 0:
                    self._cond.wait(left)
        return None

    @property
    def period(self) -> float:
        """Wall-clock seconds per tick in realtime mode."""
        return self.config.comm_period * self.config.time_scale

    def run(self) -> dict:
        """Wait for the agents, run every tick, write the results; return the summary.

        Results and the world's checkpoint are rewritten after every tick, so a crashed world
        continues with ``python -m world --resume RUN_DIR``. The run ends early (result
        written with ``complete: false``) when an agent stops settling (lockstep), does not
        come back after vanishing, or the swarm leaves the surface's domain.
        """
        started = time.monotonic()
        self.wait_for_agents(self.config.start_timeout)
        reason = ""
        try:
            for tick in range(self.recorder.ticks_done, self.config.ticks):
                ended = self._run_tick(tick)
                if ended is not None:
                    reason = ended
                    break
                with self._cond:
                    self._checkpoint(complete=False, reason="running",
                                     wall_time=time.monotonic() - started)
                if self.crash_after_tick is not None and tick >= self.crash_after_tick:
                    os._exit(CRASH_EXIT)  # fault injection for tests: no clean-up at all
                if self.on_tick is not None:
                    self.on_tick(tick)
        except BaseException:
            with self._cond:
                self.recorder.write(complete=False, reason="interrupted",
                                    wall_time=time.monotonic() - started)
            raise
        complete = not reason
        if reason:
            log.error("world: run ended early: %s", reason)
        with self._cond:
            self._checkpoint(complete=complete, reason=reason, wall_time=time.monotonic() - started)
        self._done_pub.put(encode(Done(tick=max(self.recorder.ticks_done - 1, 0),
                                       results=str(self.recorder.out_dir), complete=complete,
                                       reason=reason)))
        self._wait_agents_gone(timeout=5.0)
        return self.recorder.summary(complete=complete, reason=reason,
                                     wall_time=time.monotonic() - started)

    def _checkpoint(self, **status) -> None:
        """(Lock held.) Results so far and the world's state after the last complete tick."""
        self.recorder.write(**status)
        state = {**self.sim.state(), "missed_counts": self.recorder.missed}
        write_atomic(self.recorder.out_dir / STATE_FILE, json.dumps(state))

    def _wait_agents_gone(self, timeout: float) -> None:
        """Give agents time to see ``world/done`` and leave before the session closes."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._alive and time.monotonic() < deadline:
                self._cond.wait(deadline - time.monotonic())
