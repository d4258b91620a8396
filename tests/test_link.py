"""An agent's queries to the world when the answer is Zenoh's own error, not the world's.

A world killed while a query of an agent is in flight leaves Zenoh to end that query with an
error of its own (seen in a loaded CI run: "Timeout"). That is not a refusal by the world: the
agent must report that the world disappeared when its liveliness token goes, and otherwise
say that the world did not answer, with Zenoh's reason. A stand-in world on loopback answers
the agent's move with such an error.
"""
from __future__ import annotations

import threading

import pytest
import zenoh

from agents.link import AgentAbort, AgentLink
from protocol import keys
from protocol.messages import Move
from protocol.session import free_tcp_endpoint, zenoh_config
from tests.waiting import wait_for

RUN = "link-errors"


@pytest.mark.parametrize("world_dies", [True, False], ids=["world-gone", "world-alive"])
def test_a_zenoh_error_reply_is_not_reported_as_the_worlds_refusal(world_dies):
    endpoint = free_tcp_endpoint()
    asked = []
    with zenoh.open(zenoh_config("peer", listen=[endpoint])) as world:
        token = world.liveliness().declare_token(keys.alive(RUN, "world"))
        gone = threading.Event()

        def answer(query: zenoh.Query) -> None:
            asked.append(str(query.key_expr))
            if world_dies and not gone.is_set():
                token.undeclare()  # what the world's death does to its token
                gone.set()
            query.reply_err(b"Timeout")  # Zenoh's words, not an ErrorReply

        queryable = world.declare_queryable(keys.act(RUN, 1), answer)
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as agent:
            link = AgentLink(agent, RUN, 1, follow=0, query_timeout=5.0)
            try:
                wait_for(lambda: link._world_alive, 10, "the world's liveliness")
                with pytest.raises(AgentAbort) as err:
                    link.act(Move(tick=3, offset=(0.1, 0.2)))
            finally:
                link.close()
        queryable.undeclare()
        if not world_dies:
            token.undeclare()
    message = str(err.value)
    assert "refused" not in message
    if world_dies:
        assert message == "the world process disappeared"
    else:
        assert message == "the world did not answer move at tick 3: Timeout"
    assert len(asked) == 1  # never asked twice: the world may have acted on it


class _Noting(AgentLink):
    """A link that notes when Zenoh calls its world-liveliness subscriber's drop callback."""

    released = False

    def _on_closed(self) -> None:
        self.released = True  # before close's wait can end (it ends on what super() sets)
        super()._on_closed()


@pytest.mark.parametrize("session_closed", [False, True], ids=["undeclared", "session-closed"])
def test_a_closed_link_is_let_go_of_by_zenoh_before_close_returns(session_closed):
    """Zenoh calls the drop callback on a thread of its own, after the undeclaration (or the
    session's closing, as a launcher ending its in-process agents does) returns: ``close``
    waits for it, so an agent thread ends only once no Zenoh thread will call into Python for
    it (one doing so while the interpreter finalises aborts the process)."""
    endpoint = free_tcp_endpoint()
    with zenoh.open(zenoh_config("peer", listen=[endpoint])) as world:
        token = world.liveliness().declare_token(keys.alive(RUN, "world"))
        agent = zenoh.open(zenoh_config("client", connect=[endpoint]))
        try:
            links = [_Noting(agent, RUN, k, follow=k - 1, query_timeout=5.0) for k in (1, 2, 3)]
            wait_for(lambda: all(link._world_alive for link in links), 10, "the world's token")
            if session_closed:
                agent.close()
            for link in links:
                link.close()
                assert link.released
        finally:
            agent.close()
        token.undeclare()
