"""``--motion drive`` (design §4 "Motion"): the unicycle on the surface, the control protocol, the
follower's controller, what is measured, honest noise, refusals, and convergence to the
teleport run as the control steps grow."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from agents.drive import (
    HeadingFilter,
    Limits,
    Track,
    chart_turn,
    goal_heading,
    metric_angle,
    slope_ahead,
    step_command,
    wrap,
)
from agents.follower import follower_tick
from agents.policies import make_policy
from protocol.config import CORRECTION_SHARE, AgentSettings, RunConfig
from protocol.messages import Control, Move, Sensing, Snap
from protocol.record import read_controls, read_ticks
from swarm.cli import main as swarm_main
from swarm.local import LocalLink, run_local
from tests.driving import drive_world
from tests.make_dem_data import HILLS, HILLS_LEADER_START
from world import geometry, motion
from world.main import resolve_with_surface
from world.noise import CHANNELS, PHASES, gaussian
from world.sim import RequestError, WorldSim
from world.surfaces import make_surface

NOISE = dict(noise_range=0.01, noise_bearing=0.005, noise_velocity=0.01, noise_speed=0.02,
             noise_turn=0.02)


def _pos(rows, agent=None):
    return {(r["tick"], r["agent"]): np.array([r["pos_x"], r["pos_y"]]) for r in rows
            if agent is None or r["agent"] == agent}


# --- the unicycle ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["elliptic", "hyperbolic", "wavy"])
def test_driving_straight_is_the_geodesic(name):
    surface = make_surface(name)
    start = np.array([30.0, 5.0])
    heading = motion.unit_heading(surface, start, [-1.0, 0.3])
    end, h = motion.drive(surface, start, heading, 2.5, 0.0, 1.28)
    exact, velocity = geometry.integrate_geodesic(surface, start, 2.5 * heading, 1.28)
    assert np.abs(end - exact).max() < 1e-9
    assert np.abs(h - velocity / 2.5).max() < 1e-9


def test_on_flat_ground_a_constant_command_is_a_circle():
    plane = make_surface("plane", {"a": 0.0, "b": 0.0})
    end, h = motion.drive(plane, [0.0, 0.0], [1.0, 0.0], 1.0, 0.5, 2 * math.pi)  # half a turn
    assert np.abs(end - [0.0, 4.0]).max() < 1e-9  # radius v/ω = 2
    assert np.abs(h - [-1.0, 0.0]).max() < 1e-9


def test_the_turn_rate_is_measured_in_the_metric():
    """On a tilted plane (constant metric, no transport) turning in place by ω t rotates the
    heading by ω t in g: g(h0, h1) = cos(ω t), with the positive orientation."""
    plane = make_surface("plane", {"a": 1.5, "b": -0.5})
    g = geometry.metric(plane, [0.0, 0.0])
    h0 = motion.unit_heading(plane, [0.0, 0.0], [1.0, 0.2])
    _, h1 = motion.drive(plane, [0.0, 0.0], h0, 0.0, 0.7, 1.0)
    assert h1 @ g @ h1 == pytest.approx(1.0, abs=1e-12)
    assert h0 @ g @ h1 == pytest.approx(math.cos(0.7), abs=1e-8)
    assert h0[0] * h1[1] - h0[1] * h1[0] > 0
    # the controller's conversion of a chart turn to the metric angle agrees
    chart = math.atan2(h1[1], h1[0]) - math.atan2(h0[1], h0[0])
    psi = math.atan2(h0[1], h0[0])
    assert metric_angle(np.array([1.5, -0.5]), psi, psi + chart) == pytest.approx(0.7, abs=1e-8)


DEM_RUN = dict(surface=f"dem:{HILLS}", leader_start=HILLS_LEADER_START, ticks=24)


@pytest.mark.parametrize("surface", ["elliptic", "wavy", "dem"])
def test_halving_the_substeps_moves_a_run_by_less_than_a_micrometre(monkeypatch, surface):
    base = DEM_RUN if surface == "dem" else dict(surface=surface, ticks=30)
    config = RunConfig(followers=2, motion="drive", estimator="persist", seed=4, **base,
                       **NOISE)
    _, rows = run_local(config)
    monkeypatch.setattr(motion, "ARC_STEP", motion.ARC_STEP / 2)
    monkeypatch.setattr(motion, "TURN_STEP", motion.TURN_STEP / 2)
    _, finer = run_local(config)
    coarse, fine = _pos(rows), _pos(finer)
    assert coarse.keys() == fine.keys() and len(coarse) >= 3 * 20
    worst = max(float(np.linalg.norm(coarse[key] - fine[key])) for key in coarse)
    assert worst < 1e-6
    assert worst > 0  # the refinement did change the integration


# --- the controller (pure, flat ground) --------------------------------------------------------


def _limits(**changes) -> Limits:
    settings = AgentSettings.from_config(RunConfig(motion="drive", max_speed=1.0, **changes))
    return Limits.from_settings(settings)


def test_the_controller_stays_within_the_limits_and_reverses_to_a_goal_behind():
    limits = _limits(max_turn=0.5)
    v, omega, _ = step_command(np.zeros(2), 0.0, np.zeros(2), np.array([5.0, 1.0]), 0.0, 0.0,
                               0.0, 0, limits)
    assert 0 < v <= limits.max_accel * limits.durations[0] + 1e-12  # from rest
    assert abs(omega) <= 0.5
    v, _, _ = step_command(np.zeros(2), 0.0, np.zeros(2), np.array([-0.05, 0.0]), 0.0, 0.0,
                           0.0, 3, limits)
    assert v < 0  # reverse, keeping the heading


def test_the_timed_drive_lands_on_a_goal_ahead_at_rest():
    """On flat ground a goal straight ahead is reached when the tick ends, every step within
    the acceleration limit, the last one slow enough to stop."""
    plane = make_surface("plane", {"a": 0.0, "b": 0.0})
    limits = _limits()
    p, h, speed, heading = np.zeros(2), np.array([1.0, 0.0]), 0.0, 0.0
    goal = np.array([0.9, 0.0])
    for step, dt in enumerate(limits.durations):
        v, omega, _ = step_command(p, heading, np.zeros(2), goal, 0.0, 0.0, speed, step, limits)
        assert abs(v - speed) <= limits.max_accel * dt + 1e-12
        p, h = motion.drive(plane, p, h, v, omega, dt)
        speed, heading = v, math.atan2(h[1], h[0])
    assert abs(speed) <= limits.max_accel * limits.durations[-1] + 1e-12
    assert np.abs(p - goal).max() < 1e-9


def test_a_step_commands_less_the_turn_the_terrain_adds():
    """With the terrain turning the chart heading by ``r`` rad per metre, a step commands the
    turn the law wants less ``r`` times its arc, so that it turns (and drives along) what the
    law wants; its speed is the same."""
    limits = _limits()
    goal, args = np.array([0.6, 0.08]), (0.05, 0.0, 0.9, 9, limits)
    v0, omega0, turn0 = step_command(np.zeros(2), 0.05, np.zeros(2), goal, *args)
    v, omega, turn = step_command(np.zeros(2), 0.05, np.zeros(2), goal, *args, drift=0.02)
    assert v == v0 and turn0 != 0.0
    assert turn == pytest.approx(turn0 - 0.02 * abs(v) * limits.durations[9], rel=1e-12)
    assert omega == pytest.approx(turn / limits.durations[9], rel=1e-12)  # flat: chart = metric


def test_a_step_is_planned_with_the_slope_half_way_along_it():
    """The slope ``ahead`` m on, from its change per metre over the tick so far: exact without
    noise; a change within three times the tilt readings' declared spread is left out, one far
    beyond it kept almost whole."""
    start, now = np.array([0.3, -0.1]), np.array([0.33, -0.12])
    assert np.allclose(slope_ahead(start, now, 1.5, 0.15, 0.0), now + (now - start) * 0.1)
    assert np.array_equal(slope_ahead(start, now, 0.0, 0.15, 0.0), now)  # nothing driven yet
    assert np.array_equal(slope_ahead(start, now, 1.5, 0.15, 0.02), now)  # within the noise
    far = np.array([1.3, -0.9])
    kept = slope_ahead(start, far, 1.5, 0.15, 0.001) - far
    assert np.allclose(kept, (far - start) * 0.1, rtol=1e-3)


def test_a_goal_a_rounding_error_away_turns_nothing():
    """Case C of issue #30: without noise a leftover of 1e-14 m sets no goal heading and no
    turn (no singular branch)."""
    assert goal_heading(0.7, np.array([3.6e-14, -1e-14]), (), 0.0, 3.57) == 0.7
    _, omega, _ = step_command(np.zeros(2), 0.7, np.zeros(2), np.array([3.6e-14, 2e-14]),
                               0.7, 0.0, 0.0, 11, _limits())
    assert abs(omega) < 1e-9


def test_the_goal_heading_follows_the_chords():
    """Chords of a circle turning 0.2 rad per chord: the end tangent of the last one is its
    direction plus half the turn (the quadratic through the three points: to second order);
    a chord lost in noise keeps the heading."""
    chord, previous = np.array([math.cos(0.3), math.sin(0.3)]), np.array([math.cos(0.1),
                                                                          math.sin(0.1)])
    assert goal_heading(0.2, chord, (previous,), 0.0) == pytest.approx(0.4, abs=3e-3)
    assert goal_heading(0.2, chord, (), 0.0) == pytest.approx(0.4)  # the arc from 0.2
    assert goal_heading(0.2, 0.01 * chord, (previous,), 1e-4) == 0.2


def test_a_path_driven_backwards_gives_its_own_line_not_its_mirror_image():
    """A follower reversing along a straight line at 0.1 rad (its steps point at π + 0.1)
    with its heading at 0: the tangent on the heading's side is the same line, 0.1, and not
    its mirror image across the heading's normal (−0.1, what ``asin(sin(·))`` gave before
    stop 47), with or without noise."""
    back = -np.array([math.cos(0.1), math.sin(0.1)])
    for variance in (0.0, 1e-4):
        assert goal_heading(0.0, back, (back, back), variance) == pytest.approx(0.1, abs=1e-3)


def test_with_no_track_under_noise_the_arc_bends_only_as_far_as_its_bend_stands_out():
    """A column setting off: no past step, one chord. Without noise the goal heading is the
    arc's end tangent, the start heading plus twice the bend. Under noise a bend within the
    chord's angle noise is mostly noise, and doubling it doubles the error: the heading stays
    near the chord's own direction; a bend far above the noise is the arc's, nearly."""
    chord = np.array([math.cos(0.3), math.sin(0.3)])  # 1 m, at 0.3 rad
    assert goal_heading(0.2, chord, (), 0.0) == pytest.approx(0.4)  # the arc: 0.2 + 2 · 0.1
    within = goal_heading(0.29, chord, (), 1e-3)  # a bend of 0.01 rad, its σ about 0.03
    assert abs(within - 0.3) < 0.002  # the chord's direction, not 0.31
    beyond = goal_heading(0.0, chord, (), 1e-5)  # a bend of 0.3 rad, its σ about 0.003
    trust = 1.0 - 9e-5 / float(chord @ chord)  # the chord's trust (goal_heading's docstring)
    assert beyond == pytest.approx(trust * 0.6, abs=1e-3)


def test_the_exact_goal_heading_keeps_the_polynomial_through_a_smooth_path():
    """Without noise, points along a circle (steps of 1.2 m turning 0.05 rad a tick): every
    fit agrees, and the tangent is the quartic's through all of them (equal steps: their
    distances along the path are their ticks)."""
    angles = 0.05 * np.arange(4)
    steps = [1.2 * np.array([math.cos(a), math.sin(a)]) for a in angles]
    track, chord = tuple(steps[:3]), steps[3]
    points = np.cumsum([np.zeros(2), *steps], axis=0)
    times = np.arange(-3.0, 2.0)
    tangent = [np.polyval(np.polyder(np.polyfit(times, points[:, k], 4)), 1.0) for k in (0, 1)]
    assert goal_heading(0.1, chord, track, 0.0) == pytest.approx(
        math.atan2(tangent[1], tangent[0]), abs=1e-9)


def test_the_exact_goal_heading_places_its_points_by_their_distance_along_the_path():
    """Without noise, a path travelled at a changing speed (a column's far end setting off:
    steps of 0.2, 0.5, 1.0 m) has the tangent of the path, not of the speed: points on a
    circle with unequal steps give the circle's tangent at the goal to the fit's order."""
    radius, arcs = 5.0, np.cumsum([0.0, 0.2, 0.5, 1.0, 1.3])
    points = radius * np.stack([np.sin(arcs / radius), 1.0 - np.cos(arcs / radius)], axis=1)
    steps = np.diff(points, axis=0)
    heading = goal_heading(0.0, steps[-1], tuple(steps[:-1]), 0.0)
    assert heading == pytest.approx(arcs[-1] / radius, abs=2e-3)  # 0.6 rad


def test_the_exact_goal_heading_of_a_path_that_stood_still_for_a_tick():
    """Without noise, a track with a step of no length (the follower's rod end did not move
    that tick): placed by their distance along the path two points would coincide and the
    polynomial through them would not exist (the fit raised); they keep their ticks, and
    the heading is the polynomial's through them at their ticks."""
    track = (np.array([1.0, 0.0]), np.zeros(2), np.array([1.0, 0.1]))
    chord = np.array([1.0, 0.15])
    points = np.cumsum([np.zeros(2), *track, chord], axis=0)
    times = np.arange(-3.0, 2.0)
    heading = goal_heading(0.0, chord, track, 0.0)
    fits = [np.polyder(np.polyfit(times[-n:], points[-n:, k], n - 1)) for k in (0, 1)
            for n in (3, 4, 5)]
    candidates = [math.atan2(np.polyval(fits[3 + i], 1.0), np.polyval(fits[i], 1.0))
                  for i in range(3)]
    assert math.isfinite(heading)
    assert min(abs(heading - c) for c in candidates) < 1e-9


def test_the_exact_goal_heading_drops_a_fit_the_path_s_turns_cannot_explain():
    """Follower 4's rod ends on wavy at a comm period of 2.56 s (tick 35): steps of 3.4, 2.1,
    1.7 m, then a goal 0.9 m ahead, turning 0.11 rad at most. The quartic through them said
    1.42 rad, the follower turned round and the column behind it broke (follower 5 6.7 m
    off); the fits through fewer points disagree with it, so the shortest is taken."""
    track = (np.array([3.447, 0.045]), np.array([2.078, -0.039]), np.array([1.718, 0.046]))
    chord = np.array([0.923, 0.13])
    heading = goal_heading(0.0622, chord, track, 0.0, 3.57)
    assert abs(heading - math.atan2(chord[1], chord[0])) < 0.3
    _, rows = run_local(RunConfig(surface="wavy", followers=5, ticks=40, comm_period=2.56,
                                  motion="drive", estimator="persist"))
    assert max(r["formation_error"] for r in rows if r["agent"] > 0) < 1.5  # 6.74 before


def test_chart_turn_inverts_the_metric_angle():
    slope = np.array([1.5, -0.5])
    for start, angle in ((0.3, 0.7), (-2.0, -1.2), (1.0, 0.01)):
        assert metric_angle(slope, start, start + chart_turn(slope, start, angle)) == \
            pytest.approx(angle, abs=1e-9)


def test_the_heading_filter_averages_the_compass():
    """Standing still, a compass read with σ 0.03 twelve times is known to about σ/√12."""
    limits = _limits(noise_bearing=0.03)
    rng = np.random.default_rng(5)
    errors = []
    for _ in range(200):
        f = HeadingFilter(0.5 + rng.normal(0, 0.03), limits)
        for step in range(len(limits.durations)):
            f.step(step, 0.0, 0.0, 0.5 + rng.normal(0, 0.03), np.zeros(2))
        errors.append(f.heading - 0.5)
    assert np.std(errors) < 0.03 / math.sqrt(12) * 1.3


def test_the_heading_filter_reads_the_odometry_on_the_heading_s_axis_either_way():
    """A step commanded backwards but driven forwards (a command slower than the speed's
    actuation noise) moves the robot along its heading: with exact odometry the filter took
    the command's sign and turned the heading by π (on egg_crate with σ_θ 0.06 and speed
    noise, follower 1 spun at tick 0 and follower 2 ended 7 m off); it keeps it now, and a
    step driven backwards as commanded still reads the same axis."""
    limits = _limits(noise_bearing=0.06)
    for commanded, driven in ((-0.002, 0.0001), (-0.5, -0.1), (0.5, 0.1), (0.002, -0.0001)):
        f = HeadingFilter(0.035, limits)
        odometry = driven * np.array([math.cos(0.035), math.sin(0.035)])
        f.step(0, 0.0, commanded, 0.0665, odometry)
        assert abs(f.heading - 0.035) < 0.05, (commanded, driven, f.heading)
        assert abs(f.drift()) < 1.0


def test_a_column_setting_off_under_speed_noise_does_not_turn_round():
    """The run that showed it (egg_crate, σ_r 0.005, σ_θ 0.06, speed noise 0.02, T_c 2.56):
    follower 2 was 3.9-7.2 m off in its first ticks; within half a metre now."""
    summary, rows = run_local(RunConfig(
        surface="world.held_out:egg_crate", followers=2, ticks=10, seed=7, motion="drive",
        noise_range=0.005, noise_bearing=0.06, comm_period=2.56, init_ticks=8,
        noise_speed=0.02))
    assert max(r["formation_error"] for r in rows if r["agent"] > 0) < 0.5


# --- the protocol at the world -----------------------------------------------------------------


def test_control_steps_are_validated():
    sim, config = drive_world()
    with pytest.raises(RequestError, match="goal is given with the first"):
        sim.act(1, Control(tick=0, step=0, speed=0.0, turn=0.0))
    with pytest.raises(RequestError, match="out of order"):
        sim.act(1, Control(tick=0, step=1, speed=0.0, turn=0.0))
    with pytest.raises(RequestError, match="exceeds the limits"):
        sim.act(1, Control(tick=0, step=0, speed=config.max_speed * 1.01, turn=0.0,
                           goal=(0.0, 0.0)))
    with pytest.raises(RequestError, match="exceeds the limits"):
        sim.act(1, Control(tick=0, step=0, speed=0.0, turn=-2.5, goal=(0.0, 0.0)))
    with pytest.raises(RequestError, match="send Control steps"):
        sim.act(1, Move(tick=0, offset=(0.1, 0.0)))
    with pytest.raises(RequestError, match="cannot settle yet"):
        sim.act(1, Snap(tick=0))
    reply = sim.act(1, Control(tick=0, step=0, speed=0.5, turn=0.1, goal=(0.0, 0.0)))
    assert reply.odometry is not None and reply.compass is not None and reply.slope is not None
    with pytest.raises(RequestError, match="goal is given with the first"):
        sim.act(1, Control(tick=0, step=1, speed=0.0, turn=0.0, goal=(0.0, 0.0)))
    for step in range(1, config.control_steps + config.snap_steps):
        sim.act(1, Control(tick=0, step=step, speed=0.0, turn=0.0))
    with pytest.raises(RequestError, match="past the tick"):
        sim.act(1, Control(tick=0, step=config.control_steps + config.snap_steps, speed=0.0,
                           turn=0.0))
    assert sim.act(1, Snap(tick=0)).moved


def test_teleport_refuses_control_steps():
    config, surface = resolve_with_surface(RunConfig())
    sim = WorldSim(config, surface)
    sim.start_tick(0)
    sim.drive(0, 0, 0.0)
    with pytest.raises(RequestError, match="need motion 'drive'"):
        sim.act(1, Control(tick=0, step=0, speed=0.0, turn=0.0, goal=(0.0, 0.0)))


def test_a_lost_tick_still_drives_its_window_to_stop():
    """Beyond the sensing range after the move phase the tick is lost; the robot still has
    the correction window's steps, to come to rest (no rod end to drive onto)."""
    _, rows = run_local(RunConfig(motion="drive", surface="wavy", estimator="stay",
                                  sensing_range=0.05, ticks=8))
    lost = [r for r in rows if r["agent"] == 1 and r["lost"]]
    assert lost and all(r["snap_error"] is None for r in lost)


def test_the_default_top_speed_is_twice_the_leaders():
    config, surface = resolve_with_surface(RunConfig(motion="drive", surface="wavy"))
    start = np.array(config.leader_start)
    speed = math.sqrt(start[2:] @ geometry.metric(surface, start[:2]) @ start[2:])
    assert config.max_speed == pytest.approx(2 * speed)


# --- honest sensing ----------------------------------------------------------------------------


class TruthLink(LocalLink):
    """Notes every reading a driving follower gets beside the exact value."""

    def __init__(self, sim, agent, seen):
        super().__init__(sim, agent)
        self.seen = seen

    def act(self, request):
        state = self.sim.agents[self.agent]
        before = state.pos.copy()
        reply = super().act(request)
        if isinstance(request, Control):
            end = self.sim._leader_rod(self.agent, request.tick)[0]
            leader = self.sim.agents[self.agent - 1].settled[request.tick]
            rel = leader - state.pos
            self.seen.append({
                "odometry": (reply.odometry, state.pos - before),
                "compass": (reply.compass, math.atan2(state.heading[1], state.heading[0])),
                "slope": (reply.slope, self.sim.surface.gradient(state.pos)),
                "r": (reply.r, math.hypot(*rel)),
                "theta": (reply.theta, math.atan2(rel[1], rel[0])),
            })
            # the rod end is looked for after the move phase's last step and in the
            # correction window, never before (design §4)
            looks = request.step >= self.sim.config.control_steps - 1
            assert (reply.rod is not None) == looks, (request.tick, request.step)
            if looks:
                self.seen[-1]["rod"] = (reply.rod, end - state.pos)
        return reply


def test_with_every_sigma_positive_no_drive_reading_is_exact():
    config, surface = resolve_with_surface(RunConfig(motion="drive", surface="wavy", ticks=8,
                                                     followers=2, seed=2, **NOISE))
    sim, settings = WorldSim(config, surface), AgentSettings.from_config(config)
    seen: list = []
    links = [TruthLink(sim, k, seen) for k in (1, 2)]
    policies = [make_policy(settings) for _ in links]
    limits = Limits.from_settings(settings)
    for tick in range(config.ticks):
        sim.start_tick(tick)
        sim.drive(0, tick, sim.time_of(tick))
        for link, policy in zip(links, policies, strict=True):
            follower_tick(link, policy, settings, tick, limits)
        sim.finish_tick(tick)
    assert len(seen) == 8 * 2 * 12
    for readings in seen:
        for name, (got, exact) in readings.items():
            assert got is not None, name
            assert np.all(np.asarray(got, dtype=float) != np.asarray(exact, dtype=float)), name


def test_every_control_step_draws_from_a_noise_block_of_its_own():
    """No value of a control step's block is the tick's (numpy seeds ``[s, a, t, 0]`` exactly
    like ``[s, a, t]``: step 0 must not be keyed by its bare index), nor another step's."""
    for channel, phase in itertools.product(CHANNELS, PHASES):
        blocks = [gaussian(7, 1, 5, channel, phase, 1.0, 3, step=step)
                  for step in (None, 0, 1, 2)]
        for a, b in itertools.combinations(blocks, 2):
            assert np.all(a != b), (channel, phase)


class NotingLink(LocalLink):
    """A follower's in-memory link that notes in ``seen`` what :meth:`note` takes from each
    reply: the pre-move sensing's (``request`` None) and every action's."""

    def __init__(self, sim, agent, seen):
        super().__init__(sim, agent)
        self.seen = seen

    def sense(self, tick, look=False):
        reply = super().sense(tick, look)
        self.note(tick, None, reply)
        return reply

    def act(self, request):
        reply = super().act(request)
        self.note(request.tick, request, reply)
        return reply

    def note(self, tick, request, reply) -> None:
        raise NotImplementedError


class OdometryLink(NotingLink):
    """Notes a driving follower's odometry: its velocity readings (``pre``, ``settled``), its
    step readings, and where it settled."""

    def note(self, tick, request, reply):
        key = (self.agent, tick)
        if request is None:
            self.seen[*key, "pre"] = reply.velocity
        elif isinstance(request, Control):
            self.seen.setdefault((*key, "steps"), []).append(reply.odometry)
        elif isinstance(request, Snap):
            self.seen[*key, "settled"] = reply.velocity
            self.seen[*key, "pos"] = self.sim.agents[self.agent].pos.copy()


def test_a_driving_follower_has_one_odometer():
    """The velocity reading over a comm interval is the sum of the step odometry readings the
    robot got in that tick over ``T_c`` (the same draws, not a second instrument), and it is
    one reading: the same at settling and before the next tick."""
    config = RunConfig(motion="drive", surface="wavy", followers=2, ticks=10, seed=4, **NOISE)
    seen: dict = {}
    run_local(config, link_factory=lambda sim, k: OdometryLink(sim, k, seen))
    for k in (1, 2):
        for j in range(1, config.ticks - 1):
            reading = np.asarray(seen[k, j, "settled"])
            assert seen[k, j, "settled"] == seen[k, j + 1, "pre"]
            summed = np.sum(seen[k, j, "steps"], axis=0) / config.comm_period
            assert np.abs(reading - summed).max() < 1e-12
            exact = (seen[k, j, "pos"] - seen[k, j - 1, "pos"]) / config.comm_period
            assert np.all(reading != exact)


class ToldLink(NotingLink):
    """Notes what a driving follower told of its heading with its :class:`Snap` and what its
    own readings relayed of its leader's."""

    def note(self, tick, request, reply):
        key = (self.agent, tick)
        if request is None:
            self.seen[*key, "pre"] = reply.shared_heading
        elif isinstance(request, Snap):
            self.seen[*key, "told"] = request.heading
            self.seen[*key, "settled"] = reply.shared_heading
            self.seen[*key, "true"] = self.sim.agents[self.agent].heading


def test_a_driving_follower_hears_what_its_leader_told_of_its_heading():
    """Each driving follower tells its heading as it settles (its filter's estimate, with a
    variance: the robot's own belief, never the truth), and the world relays exactly that to
    its successor with the tick's pre-move and settled readings; the column's leader, which
    drives no filter, tells nothing. Without noise nothing is told (the runs stay exact)."""
    config = RunConfig(motion="drive", surface="wavy", followers=3, ticks=8, seed=3, **NOISE)
    seen: dict = {}
    run_local(config, link_factory=lambda sim, k: ToldLink(sim, k, seen))
    for j in range(config.ticks):
        assert seen[1, j, "pre"] is None and seen[1, j, "settled"] is None
        for k in (2, 3):
            told = seen[k - 1, j, "told"]
            assert told is not None and told[1] > 0.0
            assert seen[k, j, "pre"] == told == seen[k, j, "settled"]
            true = seen[k - 1, j, "true"]
            assert told[0] != math.atan2(true[1], true[0])  # an estimate
            assert abs(wrap(told[0] - math.atan2(true[1], true[0]))) < 0.1
    seen.clear()
    run_local(RunConfig(motion="drive", surface="wavy", followers=3, ticks=6),
              link_factory=lambda sim, k: ToldLink(sim, k, seen))
    assert all(v is None for key, v in seen.items() if key[2] != "true")


def test_a_told_heading_is_refused_where_it_has_no_place():
    """A teleporting follower takes its heading from its rod end: a Snap telling one is
    refused, as is a told heading that is no angle or has a negative variance."""
    config, surface = resolve_with_surface(RunConfig(surface="wavy", followers=1, ticks=4))
    sim = WorldSim(config, surface)
    sim.start_tick(0)
    sim.drive(0, 0, 0.0)
    sim.sense(1, 0, look=True)
    with pytest.raises(RequestError, match="teleporting follower"):
        sim.act(1, Snap(tick=0, heading=(0.1, 0.01)))
    sim, _ = drive_world(surface="wavy", followers=1, ticks=4)
    for told in ((4.0, 0.01), (0.1, -1.0)):
        with pytest.raises(RequestError, match="told heading"):
            sim.snap(1, 0, told)


def test_a_told_heading_is_weighed_by_what_it_erred_on_the_followers_own_path():
    """``Track`` judges the heading its leader told at each tick against the lag-free tangent
    through that tick's rod end, as it judges its own tangents, and ``fuse`` weighs the two by
    those mean squared errors — from :data:`agents.drive.JUDGED` judged ticks of its own and
    one of the told headings on; without noise the told heading is left out."""
    track = Track(1.28, 0, 0.02, 0.01, 3.57, chord_variance=4e-4, odometry_variance=1e-4,
                  side=1)
    for tick in range(8):  # straight east at 1 m/s, the leader 3.57 m to the south
        track.record(Sensing(tick=tick, r=3.57, theta=-math.pi / 2, rod=(0.0, 0.0),
                             velocity=(1.0, 0.0), compass=0.0, shared_heading=(0.05, 1e-4)))
    assert track.told_judged >= 1 and track.judged >= 3
    assert track.told_errors / track.told_judged == pytest.approx(0.05**2)
    step, chord = np.array([1.28, 0.0]), np.array([0.0, 3.57])
    own = track.fuse(0.1, 4e-4, step, chord)
    # its own tangents were exact on this path: the told heading, 0.05 off, moves nothing
    assert track.fuse(0.1, 4e-4, step, chord, told=(0.0, 1e-4)) == own
    track.errors = np.array([3e-4, 2e-4]) * track.judged  # had they erred (the filter less)
    gain = 2e-4 / (2e-4 + 0.05**2)
    told = track.fuse(0.1, 4e-4, step, chord, told=(0.0, 1e-4))
    assert told.heading == pytest.approx(own.heading * (1.0 - gain)) and told.heading < 0.095
    assert told.variance == pytest.approx((1.0 - gain) * own.variance)
    fresh = Track(1.28, 0, 0.02, 0.01, 3.57, chord_variance=4e-4, side=1)  # nothing judged
    assert fresh.fuse(0.1, 4e-4, step, chord, told=(0.0, 1e-4)).heading == 0.1
    exact = Track(1.28, 0, side=1)
    assert exact.fuse(0.1, None, step, chord, told=(0.0, 1e-4)).heading == 0.1


def test_without_noise_the_readings_are_exact_and_the_actuation_too():
    """σ = 0: the world drives exactly the commanded (v, ω) (the arc length driven is the
    commanded speeds times the step duration)."""
    config = RunConfig(motion="drive", surface="hyperbolic", ticks=6)
    summary, rows = run_local(config)
    assert summary["followers"]["1"]["path_length"] == pytest.approx(
        sum(r["path_length"] for r in rows if r["agent"] == 1), rel=1e-12)


# --- what is measured --------------------------------------------------------------------------


class CommandLink(LocalLink):
    """Notes every control step a follower sends, as it sends it."""

    def __init__(self, sim, agent, sent):
        super().__init__(sim, agent)
        self.sent = sent

    def act(self, request):
        if isinstance(request, Control):
            self.sent.append((request.tick, self.agent, request.step, request.speed,
                              request.turn))
        return super().act(request)


def test_controls_csv_holds_every_step_the_followers_commanded(tmp_path):
    """``controls.csv``: each step a follower sent, in order (a lost tick's correction window
    included: the robot still comes to rest), its stamp ``t_j`` plus the durations of the
    steps before it (the move phase filling its share of ``T_c``, the window the rest), and
    the achieved speeds, which make up ``ticks.csv``'s path lengths, never beyond a limit
    (a clipped step counts as saturated); a teleport run writes no such file."""
    config = RunConfig(motion="drive", surface="wavy", followers=2, ticks=10, seed=4,
                       sensing_range=0.3, control_steps=5, snap_steps=3, **NOISE)
    sent: list = []
    run_local(config, tmp_path / "drive",
              link_factory=lambda sim, k: CommandLink(sim, k, sent))
    controls = read_controls(tmp_path / "drive" / "controls.csv")
    # in (tick, agent, step) order: pipelined, the followers send them interleaved
    assert [(c["tick"], c["agent"], c["step"], c["speed"], c["turn"])
            for c in controls] == sorted(sent)
    resolved, _ = resolve_with_surface(config)
    ticks = read_ticks(tmp_path / "drive" / "ticks.csv")
    assert any(r["lost"] for r in ticks), "the run should lose a tick (sensing_range)"
    move = 1.0 - CORRECTION_SHARE  # the move phase's share of T_c, then the window's
    starts = [resolved.comm_period * move * k / 5 for k in range(5)] + [
        resolved.comm_period * (move + CORRECTION_SHARE * k / 3) for k in range(3)]
    for row in (r for r in ticks if r["agent"] > 0):
        steps = [c for c in controls if (c["tick"], c["agent"]) == (row["tick"], row["agent"])]
        assert [c["step"] for c in steps] == list(range(8))
        assert [c["t"] for c in steps] == pytest.approx(
            [row["tick"] * config.comm_period + starts[c["step"]] for c in steps], abs=1e-12)
        path = 0.0
        for c in steps:
            path += abs(c["achieved_speed"]) * resolved.step_duration(c["step"])
            assert abs(c["achieved_speed"]) <= resolved.max_speed
            assert abs(c["achieved_turn"]) <= resolved.max_turn
        assert path == pytest.approx(row["path_length"], rel=1e-12)
        assert row["saturated_steps"] >= sum(abs(c["speed"]) >= resolved.max_speed
                                             or abs(c["turn"]) >= resolved.max_turn
                                             for c in steps)
    run_local(RunConfig(surface="wavy", followers=2, ticks=4), tmp_path / "teleport")
    assert not (tmp_path / "teleport" / "controls.csv").exists()



def test_the_driven_paths_are_rebuilt_from_the_record(tmp_path):
    """``swarm plot``'s driven paths come from ``controls.csv`` and ``ticks.csv`` alone: each
    follower starts where the world put it, and every tick's rebuilt path ends exactly where
    ``ticks.csv`` says the follower settled, in a noisy run that loses ticks too."""
    from swarm.plots import driven_paths  # matplotlib: here, not in every pytest worker

    config = RunConfig(motion="drive", surface="wavy", followers=2, ticks=10, seed=4,
                       sensing_range=0.3, control_steps=5, snap_steps=3, **NOISE)
    run_local(config, tmp_path)
    rows, controls = read_ticks(tmp_path / "ticks.csv"), read_controls(tmp_path / "controls.csv")
    assert any(r["lost"] for r in rows), "the run should lose a tick (sensing_range)"
    resolved, surface = resolve_with_surface(config)
    paths = driven_paths(resolved, surface, rows, controls)
    world = WorldSim(resolved, surface)
    settled = _pos(rows)
    for k in (1, 2):
        assert np.array_equal(paths[k][0][0], world.agents[k].pos)
        assert len(paths[k]) == config.ticks
        for j, tick in enumerate(paths[k]):
            assert len(tick) == 1 + 8  # a lost tick drives its window too
            assert np.array_equal(tick[-1], settled[j, k])
            if j:
                assert np.array_equal(tick[0], settled[j - 1, k])


def test_a_slow_robot_falls_short_and_says_so():
    base = dict(motion="drive", surface="wavy", followers=2, estimator="persist", ticks=20)
    fast, _ = run_local(RunConfig(**base))
    config, _ = resolve_with_surface(RunConfig(**base))
    slow, rows = run_local(RunConfig(**base, max_speed=config.max_speed / 2.6))
    for k in ("1", "2"):
        assert slow["followers"][k]["saturated_steps"] > fast["followers"][k]["saturated_steps"]
        assert slow["followers"][k]["mean_snap_error"] > 3 * fast["followers"][k][
            "mean_snap_error"]
        assert set(fast["followers"][k]) >= {"path_length", "mean_reach_error",
                                             "mean_snap_error", "saturated_steps",
                                             "mean_formation_error"}
    estimated = [r for r in rows if r["agent"] == 1 and r["tick"] >= 4]
    assert all(r["reach_error"] is not None for r in estimated)
    assert all(r["reach_error"] is None for r in rows if r["agent"] == 1 and r["tick"] < 4)


def test_the_leader_is_not_bounded():
    base = dict(surface="elliptic", ticks=10, estimator="persist")
    _, teleport = run_local(RunConfig(**base))
    _, drive = run_local(RunConfig(**base, motion="drive", max_speed=0.5, max_turn=0.1))
    leader_teleport, leader_drive = _pos(teleport, 0), _pos(drive, 0)
    assert leader_teleport.keys() == leader_drive.keys()
    assert all(np.array_equal(leader_teleport[key], leader_drive[key]) for key in leader_drive)


@pytest.mark.parametrize("surface", ["elliptic", "hyperbolic", "wavy"])
def test_settled_positions_converge_to_the_teleport_run(surface):
    """No noise, unbounded limits: follower 1's settled positions approach the teleport run's
    (where it stands on its leader's rod end) as the control steps grow (from 4 to 256, each
    correction window of half as many), every step closer."""
    base = dict(surface=surface, ticks=20, estimator="persist")
    _, teleport = run_local(RunConfig(**base))
    reference = _pos(teleport, 1)
    worst = []
    for steps in (4, 16, 64, 256):
        _, rows = run_local(RunConfig(**base, motion="drive", max_speed=math.inf,
                                      max_turn=math.inf, control_steps=steps,
                                      snap_steps=steps // 2))
        got = _pos(rows, 1)
        worst.append(max(float(np.linalg.norm(got[key] - reference[key])) for key in got))
    assert worst == sorted(worst, reverse=True) and len(set(worst)) == len(worst)
    assert worst[-1] < 5e-6


# --- refusals ----------------------------------------------------------------------------------


@pytest.mark.parametrize("flags, message", [
    (["--max-turn", "3"], 'max_turn = 3.0 does nothing with motion = "teleport"'),
    (["--snap-steps", "2"], 'snap_steps = 2 does nothing with motion = "teleport"'),
    (["--motion", "drive", "--noise-move", "0.1"], 'noise_move = 0.1 does nothing with motion'),
    (["--motion", "drive", "--control-steps", "0"], "control_steps must be an integer"),
    (["--motion", "drive", "--max-speed", "-1"], "max_speed must be in"),
    (["--motion", "drive", "--max-turn", "nan"], "max_turn must be in"),
    (["--motion", "walk"], "invalid choice"),
])
def test_bad_drive_options_are_refused_in_one_line(tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        raise SystemExit(swarm_main(["run", *flags, "--out", str(tmp_path / "out")]))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, flags", [("paper", ["--spacing", "5"]),
                                         ("paper", ["--dem", "x.tif"]),
                                         ("drive", ["--ticks", "3"])])
def test_terrain_flags_are_refused_by_the_other_experiments(tmp_path, capsys, name, flags):
    out = tmp_path / "study"
    with pytest.raises(SystemExit) as refused:  # each experiment has its own flags
        swarm_main(["experiment", name, *flags, "--out", str(out)])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip()
    assert f"error: unrecognized arguments: {flags[0]}" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_the_drive_study_refuses_a_missing_dem_in_one_line(tmp_path, capsys):
    missing = tmp_path / "missing.tif"
    assert swarm_main(["experiment", "drive", "--dem", str(missing), "--leader-start", "1,1,1,0",
                       "--out", str(tmp_path / "study")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    assert "no such DEM file" in err


# --- the study ---------------------------------------------------------------------------------


def test_the_drive_study_writes_its_table_figure_and_report(tmp_path, capsys):
    """``experiment drive --quick``: every run of the reduced grid is in the table, with the
    teleport reference; the minimum top speed is one of the speeds tried."""
    from swarm.drive_study import QUICK, study_runs
    from swarm.grid import read_table

    out = tmp_path / "study"
    assert swarm_main(["experiment", "drive", "--quick", "--out", str(out), "--workers",
                       "1"]) == 0
    rows = read_table(out / "tables" / "drive.csv")
    assert len(rows) == len(study_runs(QUICK))
    assert {r["block"] for r in rows} == {"teleport", "steps", "window", "speed", "noise"}
    steps = {(r["block"], r["control_steps"], r["snap_steps"]) for r in rows
             if r["block"] in ("steps", "window") and r["surface"] == "wavy"}
    assert steps == {("steps", 2, 4), ("steps", 8, 4), ("window", 2, 1), ("window", 8, 4)}
    noisy = [r for r in rows if r["block"] == "noise"]
    assert {(r["noise"], r["motion"]) for r in noisy} == {
        (level, motion) for level in QUICK.noise_levels for motion in ("drive", "teleport")}
    assert all(len(str(r["formation_errors"]).split()) == r["followers"] for r in noisy)
    assert all(r["complete"] == 1 for r in rows)
    drive_rows = [r for r in rows if r["motion"] == "drive"]
    assert all(r["mean_formation_error"] > 0 and r["path_length"] > 0 for r in drive_rows)
    minimum = read_table(out / "tables" / "drive_min_speed.csv")
    assert {m["surface"] for m in minimum} == {"wavy", "dem"}
    assert all(m["min_speed_factor"] in QUICK.speed_factors for m in minimum)
    assert (out / "figures" / "drive.png").stat().st_size > 10_000
    report = (out / "report.md").read_text()
    assert "Minimum top speed" in report and "Under sensor noise" in report
    assert "\r" not in capsys.readouterr().err  # a progress bar on a terminal only, not in a log
