"""Sensing is an act the world sequences (design §4, §5): each reading once and in order, its
noise keyed by the world's count, and the rod end read only by looking, every look counted."""
from __future__ import annotations

import concurrent.futures
import math

import numpy as np
import pytest

from agents.drive import Limits
from agents.follower import follower_tick
from agents.policies import NotReady, Policy, Proposal, make_policy
from protocol.config import AgentSettings, RunConfig
from protocol.messages import Move, Sensing, Snap
from swarm.local import LocalLink, run_local
from world.main import resolve_with_surface
from world.noise import gaussian, reading_noise
from world.sim import RequestError, WorldSim

NOISY = dict(noise_range=0.02, noise_bearing=0.01)


def _world(**options) -> WorldSim:
    config, surface = resolve_with_surface(RunConfig(surface="wavy", ticks=8, seed=3, **options))
    return WorldSim(config, surface)


def _begin(sim: WorldSim, tick: int) -> None:
    sim.start_tick(tick)
    sim.drive(0, tick, sim.time_of(tick))


def _through_initial_ticks(sim: WorldSim) -> int:
    """Follower 1 (the only one) through the initial ticks; the first estimated tick."""
    for tick in range(sim.config.init_ticks):
        _begin(sim, tick)
        sim.sense(1, tick, look=True)
        sim.act(1, Snap(tick=tick))
        sim.finish_tick(tick)
    _begin(sim, sim.config.init_ticks)
    return sim.config.init_ticks


def test_a_reading_asked_again_or_out_of_order_is_refused():
    sim = _world(**NOISY)
    j = _through_initial_ticks(sim)
    sim.sense(1, j)
    with pytest.raises(RequestError, match="already read its pre-move sensing.*comes once"):
        sim.sense(1, j)
    sim.act(1, Move(tick=j, offset=(0.1, 0.0)))
    with pytest.raises(RequestError, match="already acted"):
        sim.sense(1, j)
    sim.act(1, Snap(tick=j))
    with pytest.raises(RequestError, match="already settled"):
        sim.sense(1, j)


def test_the_pre_move_sensing_comes_before_the_move():
    sim = _world(**NOISY)
    j = _through_initial_ticks(sim)
    sim.act(1, Move(tick=j, offset=(0.1, 0.0)))  # a follower may move blind...
    with pytest.raises(RequestError, match="already acted.*before its move"):
        sim.sense(1, j)  # ...but not read "before" it afterwards


def test_an_initial_snap_needs_a_look():
    sim = _world()
    _begin(sim, 0)
    sim.sense(1, 0)  # no look: no rod end to be placed by
    with pytest.raises(RequestError, match="must look for its rod end"):
        sim.act(1, Snap(tick=0))


class Recorder(LocalLink):
    """Notes, beside every reading, the true range to the leader and whether it looked."""

    def __init__(self, sim: WorldSim, agent: int, seen: list) -> None:
        super().__init__(sim, agent)
        self.seen = seen

    def _note(self, reply: Sensing, tick: int, kind: str) -> None:
        state = self.sim.agents[self.agent]
        rel = self.sim.agents[self.agent - 1].settled[tick] - state.pos
        end = self.sim._leader_rod(self.agent, tick)[0]
        self.seen.append((self.agent, tick, kind, reply, math.hypot(*rel),
                          math.hypot(*(end - state.pos))))

    def sense(self, tick, look=False):
        reply = super().sense(tick, look)
        self._note(reply, tick, "pre-look" if look else "pre")
        return reply

    def act(self, request):
        reply = super().act(request)
        self._note(reply.sensing, request.tick, type(request).__name__)
        return reply


@pytest.mark.parametrize("motion", ["teleport", "drive"])
def test_no_two_readings_of_a_run_share_a_draw(motion):
    """Every reading's range error differs from every other's (a shared draw at another pose
    would repeat it); the count that keys them restarts each tick, one per reading."""
    options = dict(NOISY, noise_velocity=0.01)
    if motion == "teleport":
        options["noise_move"] = 0.01
    config = RunConfig(surface="wavy", followers=2, ticks=10, seed=11, motion=motion,
                       estimator="persist", **options)
    seen: list = []
    run_local(config, link_factory=lambda sim, k: Recorder(sim, k, seen))
    per_tick = 3 if motion == "teleport" else 2 + config.control_steps + config.snap_steps
    assert len(seen) > 2 * config.ticks * (2 if motion == "teleport" else 12)
    errors = [reply.r - truth for _, _, _, reply, truth, _ in seen]
    assert all(e != 0.0 for e in errors)
    assert len(set(errors)) == len(errors)
    counts: dict = {}
    for agent, tick, *_ in seen:
        counts[agent, tick] = counts.get((agent, tick), 0) + 1
    assert max(counts.values()) <= per_tick


def test_the_rod_end_is_read_only_by_looking():
    """Without a look the pre-move sensing has no rod end (R_s unlimited); the reading after
    the move and the settled one look; in an initial tick the follower looks before moving."""
    seen: list = []
    config = RunConfig(surface="hyperbolic", ticks=8, estimator="persist", **NOISY)
    run_local(config, link_factory=lambda sim, k: Recorder(sim, k, seen))
    kinds = {}
    for _, tick, kind, reply, _, _ in seen:
        kinds.setdefault((tick < config.init_ticks, kind), set()).add(reply.rod is not None)
    assert kinds == {(True, "pre-look"): {True}, (True, "Snap"): {True},
                     (False, "pre"): {False}, (False, "Move"): {True}, (False, "Snap"): {True}}


class LooksFirst(Policy):
    """A plug-in that looks for its rod end before moving and moves to where it read it."""

    name = "looks-first"
    looks_before_moving = True

    def propose(self, pre: Sensing) -> Proposal:
        if pre.rod is None:
            raise NotReady("no rod end in sight")
        return Proposal(np.asarray(pre.rod, dtype=float))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return ()


@pytest.mark.parametrize("motion", ["teleport", "drive"])
def test_a_look_before_moving_costs_its_distance(motion):
    """Moving to a pre-move rod reading reports a required range no smaller than the
    distance the follower looked from (where it stood: the stay range), tick by tick."""
    seen: list = []
    config = RunConfig(surface="wavy", ticks=16, seed=2, motion=motion, **NOISY)
    _, rows = run_local(config, policy_factory=lambda settings: LooksFirst(),
                        link_factory=lambda sim, k: Recorder(sim, k, seen))
    looked = {tick: far for _, tick, kind, _, _, far in seen if kind == "pre-look"}
    estimated = [r for r in rows if r.get("required_range") is not None]
    assert len(estimated) == config.ticks - config.init_ticks
    for row in estimated:
        assert row["required_range"] >= looked[row["tick"]] > 0.05
        if motion == "teleport":  # it looked from where it stood; after the move, from close by
            assert row["required_range"] == pytest.approx(row["stay_range"], rel=1e-9)
    # the paper's follower never looks before moving: its pre-move sensings carry no rod end
    seen.clear()
    run_local(config.replace(estimator="persist"),
              link_factory=lambda sim, k: Recorder(sim, k, seen))
    assert not any(kind == "pre-look" and tick >= config.init_ticks
                   for _, tick, kind, *_ in seen)


def test_drive_steps_count_their_looks():
    """A driving follower's required range is the longest distance it looked from: after the
    move phase's last step or in its correction window, never in the move phase."""
    config, surface = resolve_with_surface(RunConfig(motion="drive", surface="wavy", ticks=7,
                                                     seed=1, **NOISY))
    sim, settings = WorldSim(config, surface), AgentSettings.from_config(config)
    limits = Limits.from_settings(settings)
    policy, link = make_policy(settings), LocalLink(sim, 1)
    distances: dict = {}
    read = sim.sensors.read

    def noting(agent, tick, sensed, truth, role=""):
        if truth.rod_end is not None and truth.counted:
            distances.setdefault(tick, []).append(float(np.hypot(*(truth.rod_end - truth.own))))
        return read(agent, tick, sensed, truth, role)

    sim.sensors.read = noting
    for tick in range(config.ticks):
        _begin(sim, tick)
        follower_tick(link, policy, settings, tick, limits)
        row = sim.finish_tick(tick)[1]
        if tick >= config.init_ticks:
            assert len(distances[tick]) == 1 + config.snap_steps
            assert row["required_range"] == max(distances[tick])


def test_reading_keys_are_the_worlds_count():
    """Two readings of one tick draw from distinct blocks; the same count draws the same."""
    blocks = [reading_noise(3, 1, 5, n, channel, 1.0, 2) for n in range(4)
              for channel in ("range", "bearing", "rod-range", "rod-bearing")]
    flat = np.concatenate(blocks)
    assert len(set(flat.tolist())) == flat.size
    assert np.array_equal(reading_noise(3, 1, 5, 2, "range", 1.0, 2), blocks[8])
    # nor any block of the world's own streams (actuation, odometry), tick's or step's
    own = [gaussian(3, 1, 5, "range", "act", 1.0, 2, step=step) for step in (None, 0, 1, 2)]
    assert not set(np.concatenate(own).tolist()) & set(flat.tolist())


def test_a_tick_rolled_back_and_redone_reads_the_same_noise():
    """A follower's process vanished mid-tick (lockstep): the world rolls its tick back, its
    pose and its count of readings with it, and the redone tick draws exactly what an
    uninterrupted one does."""
    def tick_replies(interrupted: bool) -> list:
        sim = _world(noise_move=0.01, **NOISY)
        j = _through_initial_ticks(sim)
        if interrupted:  # what the vanished process did, as its deterministic redo will
            sim.sense(1, j)
            sim.act(1, Move(tick=j, offset=(0.1, 0.0)))
            sim.rollback(1, j)
        replies = [sim.sense(1, j), sim.act(1, Move(tick=j, offset=(0.1, 0.0))),
                   sim.act(1, Snap(tick=j))]
        return replies + [sim.finish_tick(j)[1]]

    assert tick_replies(True) == tick_replies(False)


def test_a_redone_tick_that_acts_otherwise_is_refused():
    """A rolled-back tick draws the same noise again, so a follower that rejoined mid-tick on
    purpose and moved elsewhere would read the same draws from another pose and could solve
    for the truth: a redo must repeat the undone attempt's requests (it may go further)."""
    sim = _world(**NOISY)
    j = _through_initial_ticks(sim)
    sim.sense(1, j)
    sim.act(1, Move(tick=j, offset=(0.5, 0.0)))
    sim.rollback(1, j)
    with pytest.raises(RequestError, match="must repeat"):
        sim.sense(1, j, look=True)
    sim.sense(1, j)
    with pytest.raises(RequestError, match="must repeat"):
        sim.act(1, Move(tick=j, offset=(0.0, 0.5)))
    sim.act(1, Move(tick=j, offset=(0.5, 0.0)))
    sim.act(1, Snap(tick=j))  # past what the undone attempt did: free
    assert sim.is_settled(1, j)


def test_a_process_forked_while_a_block_is_drawn_draws_its_own():
    """The one generator's lock, held by another thread at the fork (a grid worker forked
    from a busy parent), is a fresh one in the child: it draws, the same numbers."""
    import os
    import time

    from world import noise
    with noise._GENERATOR_LOCK:
        pid = os.fork()
        if pid == 0:  # the child: draw, say whether it matched, leave without cleanup
            same = np.array_equal(noise._block.__wrapped__((5, 1, 2), 48),
                                  np.random.default_rng([5, 1, 2]).standard_normal(48))
            os._exit(0 if same else 3)
    deadline = time.monotonic() + 30.0
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    if done[0] == 0:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
        pytest.fail("the forked child hung on the generator's lock")
    assert os.waitstatus_to_exitcode(done[1]) == 0


def test_a_noise_block_is_numpys_draw_of_its_key_seeded_faster():
    """The world hashes a block's key itself (``SeedSequence``'s algorithm, compiled) and sets
    a kept generator's state by ``PCG64``'s seeding rule instead of handing numpy the list: the
    same draws, whatever the key's length and the size of its ints (a seed up to 2**63 - 1)."""
    from world.noise import _block, _words
    keys = [(0, 0, 0), (1, 2, 3, 0, 1), (2**32 - 1, 5, 6), (2**32, 5, 6), (2**40 + 7, 0, 0, 0, 1),
            (2**63 - 1, 9, 149, 0, 40)]
    seed = int(np.random.SeedSequence().entropy % 2**32)
    print(f"seed {seed}")  # and random keys of 1 to 6 ints of every size
    rng = np.random.default_rng(seed)
    keys += [tuple(int(part) >> int(rng.integers(0, 63))
                   for part in rng.integers(0, 2**63 - 1, size=rng.integers(1, 7)))
             for _ in range(300)]
    for key in keys:
        for size in (48, 192):
            assert np.array_equal(_block.__wrapped__(key, size),
                                  np.random.default_rng(list(key)).standard_normal(size)), key
    def draw(offset: int) -> bool:  # threads drawing at once share the one generator safely
        return all(np.array_equal(_block.__wrapped__((offset, k, 1), 48),
                                  np.random.default_rng([offset, k, 1]).standard_normal(48))
                   for k in range(200))
    with concurrent.futures.ThreadPoolExecutor(4) as pool:
        assert all(pool.map(draw, range(8)))
    assert _words((2**32 + 3, 0)) == [3, 1, 0]
    with pytest.raises(ValueError, match="non-negative"):
        _words((1, -1))
