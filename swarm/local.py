"""The same run without a network: agents call the world's simulation directly.

Every number comes from the same code as a Zenoh run (``WorldSim`` for the world,
``agents.follower.follower_tick`` and the policies for the followers); only the transport is
replaced by function calls, with every message still passed through the codec, and the ticks
follow the service's order (:mod:`world.schedule`). A test checks that this layout gives
numbers identical to the Zenoh layouts. Used for fast estimator studies and for the benchmark
tables; ``swarm experiment`` itself runs over Zenoh.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from agents.drive import Limits, Track
from agents.follower import follower_tick
from agents.policies import Policy, estimator_settings, make_policy
from protocol.config import AgentSettings, RunConfig
from protocol.folder import FolderLock
from protocol.messages import (
    ActResult,
    ActSensing,
    Control,
    Drive,
    Message,
    Move,
    Observation,
    SenseRequest,
    Sensing,
    Snap,
    decode,
    encode,
)
from world.main import resolve_with_surface
from world.results import RunRecorder
from world.schedule import may_open, predecessor_through
from world.sim import RunEnded, WorldSim


class LocalLink:
    """The ``sense``/``act`` half of ``agents.link.AgentLink``, answered by a ``WorldSim``;
    every message goes through the codec both ways, as on the wire."""

    def __init__(self, sim: WorldSim, agent: int) -> None:
        self.sim, self.agent = sim, agent

    @staticmethod
    def wire(msg: Message) -> Message:
        """``msg`` encoded and decoded again (validated as the receiving side does)."""
        return decode(encode(msg), type(msg))

    def sense(self, tick: int, look: bool = False) -> Sensing:
        request = self.wire(SenseRequest(tick=tick, look=look))
        return self.wire(self.sim.sense(self.agent, request.tick, request.look))

    def act(self, request: Drive | Move | Snap | Control) -> ActResult | ActSensing:
        return self.wire(self.sim.act(self.agent, self.wire(request)))


def run_local(config: RunConfig, out_dir: str | Path | None = None,
              policy_factory: Callable[[AgentSettings], Policy] = make_policy,
              link_factory: Callable[[WorldSim, int], LocalLink] = LocalLink,
              ) -> tuple[dict, list[dict]]:
    """Run ``config`` in this thread; return (summary, ticks rows). Writes results if ``out_dir``.

    The ticks follow the lockstep order of the Zenoh service (:mod:`world.schedule`): in
    each step every tick that every agent is through completes, the next tick opens if it
    may, and then every agent that may begin its next tick does it (pipelined, agent ``k``
    does tick ``s - k`` in step ``s``; unpipelined, one agent at a time).
    ``policy_factory`` builds each follower's policy (default: the one the config names);
    estimator studies pass their own. It is given the settings an estimator sees
    (:func:`agents.policies.estimator_settings`: no top speed). ``link_factory`` builds each
    follower's link (one that also notes what the world did, for figures of what happens
    within a tick). ``out_dir``'s one-writer lock is held meanwhile
    (:class:`protocol.folder.FolderLock`).
    """
    if out_dir is None:
        return _simulate(config, None, policy_factory, link_factory)
    with FolderLock(out_dir, config.run_id):
        return _simulate(config, out_dir, policy_factory, link_factory)


def _simulate(config: RunConfig, out_dir: str | Path | None,
              policy_factory: Callable[[AgentSettings], Policy],
              link_factory: Callable[[WorldSim, int], LocalLink]) -> tuple[dict, list[dict]]:
    """:func:`run_local`'s run (its folder locked by the caller)."""
    config, surface = resolve_with_surface(config)
    sim = WorldSim(config, surface)
    settings = AgentSettings.from_config(config)
    limits = Limits.from_settings(settings) if settings.drives else None
    policies = [policy_factory(estimator_settings(settings)) for _ in range(config.followers)]
    tracks = [Track.for_follower(settings) for _ in range(config.followers)]
    links = [LocalLink(sim, 0)] + [link_factory(sim, k)
                                   for k in range(1, config.followers + 1)]
    recorder = RunRecorder(out_dir, config)
    if out_dir is not None:
        recorder.open()
    rows: list[dict] = []
    observations: dict[int, list[tuple[int, Observation]]] = {}  # per open tick

    def agent_tick(k: int, tick: int) -> None:
        if k == 0:  # the leader's time from its settings, as agents.leader's (not the world's)
            links[0].act(Drive(tick=tick, t=tick * settings.comm_period))
            return
        outcome = follower_tick(links[k], policies[k - 1], settings, tick, limits, tracks[k - 1])
        observations.setdefault(tick, []).append((k, LocalLink.wire(outcome.observation)))

    # the service's tick order (world.schedule); an action that meets a condition ending the
    # run leaves its agent where it was, and the world keeps the earliest such tick
    through, last = [-1] * sim.n_agents, config.ticks - 1
    while sim.complete < last and not sim.over:
        while sim.complete < last and min(through) > sim.complete:
            tick = sim.complete + 1
            tick_rows = sim.finish_tick(tick)
            rows.extend(tick_rows)
            recorder.add_tick(tick_rows, observations.pop(tick, []), sim.control_rows(tick))
        if (may_open(through, sim.tick, sim.complete, last, config.pipelined)
                and not sim.ends_before(sim.tick + 1)):
            sim.open_tick(sim.tick + 1)
        ready = [k for k in range(sim.n_agents)
                 if through[k] < sim.tick and not sim.ends_before(through[k] + 1)
                 and predecessor_through(through, k, through[k] + 1)]
        if not ready and not sim.over and sim.complete < last and min(through) <= sim.complete:
            raise RuntimeError(f"no agent can go on at tick {sim.complete + 1}")
        for k in ready:
            try:
                agent_tick(k, through[k] + 1)
            except RunEnded:
                continue
            through[k] += 1
    complete, reason = sim.end_tick is None, sim.end_detail
    if out_dir is not None:
        recorder.write_summary(complete=complete, reason=reason, final=True)
        recorder.close()
    return recorder.summary(complete=complete, reason=reason), rows
