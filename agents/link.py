"""An agent's side of the wire: its Zenoh declarations, waits with timeouts, world queries.

:class:`AgentLink` subscribes to what the agent needs (``world/tick``, ``world/done``, its
leader's rod, the world's liveliness), holds the agent's liveliness token, and offers
blocking waits that end with :class:`AgentAbort` on timeout, on ``world/done`` or when the
world disappears, so no agent ever hangs.
"""
from __future__ import annotations

import logging
import threading
import time

import zenoh

from protocol import keys
from protocol.messages import (
    ActRequest, ActResult, Done, ErrorReply, Message, Missed, Observation, ProtocolError, Rod,
    Sensing, SenseRequest, TickStart, decode, encode,
)

log = logging.getLogger(__name__)

QUERY_TIMEOUT_S = 10.0  # the least time an agent waits for the world's reply to a query


class AgentAbort(RuntimeError):
    """The agent must stop: the run is done, the world vanished, or a wait timed out."""


class RunFinished(AgentAbort):
    """``world/done`` arrived: a normal end."""


class TickMissed(RuntimeError):
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
    """

    def __init__(self, session: zenoh.Session, run_id: str, agent_id: int, follow: int | None,
                 query_timeout: float) -> None:
        self.session, self.run_id, self.agent_id = session, run_id, agent_id
        self.query_timeout = query_timeout
        self._cond = threading.Condition()
        self._latest = -1  # newest tick announced by whatever this agent waits for
        self._done: Done | None = None
        self._world_alive = False
        self._world_seen = False
        self._declared = []
        if self._id_in_use():
            raise AgentAbort(f"agent id {agent_id} is already live in run {run_id}: refusing to start")
        self.follow = follow
        source = keys.tick(run_id) if follow is None else keys.rod(run_id, follow)
        kind = TickStart if follow is None else Rod
        self._declared.append(session.declare_subscriber(source, lambda s: self._on_step(s, kind)))
        if follow is not None:  # a leader that missed its tick counts as settled where it stands
            self._declared.append(session.declare_subscriber(keys.missed(run_id), self._on_missed))
        self._declared.append(session.declare_subscriber(keys.done(run_id), self._on_done))
        self._declared.append(session.liveliness().declare_subscriber(
            keys.alive(run_id, "world"), self._on_world_liveliness, history=True))
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
        """Undeclare everything (the session itself stays open)."""
        for handle in reversed(self._declared):
            try:
                handle.undeclare()
            except zenoh.ZError:  # already gone with a closing session
                pass
        self._declared.clear()

    # --- callbacks -----------------------------------------------------------------------------

    def _id_in_use(self) -> bool:
        replies = self.session.liveliness().get(keys.alive(self.run_id, self.agent_id), timeout=0.5)
        return any(reply.ok is not None for reply in replies)

    def _decode(self, sample: zenoh.Sample, kind: type[Message]) -> Message | None:
        """The sample's message, or None (logged and dropped) if it is malformed."""
        try:
            return decode(sample.payload, kind)
        except ProtocolError as exc:
            log.warning("agent %d: dropped bad sample on %s: %s", self.agent_id, sample.key_expr, exc)
            return None

    def _on_step(self, sample: zenoh.Sample, kind: type[Message]) -> None:
        msg = self._decode(sample, kind)
        if msg is not None:
            self._advance(msg.tick)

    def _on_missed(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, Missed)
        if msg is not None and msg.agent == self.follow:
            self._advance(msg.tick)

    def _advance(self, tick: int) -> None:
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
            self._world_seen = self._world_seen or self._world_alive
            self._cond.notify_all()

    # --- waits ---------------------------------------------------------------------------------

    def wait_step(self, after: int, timeout: float) -> int:
        """Block until a tick newer than ``after`` is announced; return it.

        Raises RunFinished on ``world/done`` and AgentAbort if the world vanishes or nothing
        comes within ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                if self._latest > after:
                    return self._latest
                if self._done is not None:
                    raise RunFinished(f"run finished: results in {self._done.results}")
                if self._world_seen and not self._world_alive:
                    raise AgentAbort("the world process disappeared")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AgentAbort(f"agent {self.agent_id}: nothing to do for {timeout:.1f} s "
                                     "(is the world running?)")
                self._cond.wait(left)

    # --- world requests ------------------------------------------------------------------------

    def _query(self, key: str, request: Message, expected: type[Message]) -> Message:
        replies = self.session.get(key, payload=encode(request), timeout=self.query_timeout)
        for reply in replies:
            if reply.ok is None:
                try:
                    error = decode(reply.err.payload.to_bytes(), ErrorReply)
                    problem, code = error.error, error.code
                except ProtocolError:  # not the world's: zenoh's own (e.g. a query timeout)
                    problem, code = reply.err.payload.to_bytes()[:200].decode(errors="replace"), "bad-request"
                if code == "missed":
                    raise TickMissed(problem)
                raise AgentAbort(f"the world refused {request.TYPE} at tick {request.tick}: {problem}")
            return decode(reply.ok.payload.to_bytes(), expected)
        raise AgentAbort(f"no reply from the world on {key} within {self.query_timeout} s")

    def sense(self, tick: int, phase: str) -> Sensing:
        return self._query(self._sense_key, SenseRequest(tick=tick, phase=phase), Sensing)

    def act(self, request: ActRequest) -> ActResult:
        return self._query(self._act_key, request, ActResult)

    def publish_rod(self, tick: int, length: float, side: int) -> None:
        self._rod_pub.put(encode(Rod(tick=tick, length=length, side=side)))

    def publish_obs(self, obs: Observation) -> None:
        self._obs_pub.put(encode(obs))
