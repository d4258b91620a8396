"""A driving follower's controller (design §4 "Motion", ``--motion drive``): pure numpy.

The robot is a unicycle on the surface; it knows only what its sensors read (design §5): its
odometry (the displacement of each control step in its local compass frame), its compass
heading, the slope under it (tilt sensor) and the range/bearing readings of its leader and of
the rod end. It never knows its absolute position: within a tick it dead-reckons in the frame
of where it stood when the tick began, by summing its odometry readings.

A tick has two phases of control steps (each one round trip, :class:`Control`):

1. **move** (``control_steps`` steps): drive to the estimate, an offset from the tick's start;
2. **snap** (``snap_steps`` steps, the correction window): drive onto the rod end, re-read at
   every step (so the landing is as good as the last reading, not the dead reckoning).

Control law: **biarc pursuit**, re-planned at every step (receding horizon) from the dead
reckoning and the latest readings, in the local frame. A biarc — two circular arcs with a
common tangent — is the standard smooth path joining two poses (position and heading), and a
control step of constant speed and turn rate *is* a circular arc, so on flat ground the plan
is executed exactly and nothing needs tuning: the first arc's speed and turn rate are its
length and turn over half the time left (the least constant speed that arrives when the
window closes, so the limits bind as late as they can). Sideways offsets that no S-curve of
the run's turn rate reaches within the time left are driven by point turns when they fit,
else the reachable part is. The last steps turn onto the goal heading first: the heading a
follower settles with sets the rod the follower behind it follows (design §3), and an error of
ε rad there moves that follower's ideal position by about ``d·ε``. Chart speed and turn
become surface commands through the slope reading ``s = ∇F``: along a chart direction ``ĥ``
one metre of chart is ``√(1 + (s·ĥ)²)`` metres of arc, and the turn is the angle between the
two chart directions in the metric ``I + s sᵀ``. Then both are saturated at the run's limits
(a step at a limit is counted by the world).

Why not the usual laws: Corke's pose controller (``move_to_pose``; ρ, α, β in polar
coordinates) is singular at the goal — exactly where the correction window works: with the
goal a tenth of a millimetre away its bearing, and so its turn command, is arbitrary; and
pure pursuit steers onto the goal position only, so a sideways correction swings the heading
by up to π. Both also need gains; the biarc has none.

Goal heading: in ideal formation a follower moves along its heading (its velocity is
g-orthogonal to its rod, as its heading is), so its path is tangent to its heading; the goal
heading is estimated from the chord of this tick and of the last one (:func:`goal_heading`).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agents.policies import move_variance, reading_variance
from protocol.config import AgentSettings
from protocol.messages import ActSensing, Control, Sensing

MAX_S_TURN = math.pi / 2
"""The sharpest turn of a sideways correction (an S-curve's first arc), radians."""
MIN_MANOEUVRE = 1e-6
"""The smallest sideways offset (m) worth a point-turn manoeuvre without sensor noise."""


@dataclass(frozen=True)
class Limits:
    """What bounds a driving follower: its top speed (m of arc per time unit), its top turn
    rate (rad per time unit), the duration of one control step, and the sideways offset
    (m) below which a point-turn manoeuvre is not worth it (the declared spread of a
    range/bearing reading at the rod's length ``d``, both coordinates together: a smaller
    offset may be noise; a rod-end reading, taken closer, spreads less). With them, the
    declared variance of a tick's chord (one range/bearing reading and one move's odometry,
    both coordinates together), below which a chord cannot be told from standing still
    (:func:`goal_heading`)."""

    max_speed: float
    max_turn: float
    step: float
    tolerance: float = 0.0
    chord_variance: float = 0.0

    @classmethod
    def from_settings(cls, settings: AgentSettings) -> Limits:
        """A follower's limits from its settings (built once per follower: they do not change
        within a run)."""
        if settings.max_speed is None:
            raise ValueError("settings.max_speed must be resolved (the world tells it on join)")
        reading = reading_variance(settings)
        return cls(settings.max_speed, settings.max_turn,
                   settings.comm_period / settings.control_steps,
                   max(math.sqrt(2.0 * reading), MIN_MANOEUVRE),
                   2.0 * (reading + move_variance(settings)))


def wrap(angle: float) -> float:
    """``angle`` wrapped to ``(−π, π]``."""
    return math.atan2(math.sin(angle), math.cos(angle))


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def goal_heading(heading: float, chord: np.ndarray, previous: np.ndarray | None,
                 variance: float) -> float:
    """The heading to settle with after moving along ``chord`` (xy, from the tick's start),
    from a start with compass ``heading``; ``previous`` is the last tick's displacement (None
    if unknown).

    In ideal formation a follower moves along its heading, so its path is tangent to its
    heading: the end tangent of a path through chords of constant turn is the chord's
    direction plus half the turn between consecutive chords, ``χ + (χ − χ₋₁)/2``. Without a
    previous chord, the end tangent of the circular arc tangent to ``heading``,
    ``ψ₀ + 2(χ − ψ₀)`` (it passes the start heading's error on, with the opposite sign, so
    it serves only until a previous chord is known). Chords are taken on the heading's side (a
    chord behind is driven in reverse). A chord no longer than three times its declared spread
    (``variance``: both coordinates together) cannot be told from standing still: the heading
    is kept."""
    rho2 = float(chord @ chord)
    if rho2 == 0.0 or rho2 <= 9.0 * variance:
        return heading

    def forward(vector: np.ndarray) -> float:  # its direction, on the heading's side
        return heading + math.asin(max(-1.0, min(1.0, math.sin(
            math.atan2(vector[1], vector[0]) - heading))))

    chi = forward(chord)
    if previous is not None and float(previous @ previous) > 0.0:
        end = chi + 0.5 * wrap(chi - forward(previous))
    else:
        end = chi + wrap(chi - heading)
    return wrap(end)


def _arc_length(chord: float, half_turn: float) -> float:
    """The length of the circular arc of chord ``chord`` that turns by ``2 · half_turn``:
    ``chord · α / sin α`` (the chord itself for a straight line)."""
    return chord if half_turn == 0.0 else chord * half_turn / math.sin(half_turn)


def _arc_to(position: np.ndarray, heading: float, point: np.ndarray) -> tuple[float, float]:
    """Length and turn of the circular arc from ``position`` (tangent ``heading``) through
    ``point`` (ahead of it)."""
    offset = point - position
    chord = math.hypot(offset[0], offset[1])
    if chord == 0.0:
        return 0.0, 0.0
    alpha = wrap(math.atan2(offset[1], offset[0]) - heading)
    return _arc_length(chord, alpha), 2.0 * alpha


def _biarc_junction(position: np.ndarray, heading: float, goal: np.ndarray,
                    goal_heading: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the two arcs of the biarc from ``position`` (tangent ``heading``) to ``goal``
    (tangent ``goal_heading``), the goal ahead, meet, and their common tangent there (a chart
    vector): the biarc whose tangent segments have equal lengths. None if the goal is where
    the robot stands."""
    t0, t1 = _unit(heading), _unit(goal_heading)
    v = goal - position
    vv, vt, c = float(v @ v), float(v @ (t0 + t1)), float(t0 @ t1)
    if vv == 0.0:
        return None
    if 1.0 - c < 1e-12:
        d = vv / (2.0 * vt)
    else:
        d = (-vt + math.sqrt(vt * vt + 2.0 * (1.0 - c) * vv)) / (2.0 * (1.0 - c))
    q0, q1 = position + d * t0, goal - d * t1
    return 0.5 * (q0 + q1), q1 - q0


def biarc_first_arc(position: np.ndarray, heading: float, goal: np.ndarray,
                    goal_heading: float) -> tuple[float, float]:
    """Length and turn of the first arc of the biarc from ``position`` (tangent ``heading``)
    to ``goal`` (tangent ``goal_heading``), the goal ahead: the arc the controller drives
    (:func:`biarc` gives both)."""
    junction = _biarc_junction(position, heading, goal, goal_heading)
    return (0.0, 0.0) if junction is None else _arc_to(position, heading, junction[0])


def biarc(position: np.ndarray, heading: float, goal: np.ndarray,
          goal_heading: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """The two arcs, (length, turn) each, of the biarc from ``position`` (tangent ``heading``)
    to ``goal`` (tangent ``goal_heading``), the goal ahead: two circular arcs with a common
    tangent, whose tangent segments have equal lengths (a goal where the robot stands: a turn
    in place)."""
    junction = _biarc_junction(position, heading, goal, goal_heading)
    if junction is None:
        return (0.0, 0.0), (0.0, wrap(goal_heading - heading))
    point, tangent = junction
    return (_arc_to(position, heading, point),
            _arc_to(point, math.atan2(tangent[1], tangent[0]), goal))


def _turn_steps(angle: float, limits: Limits) -> int:
    """Control steps needed to turn by ``angle`` at the top turn rate."""
    return math.ceil(abs(angle) / (limits.max_turn * limits.step) - 1e-9)


def pose_command(position: np.ndarray, heading: float, slope: np.ndarray, goal: np.ndarray,
                 goal_heading: float, steps_left: int,
                 limits: Limits) -> tuple[float, float]:
    """The speed and turn rate of the next control step, saturated (module docstring).

    In the frame of the goal heading the goal lies ``ahead`` and ``aside`` (a goal behind is
    driven to in reverse). With ``back`` the steps needed to turn onto the goal heading:

    - the last ``back`` steps (at least the last one) turn onto the goal heading and cover
      the distance along it (the heading comes first: it sets the rod of the follower behind);
    - a goal an S-curve can reach (``|aside| <= ahead tan(θ/2)``, ``θ = min(π/2, ω_max τ/2)``,
      ``τ`` the time left) is driven to along a biarc: this step drives its first arc, timed
      to end when half the time left is over;
    - a goal further aside is reached by turning to face it, driving to it and turning back
      (point turns), when the steps left allow the turns at the top turn rate; else the step
      drives the biarc towards the nearest point an S-curve can reach.

    Parameters
    ----------
    position, goal : ndarray, shape (2,)
        Where the robot believes it is and where it is going (local frame, same origin).
    heading, goal_heading : float
        Compass angles (rad) of its heading now and of the heading wanted at the goal.
    slope : ndarray, shape (2,)
        The slope reading ``(∂F/∂x, ∂F/∂y)`` under the robot.
    steps_left : int
        Control steps left in the phase, this one included (``>= 1``).
    limits : Limits

    Returns
    -------
    v, omega : float
        m of arc per time unit, rad per time unit; within the limits.
    """
    if steps_left < 1:
        raise ValueError(f"steps_left must be >= 1, got {steps_left}")
    tau = steps_left * limits.step
    axis = _unit(goal_heading)
    offset = goal - position
    ahead, aside = float(offset @ axis), _cross(axis, offset)
    direction = 1.0
    if ahead < 0.0:  # reverse: plan as the robot facing backwards
        direction, heading, goal_heading = -1.0, heading + math.pi, goal_heading + math.pi
        axis, ahead, aside = -axis, -ahead, -aside
    back = max(1, _turn_steps(wrap(goal_heading - heading), limits))
    if steps_left <= back:  # turn onto the goal heading, covering the distance along it
        turn = wrap(goal_heading - heading)
        along = wrap(heading + turn / 2.0 - goal_heading)
        chord = ahead / math.cos(along) if abs(along) < math.pi / 2 else 0.0
        speed, rate = _arc_length(chord, turn / 2.0) / tau, turn / tau
    else:
        s_turn = min(MAX_S_TURN, limits.max_turn * tau / 2.0)
        speed, rate = _approach(position, heading, goal, goal_heading, ahead, aside, s_turn,
                                steps_left, limits)
    along_slope = slope[0] * math.cos(heading) + slope[1] * math.sin(heading)
    v = direction * speed * math.sqrt(1.0 + along_slope * along_slope)
    omega = metric_angle(slope, heading, heading + rate * limits.step) / limits.step
    return (float(np.clip(v, -limits.max_speed, limits.max_speed)),
            float(np.clip(omega, -limits.max_turn, limits.max_turn)))


def metric_angle(slope: np.ndarray, start: float, end: float) -> float:
    """The signed angle, in the metric ``g = I + s sᵀ`` of the slope ``s``, from the chart
    direction ``start`` to the chart direction ``end`` (rad; the chart turn from one to the
    other, taken in ``(−π, π]``, fixes the way round)."""
    a, b = _unit(start), _unit(end)
    sa, sb = float(slope @ a), float(slope @ b)
    dot = float(a @ b) + sa * sb
    cross = _cross(a, b) * math.sqrt(1.0 + float(slope @ slope))
    angle = math.atan2(cross, dot)
    turn = wrap(end - start)
    if turn * angle < 0.0:  # the chart turn and the metric angle agree in sign
        angle += math.copysign(2.0 * math.pi, turn)
    return angle


def _approach(position: np.ndarray, heading: float, goal: np.ndarray, goal_heading: float,
              ahead: float, aside: float, s_turn: float, steps_left: int,
              limits: Limits) -> tuple[float, float]:
    """Chart speed and turn rate of a step before the final turn (see :func:`pose_command`;
    the robot faces forwards here, the goal is not behind it)."""
    step = limits.step
    reach = ahead * math.tan(s_turn / 2.0)
    if abs(aside) > max(reach, limits.tolerance):  # further aside than an S-curve reaches
        bearing = math.atan2(goal[1] - position[1], goal[0] - position[0])
        face = wrap(bearing - heading)
        back = max(1, _turn_steps(wrap(goal_heading - bearing), limits))
        if _turn_steps(face, limits) + 1 + back <= steps_left:  # the point turns fit
            if abs(face) > s_turn / 2.0:
                return 0.0, face / step  # turn to face the goal
            length, turn = _arc_to(position, heading, goal)
            drive = (steps_left - back) * step
            return length / drive, turn / drive
        aside = math.copysign(reach, aside)  # the part an S-curve reaches
    axis = _unit(goal_heading)
    target = position + ahead * axis + aside * np.array([-axis[1], axis[0]])
    length, turn = biarc_first_arc(position, heading, target, goal_heading)
    first = steps_left / 2 * step  # the biarc's two arcs share the time left
    return length / first, turn / first


@dataclass(frozen=True)
class Driven:
    """How a driving tick went: ``moved`` is the sensing after the move phase, ``travelled``
    the displacement the odometry summed over it (local frame, from the tick's start)."""

    moved: Sensing
    travelled: np.ndarray


@dataclass(frozen=True)
class _Reckoned:
    """What a driving follower knows of its pose within a tick: its dead-reckoned position
    (local frame, from the tick's start), its compass heading and the slope under it."""

    position: np.ndarray
    heading: float
    slope: np.ndarray


def _drive_phase(act: Callable[[Control], ActSensing], tick: int, first: int, steps: int,
                 pose: _Reckoned, target: np.ndarray, target_heading: float, limits: Limits,
                 reread: bool) -> tuple[_Reckoned, ActSensing | None]:
    """Drive ``steps`` control steps (numbered from ``first``) towards ``target`` with
    ``target_heading``, re-aiming at the rod end after every step if ``reread``; return the
    pose after them and the last reply (None if no step)."""
    reply = None
    for left in range(steps, 0, -1):
        step = first + steps - left
        v, omega = pose_command(pose.position, pose.heading, pose.slope, target, target_heading,
                                left, limits)
        given = (float(target[0]), float(target[1])) if step == 0 else None
        reply = act(Control(tick=tick, step=step, speed=v, turn=omega, goal=given))
        pose = _Reckoned(pose.position + np.asarray(reply.odometry), reply.compass,
                         np.asarray(reply.slope))
        if reread and reply.rod is not None:
            target = pose.position + np.asarray(reply.rod)
    return pose, reply


def drive_tick(act: Callable[[Control], ActSensing], pre: Sensing, goal: np.ndarray,
               settings: AgentSettings, limits: Limits) -> Driven:
    """Drive one tick's control steps: to ``goal`` (an offset from where the follower stands
    at ``pre``), then onto the rod end (re-read after every step) if it is in range after the
    move phase. ``act`` sends one :class:`Control` and returns the world's reply; ``limits``
    are the follower's (:meth:`Limits.from_settings`)."""
    if pre.compass is None or pre.slope is None:
        raise ValueError("a driving follower's sensing must carry its compass and slope")
    previous = None if pre.velocity is None else settings.comm_period * np.asarray(pre.velocity)

    def heading_at(target: np.ndarray) -> float:
        return goal_heading(pre.compass, target, previous, limits.chord_variance)

    target = np.asarray(goal, dtype=float)
    pose = _Reckoned(np.zeros(2), pre.compass, np.asarray(pre.slope))
    pose, reply = _drive_phase(act, pre.tick, 0, settings.control_steps, pose, target,
                               heading_at(target), limits, reread=False)
    moved, travelled = reply.sensing, pose.position.copy()
    if moved.rod is not None:  # else out of range: no correction (a lost tick)
        target = pose.position + np.asarray(moved.rod)
        _drive_phase(act, pre.tick, settings.control_steps, settings.snap_steps, pose, target,
                     heading_at(target), limits, reread=True)
    return Driven(moved, travelled)
