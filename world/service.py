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
    ACTIONS, Done, Joined, JoinRequest, Missed, Observation, ProtocolError, Rod,
    SenseRequest, TickStart, decode, encode, error_payload,
)
from protocol.messages import safe_text
from world import checkpoint
from world.results import RunRecorder
from world.sim import RequestError, RunEnded, TickMissed, WorldSim
from world.surfaces import Surface
from world.view import ViewPublisher

log = logging.getLogger(__name__)

STATE_FILE = checkpoint.STATE_FILE


class NotYet(RequestError):
    """A follower's request before the world has its predecessor through the tick (the rod
    reached the follower first): answered with code ``wait``, the follower asks again."""


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
                 resume: bool = False) -> None:
        self.session, self.config = session, config
        run = config.run_id
        if self._world_live(session, run):
            raise RuntimeError(f"run id {run!r} is already live: another world serves it "
                               "(refusing to join it)")
        self.sim = WorldSim(config, surface)
        self.recorder = RunRecorder(out_dir, config)
        self.out_dir = self.recorder.out_dir
        self._cond = threading.Condition()
        self._done: set[int] = set()  # agents through the current tick: settled or missed
        self._obs: dict[int, Observation] = {}  # the current tick's observations by follower
        self._rods: set[int] = set()  # agents whose rod for the current tick arrived
        self._settled_at: dict[int, float] = {}  # when each of them got through
        self._tick_started = 0.0
        self._alive: set[int] = set()
        self._ended: str | None = None
        self._rejected = 0
        self._wall_before = 0.0  # wall time of earlier starts of this run (resume)
        self._started = time.monotonic()
        if resume and checkpoint.has_progress(self.out_dir):
            self._resume()
        else:
            self.start = checkpoint.new_start()
            self.recorder.open()
            self._save_state(0.0)  # a world killed before tick 0 completes resumes from here
        self.on_tick = on_tick
        self.view = ViewPublisher(session, config, surface, self.sim.ideal, out_dir)
        self._declared = [
            self.view,
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

    @staticmethod
    def _world_live(session: zenoh.Session, run: str) -> bool:
        replies = session.liveliness().get(keys.alive(run, "world"), timeout=0.5)
        return any(reply.ok is not None for reply in replies)

    def _resume(self) -> None:
        """Continue from the checkpoint: the state after the last complete tick, the CSV files
        cut back to that tick, every agent counted through it (restarted agents redo the next)."""
        state = checkpoint.load(self.out_dir, self.config.run_id)
        try:
            self.sim.restore(state["sim"])
        except (KeyError, TypeError, ValueError) as exc:
            raise checkpoint.StateError(f"checkpoint {self.out_dir / STATE_FILE}: bad simulation "
                                        f"state ({exc}); refusing it") from None
        self.recorder.open(resume_offsets=state["offsets"])
        if self.recorder.ticks_done != self.sim.tick + 1:
            raise checkpoint.StateError(
                f"cannot resume {self.out_dir}: ticks.csv holds {self.recorder.ticks_done} ticks, "
                f"the checkpoint {self.sim.tick + 1}")
        self.start, self._wall_before = state["start"], state["wall_time"]
        self._done = set(range(self.sim.n_agents)) if self.sim.tick >= 0 else set()
        log.warning("world: resuming run %s after tick %d", self.config.run_id, self.sim.tick)

    def close(self) -> None:
        for handle in reversed(self._declared):
            try:
                handle.undeclare()
            except zenoh.ZError:
                pass
        self._declared.clear()
        self.recorder.close()

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
        except NotYet as exc:  # not a refusal: the agent asks again
            query.reply_err(error_payload(self.sim.tick, str(exc), "wait"))
            return
        except (ProtocolError, RequestError, ValueError) as exc:
            problem = str(exc)
        except RunEnded as exc:
            self.abort(str(exc))
            problem, code = f"run ended: {exc}", "ended"
        self._rejected += 1
        log.info("world: refused %s: %s", query.key_expr, problem)
        query.reply_err(error_payload(self.sim.tick, problem, code))

    def _check_turn(self, agent: int, tick: int) -> None:
        """(Lock held.) A follower acts at the current tick only once the world has its
        predecessor through it: a predecessor that vanished before its rod reached the world
        is rolled back, and its successor must not have seen it moved."""
        if 0 < agent < self.sim.n_agents and tick == self.sim.tick and agent - 1 not in self._done:
            raise NotYet(f"agent {agent - 1} is not through tick {tick} yet")

    def _on_sense(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, SenseRequest)
            with self._cond:
                self._check_turn(agent, req.tick)
                # the agent validates it on decode; its numbers are the world's own
                return encode(self.sim.sense(agent, req.tick, req.phase), check=False)
        self._answer(query, handle)

    def _joined(self, agent: int) -> Joined:
        """(Lock held.) Where the run stands for a starting agent process."""
        if not 0 <= agent < self.sim.n_agents:
            raise RequestError(f"unknown agent id {agent} (this run has agents "
                               f"0..{self.sim.n_agents - 1})")
        tick = self.sim.tick
        if tick < 0:
            return Joined(tick=0, settled=False, ready=False, start=self.start)
        settled = agent in self._done
        ready = not settled and (agent == 0 or agent - 1 in self._done)
        return Joined(tick=tick, settled=settled, ready=ready, start=self.start)

    def _on_act(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, (*ACTIONS, JoinRequest))
            with self._cond:
                if isinstance(req, JoinRequest):
                    return encode(self._joined(agent))
                self._check_turn(agent, req.tick)
                # the agent validates the reply on decode; its numbers are the world's own
                return encode(self.sim.act(agent, req), check=False)
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
                self._rods.add(agent)
                self._through_if_reported(agent)
        except (ProtocolError, ValueError) as exc:
            self._drop("rod sample", sample, exc)

    def _through_if_reported(self, agent: int) -> None:
        """(Lock held.) An agent is through the tick once the world has its rod and, for a
        follower, its observation (the two samples may arrive in either order)."""
        if agent in self._rods and (agent == 0 or agent in self._obs):
            self._done.add(agent)
            self._settled_at[agent] = time.monotonic()
            self._cond.notify_all()

    def _on_obs(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload, Observation)
            if not 1 <= agent < self.sim.n_agents:
                raise ValueError(f"unknown follower id {agent}")
            with self._cond:  # one per follower and tick, for the tick in progress (SPEC §8)
                if msg.tick != self.sim.tick:
                    raise ValueError(f"observation for tick {msg.tick} while the world is at "
                                     f"{self.sim.tick}")
                if agent in self._obs or agent in self._done:
                    raise ValueError(f"follower {agent} already reported tick {msg.tick}")
                if not self.sim.is_settled(agent):
                    raise ValueError(f"follower {agent} reported tick {msg.tick} before settling")
                self._obs[agent] = msg
                self._through_if_reported(agent)
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
                    if self.config.mode == "realtime":
                        self._mark_missed(agent, "its process vanished")
                    else:  # lockstep: it redoes the tick when it is back (SPEC §4)
                        log.warning("world: agent %d vanished during tick %d; its tick is rolled "
                                    "back until it is back", agent, self.sim.tick)
                        self.sim.rollback(agent)
                        self._obs.pop(agent, None)
                        self._rods.discard(agent)
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
            self._obs.clear()
            self._rods.clear()
            self._settled_at = {}
            self._tick_started = time.monotonic()
        self._tick_pub.put(encode(TickStart(tick=tick, t=self.sim.time_of(tick))))
        limit = self.config.agent_timeout
        with self._cond:
            if realtime:  # a dead agent misses at once: those behind it keep their time budget
                for agent in sorted(set(range(self.sim.n_agents)) - self._alive):
                    self._mark_missed(agent, "its process is not live")
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
            rows = self.sim.finish_tick()
            self.recorder.add_tick(rows, sorted(self._obs.items()))
            self._save_state(self._wall())
            self.recorder.write_summary(complete=False, reason="running", wall_time=self._wall())
            self.view.publish_tick(rows)
            if realtime:  # pace by the wall clock
                next_start = self._tick_started + self.period
                while self._ended is None and (left := next_start - time.monotonic()) > 0:
                    self._cond.wait(left)
        return None

    @property
    def period(self) -> float:
        """Wall-clock seconds per tick in realtime mode."""
        return self.config.comm_period * self.config.time_scale

    def _wall(self) -> float:
        """Wall time of the run so far, earlier starts included."""
        return self._wall_before + (time.monotonic() - self._started)

    def _save_state(self, wall_time: float) -> None:
        """(Lock held.) The checkpoint after the last complete tick (its rows are on disk)."""
        checkpoint.save(self.out_dir, run_id=self.config.run_id, start=self.start,
                        sim=self.sim.state(), offsets=self.recorder.offsets,
                        wall_time=float(wall_time))

    def run(self) -> dict:
        """Wait for the agents, run every tick, write the results; return the summary.

        Each complete tick is appended to the results and then checkpointed, so a world killed
        at any moment continues with ``python -m world --resume RUN_DIR`` from the last
        complete tick. The run ends early (result written with ``complete: false``, the
        checkpoint kept for a resume) when an agent stops settling (lockstep), does not come
        back after vanishing, or the swarm leaves the surface's domain. Once the run is
        complete the checkpoint is deleted.
        """
        self._started = time.monotonic()
        self.wait_for_agents(self.config.start_timeout)
        self.view.publish_map(force=True)
        reason = ""
        try:
            for tick in range(self.recorder.ticks_done, self.config.ticks):
                ended = self._run_tick(tick)
                if ended is not None:
                    reason = ended
                    break
                if self.on_tick is not None:
                    self.on_tick(tick)
        except BaseException:
            with self._cond:
                self.recorder.write_summary(complete=False, reason="interrupted",
                                            wall_time=self._wall())
            raise
        complete = not reason
        if reason:
            log.error("world: run ended early: %s", reason)
        with self._cond:
            self.recorder.write_summary(complete=complete, reason=reason, wall_time=self._wall())
        self._done_pub.put(encode(Done(tick=max(self.recorder.ticks_done - 1, 0),
                                       results=str(self.out_dir), complete=complete,
                                       reason=safe_text(reason))))
        self._wait_agents_gone(timeout=5.0)
        if complete:  # a world killed before this resumes into the end phase again
            checkpoint.discard(self.out_dir)
        return self.recorder.summary(complete=complete, reason=reason, wall_time=self._wall())

    def _wait_agents_gone(self, timeout: float) -> None:
        """Give agents time to see ``world/done`` and leave before the session closes."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._alive and time.monotonic() < deadline:
                self._cond.wait(deadline - time.monotonic())
