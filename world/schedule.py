"""The lockstep tick order (design §4), one owner for every layout.

The Zenoh service (:mod:`world.service`) and the in-memory layout (:mod:`swarm.local`) ask
these two functions when a tick may open and when an agent may begin a tick, so their orders
cannot drift apart. ``through[k]`` is the last tick the world has agent ``k`` through (-1
before tick 0); agent 0 is the leader.
"""
from __future__ import annotations

from collections.abc import Sequence


def may_open(through: Sequence[int], opened: int, complete: int, last: int,
             pipelined: bool) -> bool:
    """Whether tick ``opened + 1`` may open (``opened`` is the newest open tick, ``complete``
    the newest tick every agent is through, ``last`` the run's last): pipelined, once the
    leader is through ``opened``, so the column moves as a wavefront, and no deeper than the
    column (``opened`` less than one tick per agent ahead of ``complete``); unpipelined, once
    every agent is.

    The depth is all a wavefront can use: agent ``k`` is at most one tick ahead of agent
    ``k + 1``, so with every agent busy the leader is ``len(through) - 1`` ticks ahead of the
    last follower. Without the bound a leader faster than its column ran ahead of it without
    end (over Zenoh, 3 followers: 9,139 ticks against their 3,952 after 37 s), and the world
    kept every tick it was ahead by (its rows to come, its requests in the journal),
    iterating over them at every tick, so each tick of a long run cost more than the last.

    >>> may_open([3, 2, 1], opened=3, complete=1, last=9, pipelined=True)
    True
    >>> may_open([3, 2, 1], opened=3, complete=1, last=9, pipelined=False)
    False
    >>> may_open([3, 2, 0], opened=3, complete=0, last=9, pipelined=True)  # as deep as it gets
    False
    """
    gate = through[0] if pipelined else min(through)
    return opened < last and gate >= opened and opened - complete < len(through)


def predecessor_through(through: Sequence[int], agent: int, tick: int) -> bool:
    """Whether ``agent``'s predecessor lets it act at ``tick``: the leader has none; a
    follower acts once the agent ahead of it is through ``tick`` (its rod end is settled).

    >>> predecessor_through([3, 1, 0], agent=2, tick=1), predecessor_through([3, 1, 0], 2, 2)
    (True, False)
    """
    return agent == 0 or through[agent - 1] >= tick
