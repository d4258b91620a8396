"""The follower as it was before ``act`` replies carried the sensing: after each move and snap
it asks ``world/sense`` again, five round trips per tick instead of three. Today's world serves
the pre-move sensing once per tick (design §5) and refuses the second ask, but answers it all
the same: the round trip is the same, and the numbers are those of three trips, with more
waiting. Only ``bench/bench_throughput.py`` starts it: ``python bench/five_trips_follower.py
--id K ...`` takes the arguments of ``python -m agents.follower``.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import follower  # noqa: E402
from agents.link import AgentLink  # noqa: E402
from protocol.messages import Move, SenseRequest, Snap, encode  # noqa: E402

_act = AgentLink.act


def _act_then_sense(self: AgentLink, request):
    reply = _act(self, request)
    if isinstance(request, (Move, Snap)):  # one more round trip; its refusal is ignored
        ask = encode(SenseRequest(tick=request.tick))
        for _ in self.session.get(self._sense_key, payload=ask, timeout=self.query_timeout):
            pass
    return reply


if __name__ == "__main__":
    AgentLink.act = _act_then_sense
    sys.exit(follower.main())
