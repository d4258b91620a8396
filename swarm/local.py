"""The same run without a network: agents call the world's simulation directly.

Every number comes from the same code as a Zenoh run (``WorldSim`` for the world,
``agents.follower.follower_tick`` and the policies for the followers); only the transport is
replaced by function calls, with the messages still passed through the codec. A test checks
that this layout gives numbers identical to the Zenoh layouts. Used for fast estimator studies
and for the benchmark tables; ``swarm experiment`` itself runs over Zenoh.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from agents.follower import follower_tick
from agents.policies import Policy, make_policy
from protocol.config import AgentSettings, RunConfig
from protocol.messages import (
    ActSensing,
    Control,
    Message,
    Move,
    Observation,
    Sensing,
    Snap,
    decode,
    encode,
)
from world.main import resolve_with_surface
from world.results import RunRecorder
from world.sim import RunEnded, WorldSim


class LocalLink:
    """The ``sense``/``act`` half of ``agents.link.AgentLink``, answered by a ``WorldSim``."""

    def __init__(self, sim: WorldSim, agent: int) -> None:
        self.sim, self.agent = sim, agent

    @staticmethod
    def _wire(msg: Message) -> Message:
        return decode(encode(msg), type(msg))

    def sense(self, tick: int, phase: str) -> Sensing:
        return self._wire(self.sim.sense(self.agent, tick, phase))

    def act(self, request: Move | Snap | Control) -> ActSensing:
        return self._wire(self.sim.act(self.agent, self._wire(request)))


def run_local(config: RunConfig, out_dir: str | Path | None = None,
              policy_factory: Callable[[AgentSettings], Policy] = make_policy,
              link_factory: Callable[[WorldSim, int], LocalLink] = LocalLink,
              ) -> tuple[dict, list[dict]]:
    """Run ``config`` in this thread; return (summary, ticks rows). Writes results if ``out_dir``.

    ``policy_factory`` builds each follower's policy (default: the one the config names);
    estimator studies pass their own. ``link_factory`` builds each follower's link (one that
    also notes what the world did, for figures of what happens within a tick).
    """
    config, surface = resolve_with_surface(config)
    sim = WorldSim(config, surface)
    settings = AgentSettings.from_config(config)
    policies = [policy_factory(settings) for _ in range(config.followers)]
    links = [link_factory(sim, k) for k in range(1, config.followers + 1)]
    recorder = RunRecorder(out_dir, config)
    if out_dir is not None:
        recorder.open()
    rows: list[dict] = []

    def follower(k: int, tick: int) -> tuple[int, Observation]:
        return k, follower_tick(links[k - 1], policies[k - 1], settings, tick).observation

    def finish(tick: int, observations: list[tuple[int, Observation]]) -> None:
        tick_rows = sim.finish_tick(tick)
        rows.extend(tick_rows)
        recorder.add_tick(tick_rows, observations)

    def act(action: Callable, *args):
        """``action(*args)``, or None if it met a condition that ends the run (the world
        keeps the earliest such tick, ``sim.end_tick``, as in a Zenoh run)."""
        try:
            return action(*args)
        except RunEnded:
            return None

    def ends_before(tick: int) -> bool:
        return sim.end_tick is not None and tick >= sim.end_tick

    n, ticks = config.followers, config.ticks
    if config.pipelined:  # a wavefront: at step s, agent k does tick s - k (SPEC §4)
        pending: dict[int, list] = {}
        for step in range(ticks + n):
            if step < ticks and not ends_before(step):
                sim.open_tick(step)
                act(sim.drive, 0, step, sim.time_of(step))
            for k in range(1, n + 1):
                if 0 <= step - k < ticks and not ends_before(step - k):
                    done = act(follower, k, step - k)
                    if done is not None:
                        pending.setdefault(step - k, []).append(done)
            if step - n >= 0 and not ends_before(step - n):
                finish(step - n, pending.pop(step - n))
    else:  # one agent at a time
        for tick in range(ticks):
            if ends_before(tick):
                break
            sim.start_tick(tick)
            act(sim.drive, 0, tick, sim.time_of(tick))
            observations = [act(follower, k, tick) for k in range(1, n + 1)
                            if not ends_before(tick)]
            if not ends_before(tick):
                finish(tick, observations)
    complete, reason = sim.end_tick is None, sim.end_reason
    if out_dir is not None:
        recorder.write_summary(complete=complete, reason=reason)
        recorder.close()
    return recorder.summary(complete=complete, reason=reason), rows
