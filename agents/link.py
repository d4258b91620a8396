"""An agent's side of the wire: its Zenoh declarations, waits with timeouts, world queries.

:class:`AgentLink` subscribes to what the agent needs (``world/tick``, ``world/done``, its
leader's rod, the world's liveliness), holds the agent's liveliness token, and offers
blocking waits that end with :class:`AgentAbort` on timeout, on ``world/done`` or when the
world disappears, so no agent ever hangs.

A stall is not a death (design §4). When this process (or the world) is paused for longer than
Zenoh's lease (SIGSTOP, a long garbage collection, a slow disk), the router drops its session;
the session reconnects by itself once the process runs again, and the world may meanwhile have
rolled this agent's tick back. The link sees it as the world's liveliness token going and
coming back: every wait and query then raises :class:`Rejoin`, and the agent joins again
(``JoinRequest``) from where the world has it. The world counts as gone only if its token is
not back within the run's ``start_timeout`` (the time an agent waits for its world at start)
and a fresh liveliness query does not find it either: a paused world, or one started again with
``--resume``, finds its agents still there.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace

import zenoh

from protocol import keys
from protocol.config import AgentSettings
from protocol.messages import (
    ActResult,
    ActSensing,
    Control,
    Done,
    Drive,
    ErrorReply,
    Joined,
    JoinRequest,
    Message,
    Missed,
    Move,
    Observation,
    ProtocolError,
    Rod,
    SenseRequest,
    Sensing,
    Snap,
    TickStart,
    decode,
    encode,
)
from protocol.session import token_live, undeclare_all

log = logging.getLogger(__name__)

QUERY_TIMEOUT_S = 10.0  # the least time an agent waits for the world's reply to a query
WAIT_RETRY_S = 0.002  # pause before asking again after a ``wait`` refusal
MAX_HELD = 256  # most predecessor ticks held until the world announces them
WORLD_RETURN_S = 3.0
"""The least time an agent whose session to the world was cut waits for the world's token to
come back before it asks once more and, if no world answers, concludes that the world process
has gone (an agent of a run waits its ``start_timeout``, :meth:`AgentLink.for_agent`)."""
RELEASE_S = 10.0
"""The most time :meth:`AgentLink.close` waits for Zenoh to let go of the link's callbacks
(it takes milliseconds; a loaded machine may take longer)."""


class AgentAbort(RuntimeError):
    """The agent must stop: the run is done, the world vanished, or a wait timed out."""


class RunFinished(AgentAbort):
    """``world/done`` arrived: a normal end (``complete`` False: the run ended early)."""

    def __init__(self, message: str, complete: bool = True) -> None:
        super().__init__(message)
        self.complete = complete


class Rejoin(RuntimeError):
    """The session to the world was cut and is back (this process or the world stalled): the
    world may have rolled this agent's tick back, so it must join again."""


class MarkedMissed(RuntimeError):
    """The world marked this agent as having missed the current tick; go on with the next."""


class AgentLink:
    """Zenoh declarations and waits of agent ``agent_id`` in run ``run_id``.

    Parameters
    ----------
    session : zenoh.Session
        An open session (closed by the caller).
    run_id, agent_id : str, int
    follow : int or None
        The agent whose rod this one waits for (``agent_id - 1`` for followers; None for the
        leader, which waits for world ticks instead).
    query_timeout : float
        Seconds to wait for any world reply.
    lockstep : bool
        Lockstep mode: the agent does every tick, one after the other (its predecessor, or the
        world, may be several ticks ahead in a pipelined run); else (realtime) it jumps to the
        newest tick announced.
    """

    @classmethod
    def for_agent(cls, session: zenoh.Session, settings: AgentSettings, agent_id: int) -> AgentLink:
        """The link of agent ``agent_id`` (0: the leader, which follows the world's ticks) with
        the run's timing."""
        return cls(session, settings.run_id, agent_id, agent_id - 1 if agent_id else None,
                   query_timeout=max(settings.agent_timeout, QUERY_TIMEOUT_S),
                   lockstep=settings.mode == "lockstep", end_timeout=settings.step_timeout,
                   world_return=max(settings.start_timeout, WORLD_RETURN_S))

    def __init__(self, session: zenoh.Session, run_id: str, agent_id: int, follow: int | None,
                 query_timeout: float, lockstep: bool = True,
                 end_timeout: float | None = None, world_return: float = WORLD_RETURN_S) -> None:
        self.session, self.run_id, self.agent_id = session, run_id, agent_id
        self.query_timeout, self.lockstep = query_timeout, lockstep
        self.world_return = world_return  # how long a vanished world's token is waited for
        # how long to wait for world/done once the world said the run ends before this tick
        # (it still completes the ticks before it with the other agents)
        self.end_timeout = query_timeout if end_timeout is None else end_timeout
        self._cond = threading.Condition()
        self._latest = -1  # newest tick announced by whatever this agent waits for
        self._world_tick = -1  # newest tick the world announced
        self._heard = -1  # newest tick the world announced since this agent last asked to join
        self._held: set[int] = set()  # predecessor ticks held until the world announces them
        self._done: Done | None = None
        self._closed = False  # this agent's session (its world subscriber) has gone
        self._world_alive = False
        self._world_seen = False
        self._cuts = 0  # how often the world's token went away since it was first seen
        self._joined_at = 0  # the value of _cuts when this agent last joined
        self._epoch = 0  # the world's number of that join, which its requests carry
        self._declared = []
        if token_live(session, keys.alive(run_id, agent_id)):
            raise AgentAbort(f"agent id {agent_id} is already live in run {run_id}: "
                             "refusing to start")
        self.follow = follow
        self._declared.append(session.declare_subscriber(keys.tick(run_id), self._on_tick))
        if follow is not None:
            self._declared.append(session.declare_subscriber(keys.rod(run_id, follow),
                                                             self._on_rod))
            # a leader that missed its tick counts as settled where it stands
            self._declared.append(session.declare_subscriber(keys.missed(run_id), self._on_missed))
        self._declared.append(session.declare_subscriber(keys.done(run_id), self._on_done))
        # its drop callback runs when the subscriber goes, with the session closed from
        # outside too (a launcher ending in-process agents): no wait then outlasts the session
        self._declared.append(session.liveliness().declare_subscriber(
            keys.alive(run_id, "world"),
            zenoh.handlers.Callback(self._on_world_liveliness, self._on_closed), history=True))
        self._sense_key = keys.sense(run_id, agent_id)
        self._act_key = keys.act(run_id, agent_id)
        # BLOCK: a rod or observation is never dropped when a link is congested (a peer may
        # flood it with data); lockstep would stall waiting for it.
        self._rod_pub = session.declare_publisher(
            keys.rod(run_id, agent_id), congestion_control=zenoh.CongestionControl.BLOCK)
        self._obs_pub = session.declare_publisher(
            keys.obs(run_id, agent_id), congestion_control=zenoh.CongestionControl.BLOCK)
        self._declared += [self._rod_pub, self._obs_pub]
        # Declared last: when the world sees it, every subscription above is in place.
        self._token = session.liveliness().declare_token(keys.alive(run_id, agent_id))
        self._declared.append(self._token)

    def close(self) -> None:
        """Undeclare everything (the session itself stays open), then wait until Zenoh has let
        go of this link's callbacks: the world-liveliness subscriber's drop callback, the last
        one Zenoh calls, runs on a Zenoh thread after the undeclaration (or the session's
        closing) returns. An agent thread of an in-process run ends only after it, so no
        Zenoh thread calls into the interpreter once the launcher has joined its agents
        (one that did while the interpreter finalises aborts the process). The wait is
        bounded (:data:`RELEASE_S`); past it a warning says so."""
        undeclare_all(self._declared)
        with self._cond:
            released = self._cond.wait_for(lambda: self._closed, RELEASE_S)
        if not released:
            log.warning("agent %d: Zenoh did not release its callbacks within %g s",
                        self.agent_id, RELEASE_S)

    # --- callbacks -----------------------------------------------------------------------------

    def _decode(self, sample: zenoh.Sample, kind: type[Message]) -> Message | None:
        """The sample's message, or None (logged and dropped) if it is malformed."""
        try:
            return decode(sample.payload, kind)
        except ProtocolError as exc:
            log.warning("agent %d: dropped bad sample on %s: %s", self.agent_id, sample.key_expr,
                        exc)
            return None

    def _on_tick(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, TickStart)
        if msg is None:
            return
        with self._cond:
            self._world_tick = max(self._world_tick, msg.tick)
            self._heard = max(self._heard, msg.tick)
            due = {t for t in self._held if t <= self._world_tick + 1}
            self._held -= due
            held = max(due, default=-1)
        if self.follow is None:  # the leader's step is the world's tick
            self.advance(msg.tick)
        elif held >= 0:
            self.advance(held)

    def _on_rod(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, Rod)
        if msg is not None:
            self._predecessor_through(msg.tick, sample)

    def _on_missed(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, Missed)
        if msg is not None and msg.agent == self.follow:
            self._predecessor_through(msg.tick, sample)

    def _predecessor_through(self, tick: int, sample: zenoh.Sample) -> None:
        """The predecessor got through ``tick``. A tick more than one ahead of the world's
        newest is not believed (design §8) until the world announces it: in a pipelined run the
        predecessor's rods may overtake the world's announcements (they are not dropped, or
        the agent would wait for them in vain)."""
        with self._cond:
            ahead = tick > self._world_tick + 1
            if ahead:
                self._held.add(tick)
                if len(self._held) > MAX_HELD:  # a flood of far-future ticks: keep the nearest
                    self._held.discard(max(self._held))
        if ahead:
            log.debug("agent %d: holding the sample on %s for tick %d: the world is at tick %d",
                      self.agent_id, sample.key_expr, tick, self._world_tick)
            return
        self.advance(tick)

    def advance(self, tick: int) -> None:
        """This agent may act at ``tick`` (announced by its step source, or by a join)."""
        with self._cond:
            if tick > self._latest:
                self._latest = tick
                self._cond.notify_all()

    def _on_done(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, Done)
        if msg is not None:
            with self._cond:
                self._done = msg
                self._cond.notify_all()

    def _on_world_liveliness(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self._world_alive = sample.kind == zenoh.SampleKind.PUT
            if self._world_seen and not self._world_alive:
                self._cuts += 1
            self._world_seen = self._world_seen or self._world_alive
            self._cond.notify_all()

    def _on_closed(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # --- waits (the helpers below are called holding ``_cond``) --------------------------------

    def _raise_if_finished(self) -> None:
        """Raise RunFinished once ``world/done`` has arrived, AgentAbort once this agent's
        session is closed."""
        if self._done is not None:
            raise RunFinished(f"run finished: results in {self._done.results}",
                              complete=self._done.complete)
        if self._closed:
            raise AgentAbort(f"agent {self.agent_id}: its session was closed")

    def _cut(self) -> bool:
        """(Lock held.) Whether the session to the world was cut since this agent joined."""
        return self._cuts != self._joined_at

    def _after_cut(self) -> None:
        """(Lock not held.) The session was cut: raise :class:`Rejoin` once the world's token
        is back, or AgentAbort if no world is found (RunFinished if the run ended meanwhile)."""
        with self._cond:
            back = self._cond.wait_for(
                lambda: self._world_alive or self._done is not None or self._closed,
                self.world_return)
            self._raise_if_finished()
        if not back and not token_live(self.session, keys.alive(self.run_id, "world"),
                                       timeout=1.0):
            raise AgentAbort("the world process disappeared")
        raise Rejoin(f"agent {self.agent_id}: its session to the world was cut and is back "
                     "(a stall?): joining again")

    def wait_step(self, after: int, timeout: float) -> int:
        """Block until a tick newer than ``after`` is announced; return the next one to do
        (``after + 1`` in lockstep, else the newest).

        Raises RunFinished on ``world/done``, :class:`Rejoin` if the session to the world was
        cut and is back, and AgentAbort if the world vanishes or nothing comes within
        ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while not self._cut():
                if self._latest > after:
                    return after + 1 if self.lockstep else self._latest
                self._raise_if_finished()
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AgentAbort(f"agent {self.agent_id}: nothing to do for {timeout:.1f} s "
                                     "(is the world running?)")
                self._cond.wait(left)
        self._after_cut()

    # --- world requests ------------------------------------------------------------------------

    def _query(self, key: str, request: Message, expected: type[Message]) -> Message:
        """The world's reply; a ``wait`` refusal (the world has not yet seen what this agent
        reacted to, e.g. its predecessor's rod) is asked again shortly, up to the timeout."""
        deadline = time.monotonic() + self.query_timeout
        payload = encode(request)
        failure = f"no reply from the world on {key} within {self.query_timeout} s"
        while (left := deadline - time.monotonic()) > 0:
            with self._cond:
                cut = self._cut()
            if cut:  # never act across a cut: the world may have rolled this tick back
                self._after_cut()
            reply = next(iter(self.session.get(key, payload=payload, timeout=left)), None)
            with self._cond:
                cut = self._cut()
            if cut:  # a reply from before the cut is not believed either
                self._after_cut()
            if reply is None:  # no reply at all within the time left
                break
            if reply.ok is not None:
                return decode(reply.ok.payload.to_bytes(), expected)
            try:
                error = decode(reply.err.payload.to_bytes(), ErrorReply)
            except ProtocolError:
                # Not the world's refusal but Zenoh's own error, e.g. the query timed out
                # because the world died with it in flight. Not asked again: the world may
                # have acted on it (a second move in the same tick is refused).
                problem = reply.err.payload.to_bytes()[:200].decode(errors="replace")
                failure = (f"the world did not answer {request.TYPE} at tick "
                           f"{request.tick}: {problem}")
                break
            if error.code == "stale":  # the world has it joined again since (design §8)
                raise Rejoin(f"agent {self.agent_id}: {error.error}: joining again")
            if error.code == "missed":
                raise MarkedMissed(error.error)
            if error.code == "ended":
                self._await_done(error.error)
            if error.code != "wait":
                raise AgentAbort(f"the world refused {request.TYPE} at tick {request.tick}: "
                                 f"{error.error}")
            time.sleep(WAIT_RETRY_S)
        with self._cond:  # a world that died or a session cut mid-query: its token goes soon
            cut = self._cond.wait_for(self._cut, timeout=1.0)
        if cut:
            self._after_cut()
        raise AgentAbort(failure)

    def _await_done(self, why: str) -> None:
        """The world said the run ends before this agent's tick (``why``): wait for
        ``world/done`` (raised as RunFinished) while the world completes the earlier ticks."""
        with self._cond:
            self._cond.wait_for(lambda: self._done is not None or self._cut() or self._closed,
                                timeout=self.end_timeout)
            self._raise_if_finished()
            cut = self._cut()
        if cut:
            self._after_cut()
        raise AgentAbort(f"the run ends ({why}), but world/done did not come within "
                         f"{self.end_timeout:g} s")

    def join(self, timeout: float) -> Joined:
        """Wait (up to ``timeout`` s) for the world, then ask it where the run stands: the first
        thing an agent process does, and what it does again after :class:`Rejoin`."""
        deadline = time.monotonic() + timeout
        while True:
            with self._cond:
                self._joined_at = self._cuts
                before, self._heard = self._world_tick, -1
                while not self._world_alive:
                    self._raise_if_finished()
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise AgentAbort(f"agent {self.agent_id}: no world for run "
                                         f"{self.run_id} within {timeout:.1f} s (is the world "
                                         "running?)")
                    self._cond.wait(left)
            try:
                joined = self._query(self._act_key, JoinRequest(tick=0), Joined)
            except Rejoin:  # cut again while joining: ask again
                continue
            break
        with self._cond:
            self._epoch = joined.epoch
            if joined.world < before:
                # a world started again with --resume, behind what the earlier one announced
                # (a stalled world never goes back): those later ticks no longer stand, only
                # what this world announced since it was asked
                self._world_tick = max(joined.world, self._heard)
                self._latest = min(self._latest, self._world_tick + (self.follow is not None))
            else:
                self._world_tick = max(self._world_tick, joined.world)
        if joined.ready and not joined.settled:
            self.advance(joined.until)
        return joined

    def sense(self, tick: int, look: bool = False) -> Sensing:
        """The pre-move sensing of ``tick`` (once per tick, before any action); ``look``: it
        carries the rod end, if in range, and the distance from which the follower looked
        counts in the tick's required range (design §4, §5)."""
        return self._query(self._sense_key,
                           SenseRequest(tick=tick, look=look, epoch=self._epoch), Sensing)

    def act(self, request: Drive | Move | Snap | Control) -> ActResult | ActSensing:
        """Ask the world to act; a move, control step or snap is answered with the sensing
        after it. The request is sent numbered with this agent's latest join."""
        return self._query(self._act_key, replace(request, epoch=self._epoch),
                           ActResult if isinstance(request, Drive) else ActSensing)

    def publish_rod(self, tick: int, length: float, side: int) -> None:
        self._rod_pub.put(encode(Rod(tick=tick, length=length, side=side)))

    def publish_obs(self, obs: Observation) -> None:
        self._obs_pub.put(encode(obs))
