"""The world process on Zenoh: queryables, the lockstep tick loop, results (design §4, §8).

:class:`WorldService` wraps a :class:`world.sim.WorldSim` behind the ``world/sense/<id>`` and
``world/act/<id>`` queryables, publishes ``world/tick``, collects ``agent/<id>/rod`` and
``agent/<id>/obs`` samples, and writes the results folder as ticks complete.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import zenoh

from protocol import keys
from protocol.config import RunConfig
from protocol.messages import (
    ACTIONS,
    Done,
    Joined,
    JoinRequest,
    Missed,
    Observation,
    ProtocolError,
    Rod,
    SenseRequest,
    TickStart,
    decode,
    encode,
    error_payload,
    safe_text,
)
from protocol.record import DamagedRecord
from protocol.session import token_live, undeclare_all
from world import checkpoint
from world.results import RunRecorder
from world.schedule import may_open, predecessor_through
from world.sim import RequestError, RunEnded, TickMissed, WorldSim
from world.surfaces import Surface
from world.view import ViewPublisher

log = logging.getLogger(__name__)


def agent_ranges(agents, limit: int = 12) -> str:
    """Agent ids with runs of three or more consecutive ones shortened, e.g. ``1, 2, 4–7, 9``;
    past ``limit`` pieces, how many more ids there are.

    >>> agent_ranges({9, 1, 2, 4, 5, 6, 7})
    '1, 2, 4–7, 9'
    >>> agent_ranges(range(0, 40, 2), limit=3)
    '0, 2, 4 and 17 more'
    """
    ids = sorted(agents)
    runs: list[list[int]] = []
    for k in ids:
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    pieces: list[tuple[str, int]] = []  # (text, how many ids it stands for)
    for a, b in runs:
        if b > a + 1:
            pieces.append((f"{a}–{b}", b - a + 1))
        else:
            pieces.extend((str(k), 1) for k in range(a, b + 1))
    shown = ", ".join(text for text, _ in pieces[:limit])
    if len(pieces) <= limit:
        return shown
    return f"{shown} and {len(ids) - sum(n for _, n in pieces[:limit])} more"


class NotYet(RequestError):
    """A follower's request before the world has its predecessor through the tick (the rod
    reached the follower first; the world may not even have begun the tick): answered with
    code ``wait``, the follower asks again."""


class Stale(RequestError):
    """A request of an agent's join other than its latest (:attr:`protocol.messages.Request.epoch`):
    sent before the agent joined again, it reached the world after (it was in flight when the
    session was cut). Answered with code ``stale`` and not read: the agent gave it up when it
    joined again, and its redo asks anew."""


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
        if token_live(session, keys.alive(run, "world")):
            raise RuntimeError(f"run id {run!r} is already live: another world serves it "
                               "(refusing to join it)")
        self.sim = WorldSim(config, surface)
        self.recorder = RunRecorder(out_dir, config)
        self.out_dir = self.recorder.out_dir
        self._cond = threading.Condition()
        # per agent, the last tick the world has it through (its rod and, for a follower, its
        # observation arrived; or it missed the tick): in pipelined lockstep they differ
        self._through = [-1] * self.sim.n_agents
        self._obs: dict[int, dict[int, Observation]] = {}  # per open tick, by follower
        self._rods: dict[int, set[int]] = {}  # per open tick, agents whose rod arrived
        self._progress = time.monotonic()  # when some agent last got through a tick
        self._tick_started = 0.0
        self._alive: set[int] = set()
        # per agent, the number of its latest join (its requests carry it, design §8)
        self._epochs = [0] * self.sim.n_agents
        self._ended: str | None = None
        # a results write that failed in a request handler (the journal), raised by run() as a
        # results write of its own would be: one report of a failing disk, whichever file it hit
        self._disk_failure: OSError | None = None
        self._finished: bytes | None = None  # the world/done message, once published
        self._rejected = 0
        self._wall_before = 0.0  # wall time of earlier starts of this run (resume)
        self._started = time.monotonic()
        if resume and checkpoint.has_progress(self.out_dir):
            self._resume()
        else:
            self.start = checkpoint.new_start()
            self.recorder.open()
            self._journal = checkpoint.Journal(self.out_dir, run, self.start)
            self._journal.open()
            self._save_state(0.0)  # a world killed before tick 0 completes resumes from here
        self.on_tick = on_tick
        self.view = ViewPublisher(session, config, surface, self.sim.ideal, out_dir)
        self.ros2 = None  # the run's ROS 2 topics (design §10), with --ros2
        if config.ros2:
            from world.ros2 import Ros2Publisher

            self.ros2 = Ros2Publisher(session, config, surface, self.sim.ideal)
        self._declared = [
            *([self.ros2] if self.ros2 is not None else []),
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

    def _resume(self) -> None:
        """Continue from the checkpoint: the state after the last complete tick, the CSV files
        cut back to that tick, every agent counted through it (restarted agents redo the next)."""
        state = checkpoint.load(self.out_dir, self.config.run_id)
        try:
            self.sim.restore(state["sim"])
        except (KeyError, TypeError, ValueError) as exc:
            raise checkpoint.StateError(f"checkpoint {self.out_dir / checkpoint.STATE_FILE}: bad "
                                        f"simulation state ({exc}); refusing it") from None
        # what it answered in the ticks it runs again (their redos must ask the same), read
        # before any file changes
        journal = checkpoint.Journal(self.out_dir, self.config.run_id, state["start"])
        kept = journal.read(self.sim.n_agents, self.sim.complete)
        try:  # every file is checked before any is changed
            self.recorder.open(resume_offsets=state["offsets"], resume_ticks=self.sim.tick + 1)
        except DamagedRecord as exc:
            raise checkpoint.StateError(f"cannot resume {self.out_dir}: {exc}") from None
        self.start, self._wall_before = state["start"], state["wall_time"]
        self._through = [self.sim.tick] * self.sim.n_agents
        for (agent, tick), requests in checkpoint.attempts(kept).items():
            self.sim.expect_redo(agent, tick, requests)
        self._journal = journal
        self._journal.open(kept)
        log.warning("world: resuming run %s after tick %d", self.config.run_id, self.sim.tick)

    def close(self) -> None:
        undeclare_all(self._declared)
        self.recorder.close()
        with self._cond:  # not while a request is being answered
            self._journal.close()

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
        except Stale as exc:  # a leftover of an earlier join, nobody waits for its answer
            log.info("world: ignored %s: %s", query.key_expr, exc)
            query.reply_err(error_payload(self.sim.tick, str(exc), "stale"))
            return
        except (ProtocolError, RequestError, ValueError) as exc:
            problem = str(exc)
        except RunEnded as exc:  # the run ends before this tick (WorldSim.end_tick)
            with self._cond:
                self._cond.notify_all()
            problem, code = f"run ended: {exc}", "ended"
        self._rejected += 1
        log.info("world: refused %s: %s", query.key_expr, problem)
        query.reply_err(error_payload(self.sim.tick, problem, code))

    def _check_turn(self, agent: int, tick: int) -> None:
        """(Lock held.) An agent begins a tick only once the world has it through the tick
        before, and a follower acts at a tick only once the world has its predecessor through
        it: an agent that vanishes before its reports reach the world is rolled back by one
        tick, and its successor must not have seen it moved."""
        if not 0 <= agent < self.sim.n_agents:
            return  # the simulation names the problem
        self.sim.check_not_ended(tick)
        if tick == self._through[agent] + 2 and self.sim.is_settled(agent, tick - 1):
            raise NotYet(f"agent {agent}'s report of tick {tick - 1} has not reached the world yet")
        # up to the tick after the world's newest: a predecessor's rod of it may reach the
        # follower first, even from a killed world whose tick this resumed one has not begun
        if tick <= self.sim.tick + 1 and not predecessor_through(self._through, agent, tick):
            raise NotYet(f"the world has not begun tick {tick} yet" if tick > self.sim.tick
                         else f"agent {agent - 1} is not through tick {tick} yet")

    def _check_epoch(self, agent: int, epoch: int) -> None:
        """(Lock held.) Refuse, unread, a request numbered with a join of ``agent`` other than
        its latest (:class:`Stale`); an unnumbered one (0, an older sender) is taken as it
        comes. Nothing of the tick is used up, so the redo after the join reads what the
        undone attempt read (design §5)."""
        if epoch and 0 <= agent < self.sim.n_agents and epoch != self._epochs[agent]:
            raise Stale(f"agent {agent}'s request of its join {epoch} came after its join "
                        f"{self._epochs[agent]}: not read")

    def _on_sense(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, SenseRequest)
            with self._cond:
                self._check_epoch(agent, req.epoch)
                self._check_turn(agent, req.tick)
                sensing = self.sim.sense(agent, req.tick, req.look)
                self._answered(agent, req.tick)
                # the agent validates it on decode; its numbers are the world's own
                return encode(sensing, check=False)
        self._answer(query, handle)

    def _joined(self, agent: int) -> Joined:
        """(Lock held.) Where the run stands for a starting agent process."""
        if not 0 <= agent < self.sim.n_agents:
            raise RequestError(f"unknown agent id {agent} (this run has agents "
                               f"0..{self.sim.n_agents - 1})")
        opened, through = self.sim.tick, self._through[agent]
        run = {"start": self.start, "max_speed": self.config.max_speed}
        if opened < 0:
            return Joined(tick=0, settled=False, ready=False, until=0, world=0, **run)
        if through >= opened:
            return Joined(tick=opened, settled=True, ready=False, until=opened, world=opened,
                          **run)
        until = opened if agent == 0 else self._through[agent - 1]
        return Joined(tick=through + 1, settled=False, ready=until > through, until=max(until, 0),
                      world=opened, **run)

    def _on_act(self, query: zenoh.Query) -> None:
        def handle(agent: int, payload: bytes) -> bytes:
            req = decode(payload, (*ACTIONS, JoinRequest))
            with self._cond:
                if isinstance(req, JoinRequest):
                    if self._finished is not None:  # an agent restarted after the end
                        self._done_pub.put(self._finished)
                    joined = self._joined(agent)
                    # what it sent before is void: a request of an earlier join is stale
                    self._epochs[agent] += 1
                    joined = replace(joined, epoch=self._epochs[agent])
                    if self.config.mode == "lockstep":
                        # it starts again from what the world has it through: whatever it did
                        # since (before a stall cut its session, say) is void (in realtime
                        # the tick it vanished in was marked missed)
                        self._roll_back(agent)
                    return encode(joined)
                self._check_epoch(agent, req.epoch)
                self._check_turn(agent, req.tick)
                reply = self.sim.act(agent, req)
                self._answered(agent, req.tick)
                # the agent validates the reply on decode; its numbers are the world's own
                return encode(reply, check=False)
        self._answer(query, handle)

    def _answered(self, agent: int, tick: int) -> None:
        """(Lock held.) Journal the request of ``agent`` the simulation just carried out, before
        its answer leaves (:class:`world.checkpoint.Journal`); a journal that cannot be written
        ends the run (a resumed world could not hold a redo to it), unanswered."""
        requests = self.sim.agents[agent].requests
        try:
            self._journal.add(agent, tick, len(requests) - 1, requests[-1])
        except OSError as exc:
            reason = f"cannot write {checkpoint.JOURNAL_FILE}: {exc.strerror or exc}"
            self._disk_failure = self._disk_failure or exc
            self.abort(reason)
            raise RunEnded(reason) from None

    # --- subscribers ---------------------------------------------------------------------------

    def _on_rod(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload, Rod)
            with self._cond:
                if agent >= self.sim.n_agents:
                    raise ValueError(f"unknown agent id {agent}")
                self._check_report("rod", agent, msg.tick)
                if (abs(msg.length - self.config.spacing) > 1e-12
                        or msg.side != self.config.side_sign):
                    raise ValueError(f"agent {agent}'s rod does not match the run's length/side")
                if agent in self._rods.setdefault(msg.tick, set()):
                    raise ValueError(f"agent {agent} already published its rod for tick {msg.tick}")
                self._rods[msg.tick].add(agent)
                self._through_if_reported(agent, msg.tick)
        except (ProtocolError, ValueError) as exc:
            self._drop("rod sample", sample, exc)

    def _check_report(self, what: str, agent: int, tick: int) -> None:
        """(Lock held.) A rod or observation is for the tick after the last one the world has
        the agent through, and the agent settled at it (design §8: one per agent and tick)."""
        expected = self._through[agent] + 1
        if tick != expected or tick > self.sim.tick:
            raise ValueError(f"{what} for tick {tick} while the world has agent {agent} at tick "
                             f"{expected}")
        if not self.sim.is_settled(agent, tick):
            raise ValueError(f"agent {agent} published a {what} without settling")

    def _through_if_reported(self, agent: int, tick: int) -> None:
        """(Lock held.) An agent is through a tick once the world has its rod and, for a
        follower, its observation (the two samples may arrive in either order)."""
        if agent in self._rods.get(tick, ()) and (agent == 0 or agent in self._obs.get(tick, {})):
            self._got_through(agent, tick)

    def _got_through(self, agent: int, tick: int) -> None:
        self._through[agent] = tick
        self._progress = time.monotonic()
        self._cond.notify_all()

    def _on_obs(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload, Observation)
            if not 1 <= agent < self.sim.n_agents:
                raise ValueError(f"unknown follower id {agent}")
            with self._cond:  # one per follower and tick, for its tick in progress (design §8)
                self._check_report("observation", agent, msg.tick)
                if agent in self._obs.setdefault(msg.tick, {}):
                    raise ValueError(f"follower {agent} already reported tick {msg.tick}")
                self._obs[msg.tick][agent] = msg
                self._through_if_reported(agent, msg.tick)
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
                tick = self._through[agent] + 1 if agent < self.sim.n_agents else -1
                if 0 <= tick <= self.sim.tick:
                    if self.config.mode == "realtime":
                        self._mark_missed(agent, "its process vanished")
                    else:  # lockstep: it redoes the tick when it is back (design §4)
                        # once the run is ending the agents leave: no warning (the end line
                        # alone says why the run ended)
                        report = log.warning if self._ended is None else log.info
                        report("world: agent %d vanished during tick %d; its tick is rolled "
                               "back until it is back", agent, tick)
                        self._roll_back(agent)
            self._cond.notify_all()

    def _roll_back(self, agent: int) -> None:
        """(Lock held.) Undo what ``agent`` did in the tick after the last one the world has it
        through (nothing if it has not begun it): it redoes that tick."""
        tick = self._through[agent] + 1 if 0 <= agent < self.sim.n_agents else -1
        if 0 <= tick <= self.sim.tick:
            self.sim.rollback(agent, tick)
            self._obs.get(tick, {}).pop(agent, None)
            self._rods.get(tick, set()).discard(agent)

    # --- the run -------------------------------------------------------------------------------

    def abort(self, reason: str) -> None:
        """End the run early (from any thread): the result is written marked incomplete."""
        with self._cond:
            if self._ended is None:
                self._ended = reason
            self._cond.notify_all()

    def wait_for_agents(self, timeout: float) -> None:
        """Block until the leader and every follower are live (RuntimeError after ``timeout``)."""
        missing = self._wait_live(timeout, stop_when_ended=True)
        if missing and self._ended is not None:
            raise RuntimeError(f"run aborted before it started: {self._ended} "
                               f"({self._not_up(missing)} had not come up)")
        if missing:
            raise RuntimeError(f"{self._not_up(missing)} did not come up within {timeout:.0f} s")

    def _not_up(self, missing: set[int]) -> str:
        """``agent 3`` or ``agents 1, 4–9 (7 of 12)``: who is missing, for a message."""
        if len(missing) == 1:
            return f"agent {next(iter(missing))}"
        return f"agents {agent_ranges(missing)} ({len(missing)} of {self.sim.n_agents})"

    def _wait_until(self, done, timeout: float) -> None:
        """Wait up to ``timeout`` s, woken by every change of the agents' state, until
        ``done()`` (called with the lock held) is true."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not done() and (left := deadline - time.monotonic()) > 0:
                self._cond.wait(left)

    def _missing(self) -> set[int]:
        """(Lock held.) The agents not live."""
        return set(range(self.sim.n_agents)) - self._alive

    def _wait_live(self, timeout: float, stop_when_ended: bool = False) -> set[int]:
        """Wait up to ``timeout`` s (or until the run ended, with ``stop_when_ended``) for every
        agent to be live; return those that are not."""
        self._wait_until(lambda: not self._missing()
                         or (stop_when_ended and self._ended is not None), timeout)
        with self._cond:
            return self._missing()

    def _mark_missed(self, agent: int, why: str) -> None:
        """(Lock held, realtime.) ``agent`` did not settle this tick: it keeps its pose; tell
        the chain."""
        log.warning("world: agent %d missed tick %d: %s", agent, self.sim.tick, why)
        self.sim.mark_missed(agent)
        self._got_through(agent, self.sim.tick)
        self._missed_pub.put(encode(Missed(tick=self.sim.tick, agent=agent)))

    def _complete_tick(self, tick: int) -> list[dict]:
        """(Lock held.) Every agent is through ``tick``: append its rows, observations and
        control steps in agent order, then checkpoint (the checkpoint only ever describes
        complete ticks); then publish what was recorded, with the formation health it counted."""
        rows = self.sim.finish_tick(tick)
        controls = self.sim.control_rows(tick)
        shown = self.recorder.add_tick(rows, sorted(self._obs.pop(tick, {}).items()), controls)
        self._rods.pop(tick, None)
        wall = self._wall()  # the checkpoint and the summary tell the same time
        self._save_state(wall)
        self.recorder.write_summary(complete=False, reason="running", wall_time=wall)
        self.view.publish_tick(shown)
        if self.ros2 is not None:
            self.ros2.publish_tick(shown, controls)
        return rows

    def _stalled(self) -> str:
        """(Lock held.) Why a lockstep run that made no progress for ``agent_timeout`` ends."""
        waiting = min(range(self.sim.n_agents), key=lambda k: (self._through[k], k))
        gone = "" if waiting in self._alive else " (it is no longer live)"
        return (f"agent {waiting} did not settle at tick {self._through[waiting] + 1} within "
                f"{self.config.agent_timeout:g} s{gone}")

    def _run_lockstep(self) -> str | None:
        """Run every remaining tick in lockstep; return why the run must end, or None.

        Unpipelined, tick j+1 opens once every agent is through j; pipelined (design §4), once the
        leader is through j, and each agent begins j+1 as soon as the world has it through j and
        its predecessor through j+1 (:meth:`_check_turn`), so the column moves as a wavefront.
        Ticks complete, and are written, in order. A restarted agent rejoins through
        ``JoinRequest``; a run in which nobody gets through a tick for ``agent_timeout`` s ends.
        """
        last = self.config.ticks - 1
        while True:
            with self._cond:
                while True:
                    if self._ended is not None:
                        return self._ended
                    if self.sim.over:
                        return self.sim.end_detail
                    if self.sim.complete >= last:
                        return None
                    if min(self._through) > self.sim.complete:
                        tick = self.sim.complete + 1
                        self._complete_tick(tick)
                        opened = False
                        break
                    if may_open(self._through, self.sim.tick, self.sim.complete, last,
                                self.config.pipelined):
                        tick = self.sim.tick + 1
                        self.sim.open_tick(tick)
                        self._progress = time.monotonic()
                        opened = True
                        break
                    left = self._progress + self.config.agent_timeout - time.monotonic()
                    if left <= 0:
                        return self._stalled()
                    self._cond.wait(left)
            if opened:
                self._tick_pub.put(encode(TickStart(tick=tick, t=self.sim.time_of(tick))))
            elif self.on_tick is not None:
                self.on_tick(tick)

    def _run_realtime_tick(self, tick: int) -> str | None:
        """Run one realtime tick, paced by the wall clock; return why the run must end, or None."""
        with self._cond:
            self.sim.start_tick(tick)
            self._tick_started = self._progress = time.monotonic()
        self._tick_pub.put(encode(TickStart(tick=tick, t=self.sim.time_of(tick))))
        limit = self.config.agent_timeout
        with self._cond:
            # a dead agent misses at once: those behind it keep their time budget
            for agent in sorted(set(range(self.sim.n_agents)) - self._alive):
                self._mark_missed(agent, "its process is not live")
            share = self.period / self.sim.n_agents
            while self._ended is None and not self.sim.over and min(self._through) < tick:
                waiting = min(k for k in range(self.sim.n_agents) if self._through[k] < tick)
                # the clock restarts whenever some agent gets through the tick; the agent
                # waited for has the rest of the period, and at least its share of a period
                # after its predecessor: one stalled agent never eats its successors' time
                deadline = min(self._progress + limit,
                               max(self._tick_started + self.period, self._progress + share))
                left = deadline - time.monotonic()
                if left <= 0:
                    self._mark_missed(waiting, "did not settle in time")
                    continue
                self._cond.wait(left)
            if self._ended is not None:
                return self._ended
            if self.sim.over:
                return self.sim.end_detail
            self._complete_tick(tick)
            next_start = self._tick_started + self.period
            while self._ended is None and (left := next_start - time.monotonic()) > 0:
                self._cond.wait(left)
        return None

    def _told(self, reason: str) -> str:
        """What agents are told of why the run ended: the swarm's meeting the end of the
        surface's domain without where (``WorldSim.end_reason``; absolute coordinates are
        the world's), any other reason as it is."""
        ended = self.sim.end_tick is not None and reason == self.sim.end_detail
        return self.sim.end_reason if ended else reason

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
        self._journal.keep_after(self.sim.complete)

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
            if self.config.mode == "lockstep":
                reason = self._run_lockstep() or ""
            else:
                for tick in range(self.recorder.ticks_done, self.config.ticks):
                    ended = self._run_realtime_tick(tick)
                    if ended is not None:
                        reason = ended
                        break
                    if self.on_tick is not None:
                        self.on_tick(tick)
            with self._cond:
                failure = self._disk_failure
            if failure is not None:
                raise failure
        except OSError as exc:  # the results disk failed (full, read-only): say which file
            self._record_failure(exc)
            raise
        except BaseException:
            with self._cond:
                self.recorder.write_summary(complete=False, reason="interrupted",
                                            wall_time=self._wall(), final=True)
            raise
        complete = not reason
        if reason:
            log.info("world: run ended early: %s", reason)  # the caller says it
        elif self.config.mode == "lockstep":
            # an agent that vanished after it was through every tick (pipelined, long before
            # the run completes) gets time to come back and see world/done
            self._wait_live(self.config.agent_timeout)
        with self._cond:
            self.recorder.write_summary(complete=complete, reason=reason, wall_time=self._wall(),
                                        final=True)
        done = encode(Done(tick=max(self.recorder.ticks_done - 1, 0), results=str(self.out_dir),
                           complete=complete, reason=safe_text(self._told(reason))))
        with self._cond:
            self._finished = done
        self._done_pub.put(done)
        self._wait_agents_gone(timeout=5.0)
        if complete:  # a world killed before this resumes into the end phase again
            checkpoint.discard(self.out_dir)
        return self.recorder.summary(complete=complete, reason=reason, wall_time=self._wall())

    def _record_failure(self, exc: OSError) -> None:
        """Mark the run incomplete with the file that could not be written and why; if even
        that summary cannot be written, the caller's error line is all there is."""
        name = Path(exc.filename).name if exc.filename else "the results"
        reason = f"cannot write {name}: {exc.strerror or exc}"
        with self._cond:
            if self._ended is None:  # the run is ending: its agents leave without a warning
                self._ended = reason
            try:
                self.recorder.write_summary(complete=False, reason=reason, wall_time=self._wall(),
                                            final=True)
            except OSError as again:
                log.error("world: cannot write the summary either: %s", again)

    def _wait_agents_gone(self, timeout: float) -> None:
        """Give agents time to see ``world/done`` and leave before the session closes."""
        self._wait_until(lambda: not self._alive, timeout)
