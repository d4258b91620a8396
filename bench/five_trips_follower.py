"""The follower as it was before ``act`` replies carried the sensing: after each move and snap
it asks ``world/sense`` again (the ``moved`` and ``settled`` sensing), five round trips per
tick instead of three. Same numbers (the world's noise is keyed by tick and phase), more
waiting. Only ``bench/bench_throughput.py`` starts it: ``python bench/five_trips_follower.py
--id K ...`` takes the arguments of ``python -m agents.follower``.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import follower  # noqa: E402
from agents.link import AgentLink  # noqa: E402
from protocol.messages import Move, Snap  # noqa: E402

_act = AgentLink.act


def _act_then_sense(self: AgentLink, request):
    reply = _act(self, request)
    if isinstance(request, (Move, Snap)):
        self.sense(request.tick, "moved" if isinstance(request, Move) else "settled")
    return reply


if __name__ == "__main__":
    AgentLink.act = _act_then_sense
    sys.exit(follower.main())
