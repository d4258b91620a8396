"""Test support for ``--motion drive``: a world with its tick open for follower 1's steps."""
from __future__ import annotations

from protocol.config import RunConfig
from world.main import resolve_with_surface
from world.sim import WorldSim


def drive_world(**options) -> tuple[WorldSim, RunConfig]:
    """A driving run's world (``options`` of :class:`RunConfig`) at tick 0, the leader
    moved: follower 1 may send its control steps."""
    config, surface = resolve_with_surface(RunConfig(motion="drive", **options))
    sim = WorldSim(config, surface)
    sim.start_tick(0)
    sim.drive(0, 0, 0.0)
    return sim, config
