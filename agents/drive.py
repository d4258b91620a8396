"""A driving follower's controller (design §4 "Motion", ``--motion drive``): pure numpy.

The robot is a unicycle on the surface; it knows only what its sensors read (design §5): its
odometry (the displacement of each control step in its local compass frame), its compass
heading, the slope under it (tilt sensor) and the range/bearing readings of its leader and of
the rod end. It never knows its absolute position: within a tick it dead-reckons in the frame
of where it stood when the tick began, by summing its odometry readings.

A tick is one manoeuvre from rest to rest that fills the comm interval (the world's clock,
:meth:`protocol.config.RunConfig.step_duration`), in two phases of control steps (each one
round trip, :class:`Control`):

1. **move** (``control_steps`` steps): towards the estimate, an offset from the tick's start;
2. **correction** (``snap_steps`` steps): the rod end read after the move phase replaces the
   estimate as the goal, and every reading after it refines it (:class:`_Goal`).

The goal is reached when the tick ends, not before: the drive is timed (the least cruise speed
that arrives and stops in the time left, within the acceleration limit), so the robot still
has ground to cover when the rod end is read and corrects a sideways offset with a gentle
S-curve instead of a manoeuvre on the spot.

**Control law** (:func:`step_command`), re-planned at every step from the dead reckoning and
the latest estimates, without gains: the robot steers along the *approach line*, the line
through the goal along the goal heading, aiming at the point of the line half-way between its
own projection and the goal (a parabola tangent to the line at the goal, so it arrives on it);
a goal behind is driven to in reverse, keeping the heading. Which way it travels is the
nearer for its heading, unless its heading is turned more than a right angle from the goal
heading (a detour to a wild goal, say): then it is the way that ends on the goal heading, so
the robot turns round first (no speed while facing away, below) rather than settle reversed,
which would point its rod to the wrong side and mirror the column behind it (found on
``world.random_waves:w7302``: followers 3-5 held 2-4 rods' lengths off for 140 ticks; the goal
heading's own side is :func:`on_side`'s). The aim is turned from the line by
at most what the time left can turn back, so the heading the robot settles with — which sets
the rod of the follower behind it (design §3) — is the goal heading whatever the offset; an
offset the time cannot correct is corrected in part. Offsets within the reading's spread are
given a weight that vanishes smoothly with them, and the aim point keeps a distance of at
least a tenth of the rod's length, so no branch is singular: a goal a rounding error away is
held, not turned to. The speed is the timed cruise speed, times the cosine of the heading
error (no speed while facing away), rate-limited by the acceleration limit and the stop the
tick ends with. Chart speed and turn become surface commands through the slope reading.
In the correction window the turns allow for the arcs they drive: a step that turns by ``τ``
drives along its start heading plus ``τ/2``, so a robot that turned onto the line only in its
last step would land ``L τ / 2`` aside of the goal (3.3 mm at a first predicted tick, which
the follower behind read as a jog of its path and turned by); the window's second-to-last
step turns further by what makes the last arc end on the line (:func:`_arc_turn`), kept by
its Wiener weight against the goal's spread, so that under noise, where it is far within
what the readings know, it changes almost nothing. Two things the terrain does within a step
are allowed for too, each learnt from the tick's own steps and kept only beyond three times
its declared noise: the chart turn it adds to the commanded one (the step commands that much
less, :meth:`HeadingFilter.drift`, so it drives along, not only ends on, the turn the law
wants) and the steepening of the slope along the way (the step is planned with the slope
half-way along it, :func:`slope_ahead`, so its chart length is what the law wants): noise-free
on the elliptic bowl the window's landing fell from 1.1 mm to 0.1 mm rms.

Why not the usual laws: Corke's pose controller (``move_to_pose``) and pure pursuit steer on
the goal's bearing, which is arbitrary where the correction works (the goal a tenth of a
millimetre away); both swung headings by radians, which the next follower pays as metres.

**Its own heading** (:class:`HeadingFilter`): a one-state Kalman filter on the compass angle,
predicted by the turns commanded, updated by every compass reading and by every step's
odometry (the chord of a step, plus half its turn, is its end heading), each with its declared
variance; it starts every tick from the ``pre`` compass reading.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agents.policies import move_variance, reading_variance
from agents.policies.base import polar, relative
from agents.policies.tracker import JERK_DT
from protocol.config import AgentSettings
from protocol.messages import ActSensing, Control, Sensing
from protocol.sensing import reading_variance as sensor_variance

MIN_CHORD = 1e-6
"""A chord (m) shorter than this, relative to the rod's length, says nothing of a direction."""
TRACK = 3
"""How many past ticks the goal heading's fit spans at most (:func:`goal_heading`; under noise
:data:`LEPSKI` may shorten it): the fit's noise falls and its lag grows with it; 3 was the best
of 1, 3, 6 and 10 on issue #30's grid."""
LEPSKI = 2.0
"""How far (in its σ) a shorter fit's direction may lie from a longer one's for the goal
heading to keep the longer (:func:`goal_heading`): about the 95 % band of a Gaussian. Beyond
it the longer fit's lag, not the noise, explains the difference (Lepski's rule for choosing
a smoothing window)."""
DEGREE = 2
"""The degree of the goal heading's fit in time, below its top term (:func:`goal_heading`)."""
TURN_SLIP = 0.1
"""The share of a commanded turn the robot may not have turned (its actuation noise is not
declared to it): the heading filter's process noise per radian turned."""
TRANSPORT = 0.1
"""How much a robot's chart heading may change per metre driven without a command (rad/m):
the parallel transport over the terrain, the heading filter's process noise."""
JERKS = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2)
"""The path filter's bank (:class:`PathFilter`): variances of the white jerk of the path's
tangent angle, rad² per tick⁶, a decade apart, from a path that barely bends to one whose
turn per tick changes by a tenth of a radian a tick. How fast a path's bend changes is the
hidden surface's, so it is not fixed: the readings weigh the filters (as ``ekf``'s jerks)."""
SWINGS = (8, 12, 16, 24, 32)
"""The path filter's swinging models (:class:`PathFilter`): periods, in ticks, of a turn that
swings to and fro — the path of a column crossing waves turns left and right and left again
as each wave passes under it (the ideal column's turn per tick swings with a period of about
13.5 ticks on wavy, 7.5 on the held-out egg_crate), which a white jerk takes for a bend that
goes on. From a swing a tick's chord
barely resolves (8 ticks: four chords a half period) to one slow enough that the jerk models
follow it anyway (32); how the ground waves is the hidden surface's, so the readings weigh
them with the jerk models."""
SWING_DECAY = 0.97
"""How much of a swing's amplitude the path filter's swinging models expect to be left after
a tick (its turn is an AR(2) process with poles ``SWING_DECAY · e^{±2πi / period}``): a swing
that halves over about 23 ticks, two to three periods, so one wave train is followed and a
path that stops swinging is not expected to go on. Chosen before any run; stop 47 measured
0.9 and 0.99 besides (docs/drive.md)."""
SWING_NOISES = (1e-5, 1e-4)
"""Variances (rad² per tick²) of the new turn each swinging model expects a tick, two levels
a decade apart (the lower two of :data:`JERKS`' orders of a turn's change): a gentle and a
strong swell."""
PATH_MEMORY = 0.8
"""How fast the path filter's bank forgets a tick's evidence (``ekf``'s memory: about five
ticks), so a path whose bending changes is followed."""
JUDGED = 3
"""How many ticks each path tangent (the fit's, the filter's) must have been judged on
before the track follows the one with the smaller error (:meth:`Track.tangent`)."""


@dataclass(frozen=True)
class Limits:
    """What bounds a driving follower and what it knows of its sensors' noise: top speed (m of
    arc per time unit), top turn rate (rad per time unit), top acceleration, each control
    step's duration and the time it leaves to stop (:class:`protocol.config.RunConfig`), the
    rod's length, the σ of the range and bearing sensor (also the compass's), the variance of
    a step's odometry per coordinate (``noise_velocity² · δ · T_c``) and the declared
    variance of a tick's chord (one range/bearing reading and one move's odometry, both
    coordinates together)."""

    max_speed: float
    max_turn: float
    max_accel: float
    durations: tuple[float, ...]
    stops: tuple[float, ...]
    spacing: float = 1.0
    sigma_range: float = 0.0
    sigma_bearing: float = 0.0
    odometry_variance: tuple[float, ...] = ()
    chord_variance: float = 0.0

    @classmethod
    def from_settings(cls, settings: AgentSettings) -> Limits:
        """A follower's limits from its settings (built once per follower: they do not change
        within a run)."""
        if settings.max_speed is None:
            raise ValueError("settings.max_speed must be resolved (the world tells it on join)")
        steps = range(settings.tick_steps)
        durations = tuple(settings.step_duration(k) for k in steps)
        return cls(settings.max_speed, settings.max_turn, settings.accel_limit, durations,
                   tuple(settings.stop_time(k) for k in steps), settings.spacing,
                   settings.noise_range, settings.noise_bearing,
                   tuple(settings.noise_velocity**2 * d * settings.comm_period
                         for d in durations),
                   chord_variance(settings))

    def reading_variance(self, distance: float) -> float:
        """The declared variance of a range/bearing reading of a point ``distance`` away,
        both coordinates together."""
        return point_variance(self.sigma_range, self.sigma_bearing, distance)


def point_variance(sigma_range: float, sigma_bearing: float, distance: float) -> float:
    """The declared variance of a range/bearing reading of a point ``distance`` away, both
    coordinates together: twice the per-coordinate one of the sensor model (exact: a halving
    and a doubling)."""
    return 2.0 * sensor_variance(distance, sigma_range, sigma_bearing)


def chord_variance(settings: AgentSettings) -> float:
    """The declared variance of a tick's chord, both coordinates together: one range/bearing
    reading at the rod's length and one move's odometry (:class:`Limits`)."""
    return 2.0 * (reading_variance(settings) + move_variance(settings))


def wrap(angle: float) -> float:
    """``angle`` wrapped to ``(−π, π]``."""
    return math.atan2(math.sin(angle), math.cos(angle))


def axial(angle):
    """``angle`` (rad, a float or an array) as a line's: the representative within
    ``(−π/2, π/2)`` of its class modulo π, the direction either way along the line nearest 0.
    A path's tangent is a line: the path filter and :func:`goal_heading` take the way along it
    nearest the heading, and a chord driven backwards is the same line (until stop 47
    ``goal_heading`` took ``asin(sin(·))``, the same within ±π/2 and the line's mirror image
    beyond)."""
    if isinstance(angle, float):
        return math.atan(math.tan(angle))
    return np.arctan(np.tan(angle))


def on_side(heading: float, chord: float, side: int) -> float:
    """``heading`` (rad), or the opposite direction of its line, whichever has the chord from
    the leader to the rod end (angle ``chord``) on the rods' ``side`` (+1 left, -1 right; 0
    leaves it as it is). A follower at its rod end continues its leader's rod, which points to
    that side of its heading (design §3), so a path's tangent — a line, driven either way —
    has one direction the formation allows whatever the robot's own heading is: a follower that
    turned round to reach a wild goal would otherwise settle reversed, its rod pointing the
    other way, and the column behind it would keep a mirrored formation (found on
    ``world.random_waves:w7302``, 5 followers, σ 0.05/0.03, seed 0: followers 3-5 held 2, 2
    and 4 rods' lengths from their places for 140 ticks). The chord is about a right angle
    from the heading in formation (the metric keeps which side is which), so only a heading
    on the wrong side is turned."""
    if side * math.sin(chord - heading) < 0.0:
        return wrap(heading + math.pi)
    return heading


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _weight(square: float, scale: float) -> float:
    """``square / (square + scale)``: 0 for nothing, 1 without noise (no singular branch)."""
    return 0.0 if square == 0.0 else square / (square + scale)


def beyond_noise(vector: np.ndarray, variance: float) -> np.ndarray:
    """``vector`` (shape (2,)) weighted ``|v|² / (|v|² + 9 variance)`` by its declared
    ``variance`` (both coordinates together): kept whole well above its noise, nothing of it
    within the noise (a shift by it would only add that noise); without noise, whole."""
    return _weight(float(vector @ vector), 9.0 * variance) * vector


def _chord_floor(variance: float, spacing: float) -> float:
    """The squared length below which a chord of declared ``variance`` (both coordinates
    together) says nothing of its direction: three times its spread, and at least
    :data:`MIN_CHORD` of the rod's length ``spacing`` (so a rounding error turns nothing)."""
    return 9.0 * variance + (MIN_CHORD * spacing) ** 2


def _trust(square: float, floor: float) -> float:
    """``1 − floor / square`` above ``floor``, 0 below: how much a vector of squared length
    ``square`` says of its direction when its noise has squared spread ``floor`` (continuous,
    so no branch is singular; a vector within its noise turns nothing)."""
    return 0.0 if square <= floor else 1.0 - floor / square


def goal_heading(heading: float, chord: np.ndarray, track: tuple[np.ndarray, ...],
                 variance: float, spacing: float = 1.0) -> float:
    """The heading to settle with after moving along ``chord`` (xy, from the tick's start),
    from a start with heading ``heading``; ``track`` holds the follower's last displacements,
    one per tick, oldest first (:class:`Track`; may be empty).

    In ideal formation a follower moves along its heading (its velocity is g-orthogonal to
    the rod it stands at the end of, by the Gauss lemma), so its path is tangent to its
    heading. The path through the track's positions and the goal (one comm period apart) is
    fitted, least squares, and its tangent at the goal is the heading: the fit averages the
    errors of the ticks it spans instead of passing them on. The points are placed at their
    distance along the path (:func:`arc_times`), not at their ticks: under noise the rod ends
    jitter along the path far more than across it, and that jitter does not turn a path's
    tangent; without noise a column's far end setting off speeds up along a bending path,
    and a polynomial in time reads the speed's change as a turn. It spans the most past
    ticks (up to the track's) whose fit agrees with every fit
    over fewer within :data:`LEPSKI` of their declared σ: over ticks long enough for the path
    to bend within the track, the shorter fit's smaller lag wins. The fit is a cubic whose
    cubic term ``c`` is kept by its Wiener weight ``|c|² / (|c|² + var c)`` against its
    declared variance (the points' spread, ``variance / 2`` per coordinate, through the
    least-squares covariance; the weight that minimises the tangent's mean square error
    where the term's size is estimated by itself): the cubic's lag on a winding path is a
    fourth of the quadratic's (wavy: 0.003 rad rms against 0.014), its end tangent more
    sensitive to the points' noise, and the weight trades the two (a significance test,
    ``9 var c``, kept too little of it: docs/drive.md). Without noise the points are exact
    and the polynomial through all of them is taken instead (a quartic over the full track:
    it halves the cubic's lag again; under noise a quartic term that stands out by chance
    swings the end tangent, so it is not fitted there), unless a shorter one disagrees with
    it by more than the path's turns allow (:func:`_exact_tangent`). With one displacement known it
    is the exact quadratic through three points,
    ``χ + (χ − χ₋₁)/2`` for chords of equal length; with none, the end tangent of the
    circular arc tangent to ``heading``, ``ψ₀ + 2(χ − ψ₀)``, whose bend beyond the chord,
    ``χ − ψ₀``, is kept by its Wiener weight against its declared variance (the chord's
    angle's, ``variance / 2ρ²``, and as much again for the start heading): under noise the
    doubled bend doubles the chord's and the start's errors, and a column setting off from
    rest, whose first steps are mostly noise, passed them down (docs/drive.md, *Setting
    off*). Directions are taken on the
    heading's side (a goal behind is driven to in reverse). The result is trusted by the
    weight ``1 − f / ρ²`` of the chord ``ρ`` above ``f = 9 variance + (MIN_CHORD d)²``
    (``variance``: the chord's declared spread, both coordinates together): the heading turns
    smoothly from ``heading`` (a chord of nothing, or of noise) to the fit (a chord well above
    its spread), so a chord of a rounding error turns nothing."""
    floor = _chord_floor(variance, spacing)

    def forward(vector: np.ndarray) -> float:  # its direction, on the heading's side
        return heading + axial(math.atan2(vector[1], vector[0]) - heading)

    chord = np.asarray(chord, dtype=float)
    square = float(chord @ chord)
    weight = _trust(square, floor)
    if weight == 0.0:
        return heading
    if not track:  # the arc's bend beyond the chord, by its Wiener weight (exact without noise)
        bend = wrap(forward(chord) - heading)
        spread = variance / square  # the bend's: the chord's angle's and the start's
        return wrap(heading + weight * bend * (1.0 + _weight(bend * bend, spread)))
    positions = [np.zeros(2)]
    for step in reversed(track):
        positions.insert(0, positions[0] - step)
    points = np.array(positions + [chord])  # at t = -len(track) ... 0, 1

    def fitted(ticks: int) -> tuple[np.ndarray, float]:
        """The tangent of the fit over the last ``ticks`` displacements, and the σ (rad) of
        its direction from the points' declared variance (its lower-degree map's)."""
        span = points[len(points) - ticks - 2:]
        fit = _Fit(arc_times(span))
        tangent = fit.tangent @ span
        if fit.top is not None:  # the top term, by its Wiener weight against the points' noise
            top = fit.top @ span
            tangent = tangent + fit.kept * _weight(
                float(top @ top), variance * fit.top_variance) * top
        length = math.hypot(tangent[0], tangent[1])
        spread = math.sqrt(0.5 * variance * float(fit.tangent @ fit.tangent))
        return tangent, (spread / length if length > 0.0 else math.inf)

    if variance == 0.0:  # exact points: the polynomial through them all has the least lag
        tangent = _exact_tangent(points)
    else:  # the longest fit that agrees with every shorter one within their noise (Lepski)
        tangent = _longest_agreeing(
            (candidate, forward(candidate), LEPSKI * spread)
            for candidate, spread in map(fitted, range(1, len(track) + 1)))
    return wrap(heading + weight * wrap(forward(tangent) - heading))


def _longest_agreeing(fits) -> np.ndarray:
    """Lepski's rule over ``fits``, shortest first, each ``(tangent, angle, band)``: the
    tangent of the longest fit whose angle lies within the band of every shorter one (its
    noise, or its model error), computed no further than the first that does not."""
    seen: list[tuple[float, float]] = []
    for candidate, angle, band in fits:
        if any(abs(wrap(angle - a)) > b for a, b in seen):
            break
        tangent = candidate
        seen.append((angle, band))
    return tangent


def _exact_tangent(points: np.ndarray) -> np.ndarray:
    """:func:`goal_heading`'s tangent at the goal through exact ``points`` (the track's, then
    the goal; placed by :func:`arc_times`, :func:`_through`): the polynomial through the most
    past ticks whose end tangent agrees with those through fewer within twice the path's
    largest turn between two successive steps — the rule the noisy fit follows (Lepski's),
    with the fits' model error in place of the points' σ.

    Exact points leave a fit no noise, but a model error: a polynomial in time through a path
    whose rod ends slow down and speed up (a column swinging at a long comm period, its steps
    3.4, 2.1, 1.7 then 0.9 m; before stop 44 placed the points along the path) extrapolated far
    off it (a tangent 1.28 rad from the last step's
    direction, where the steps turn by 0.11 rad at most), the follower turns round, and the
    column behind it breaks. What a fit leaves out is of the order of the path's turn per tick,
    so fits that differ by more than twice it (each one's) are not both right, and the longer
    one is dropped. Where the path is smooth every fit agrees and the one through all the
    points is taken: its lag is least (docs/drive.md)."""
    steps = np.diff(points, axis=0)
    angles = np.arctan2(steps[:, 1], steps[:, 0])
    band = 2.0 * max(abs(wrap(float(b - a))) for a, b in zip(angles[:-1], angles[1:]))
    fits = (_through(points[len(points) - ticks - 2:]) for ticks in range(1, len(points) - 1))
    return _longest_agreeing((fit, math.atan2(fit[1], fit[0]), band) for fit in fits)


def arc_times(points: np.ndarray) -> np.ndarray:
    """Where :func:`goal_heading`'s fit places its points: at their distance along
    the polyline through them (the goal, the last, at 1; one unit the mean step). A path's
    tangent does not depend on how fast it is travelled, and the rod ends a follower drives
    onto jitter mostly *along* its path (the leader's heading error swings its rod end by
    ``d`` times it, along the column's motion), which moves a point in time but hardly in
    arc length. Coincident points (a follower at rest) keep their place in time."""
    lengths = np.hypot(*np.diff(points, axis=0).T)
    total = float(lengths.sum())
    if not total > 0.0:
        return np.arange(2 - len(points), 2, dtype=float)
    along = np.concatenate(([0.0], np.cumsum(lengths))) * ((len(points) - 1) / total)
    return along - along[-1] + 1.0


class _Fit:
    """The linear maps of :func:`goal_heading`'s fit through points at ``times`` (one a row,
    the goal last, at ``t = 1``) to the tangent at ``t = 1``: with a top term (a fit of degree
    ``DEGREE + 1``), ``tangent`` is the lower-degree refit's after the kept top term is
    taken out, ``kept`` what the kept term adds, ``top`` the map to the top coefficient and
    ``top_variance`` its variance per unit of the points' (both coordinates together)."""

    def __init__(self, times: np.ndarray) -> None:
        degree = min(DEGREE + 1, len(times) - 1)
        basis, derivative = _basis(times, degree)
        if degree <= DEGREE:
            self.tangent, self.top = derivative @ np.linalg.pinv(basis), None
            self.kept = self.top_variance = 0.0
            return
        lower = derivative[:degree] @ np.linalg.pinv(basis[:, :degree])
        self.tangent = lower
        self.kept = degree - float(lower @ times**degree)
        self.top = np.linalg.pinv(basis)[degree]
        self.top_variance = float(self.top @ self.top)  # (BᵀB)⁻¹ at it, B of any rank


def _basis(times: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """The powers of :func:`goal_heading`'s points' times up to ``degree`` (one row a point)
    and each power's derivative at the goal, ``t = 1``."""
    powers = np.stack([times**n for n in range(degree + 1)], axis=1)
    return powers, np.arange(degree + 1, dtype=float)


def _through(points: np.ndarray) -> np.ndarray:
    """The tangent at the goal (the last point) of the polynomial through every one of
    ``points``, placed at their distance along the path (:func:`arc_times`):
    :func:`goal_heading`'s fit without noise. Two points in one place (a step of no length)
    have no distance between them to tell them apart, so then every point keeps its tick."""
    times = arc_times(points)
    if not np.all(np.diff(times) > 0.0):
        times = np.arange(2 - len(points), 2, dtype=float)
    basis, derivative = _basis(times, len(points) - 1)
    return derivative @ np.linalg.solve(basis, points)


def middle_tangent(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """The tangent (unnormalised) at the middle of three points of a path, ``before`` and
    ``after`` the steps into and out of it: the quadratic through them placed at their
    distance along the path (:func:`arc_times`), ``b² · before + a² · after`` for steps of
    lengths ``a`` and ``b`` (the mean of the two for equal steps). It has no lag, so it is
    what the track judges its goal tangents against, one tick late (:meth:`Track.record`)."""
    a, b = float(before @ before), float(after @ after)
    return b * before + a * after


@functools.lru_cache(maxsize=8)
def _path_models(jerks: tuple[float, ...], swings: tuple[float, ...]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The path filter's transitions, process noises and chord readings, one per filter
    (:class:`PathFilter`): the white jerks first, then each swing period at each noise."""
    transitions, noises, readings = [], [], []
    for jerk in jerks:
        transitions.append([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
        noises.append(jerk * JERK_DT)  # a white jerk over one tick, as ekf's leader
        readings.append([1.0, -0.5, 0.125])
    for period in swings:
        keep = 2.0 * SWING_DECAY * math.cos(2.0 * math.pi / period)
        back = -SWING_DECAY**2
        for level in SWING_NOISES:  # (θ, r_j, r_{j-1}) -> (θ + r_{j+1}, r_{j+1}, r_j)
            transitions.append([[1.0, keep, back], [0.0, keep, back], [0.0, 1.0, 0.0]])
            noises.append(level * np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0],
                                            [0.0, 0.0, 0.0]]))
            readings.append([1.0, -0.5, 0.0])
    arrays = tuple(np.array(x, dtype=float) for x in (transitions, noises, readings))
    for array in arrays:
        array.flags.writeable = False
    return arrays


class PathFilter:
    """The tangent of the path of rod ends a follower drove onto, filtered over its whole
    track: a bank of Kalman filters on the tangent's angle ``θ`` and how it turns, whose
    reading is each tick's step direction (the chord's) with the variance of the step across
    it over its squared length: ``point_variance``, the step's two rod ends each read from
    nearby (``σ_r²/2`` across) and the tick's odometry (its declared variance per coordinate).
    Two kinds of model, each filter one level:

    - **a white jerk** (one filter per :data:`JERKS`): the state is ``θ``, its change per tick
      ``θ'`` and that change's change ``θ''``; a chord is the tangent half a tick back,
      ``θ − θ'/2 + θ''/8``;
    - **a swinging turn** (one filter per period of :data:`SWINGS` and noise of
      :data:`SWING_NOISES`, stop 47): the turn per tick ``r`` is an AR(2) process,
      ``r_{j+1} = 2 ρ cos(2π/P) r_j − ρ² r_{j−1}`` plus a new turn, ``ρ`` =
      :data:`SWING_DECAY`: a path that turns left and right and left again as the waves under
      the column pass, with its course free to drift. The state is ``θ`` and the last two
      ticks' turns; a chord is ``θ − r/2``, ``r`` the turn of the tick it spans.

    The filters are weighted by the likelihood of every chord each predicted, old ticks
    discounted by :data:`PATH_MEMORY` (multiple-model adaptive estimation, as ``ekf``, whose
    rods swing too). Angles are axial: a chord is a line, whichever way along it a step went.
    With the jerk models alone (stop 46) a winding path's tangent lagged the more the faster
    its turn swung; on a path turning ``0.25 sin(2πj/16)`` rad, rod ends read with σ 0.01,
    the bank erred 16 mrad rms, with the swings 10 (``tests/test_drive_health.py``).

    Where :func:`goal_heading`'s fit spans the last :data:`TRACK` ticks, this follows the path
    from its start, so on a path that winds smoothly its tangent lags less at the same noise;
    where the path turns abruptly the fit's short span follows better. Which of the two the
    track follows is judged on the path itself (:meth:`Track.tangent`). State as data: the
    arrays below, a function of the steps recorded (:meth:`advanced`)."""

    def __init__(self, point_variance: float, jerks: tuple[float, ...] = JERKS,
                 swings: tuple[float, ...] = SWINGS) -> None:
        self.point_variance = point_variance
        self._F, self._Q, self._H = _path_models(tuple(jerks), tuple(swings))
        self.state: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def advanced(self, step: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bank's state (means, covariances, log-likelihood scores) after ``step`` (xy,
        shape (2,)); the filter itself is left as it is."""
        angle = math.atan2(step[1], step[0])
        noise = self.point_variance / max(float(step @ step), MIN_CHORD**2)
        if self.state is None:  # the first chord: the tangent's angle within it, no bend yet
            count = len(self._F)
            return (np.tile([angle, 0.0, 0.0], (count, 1)),
                    np.tile(np.diag([noise + 1e-2, 1e-2, 1e-3]), (count, 1, 1)),
                    np.zeros(count))
        mean, covariance, score = self.state
        mean = np.einsum("bij,bj->bi", self._F, mean)
        covariance = self._F @ covariance @ self._F.transpose(0, 2, 1) + self._Q
        seen = np.einsum("bi,bi->b", self._H, mean)
        innovation = axial(angle - seen)  # the chord's line
        across = np.einsum("bij,bj->bi", covariance, self._H)
        spread = np.einsum("bi,bi->b", self._H, across) + noise
        gain = across / spread[:, None]
        mean = mean + gain * innovation[:, None]
        covariance = covariance - gain[:, :, None] * across[:, None, :]
        score = PATH_MEMORY * score - 0.5 * (innovation**2 / spread + np.log(spread))
        return mean, covariance, score

    @staticmethod
    def estimate(state: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[float, float]:
        """The bank's tangent angle in ``state`` and its variance: its filters' angles
        weighted by their likelihoods (axially, about the first's), and their variances plus
        their spread about that mean, so weighted."""
        mean, covariance, score = state
        weights = np.exp(score - score.max())
        weights /= weights.sum()
        first = float(mean[0, 0])
        offsets = axial(mean[:, 0] - first)
        middle = float(weights @ offsets)
        return first + middle, float(weights @ (covariance[:, 0, 0] + (offsets - middle) ** 2))

    def record(self, step: np.ndarray) -> None:
        self.state = self.advanced(step)

    def reset(self) -> None:
        self.state = None


@dataclass(frozen=True)
class Settled:
    """The heading a follower settled with (rad, chart), its variance, and the angle of the
    chord from its leader to its rod end then: a one-state filter over ticks whose prediction
    turns the heading as the chord turned (the rod turns with the column, and the chord is
    read to the rod end, not to where the follower landed) and whose update is the path's
    tangent (:meth:`Track.tangent`; variance: the fit's, the chord's declared variance over
    the step's squared length; the path filter's, its own); its process noise is
    :data:`TRANSPORT` per metre driven. The chord turns with the leader's own heading error
    (its rod continues that heading), so where the prior weighs much a follower copies its
    predecessor's swing: the path filter's variance, smaller than one chord's where it has
    averaged a long track, keeps that weight down on short steps (docs/drive.md, *Stop 46*)."""

    heading: float
    variance: float
    chord: float


class Track:
    """A follower's last :data:`TRACK` steps, one per tick, oldest first: the path of the rod
    ends it drove onto, in the local compass frame (axes parallel to the world's, so they add
    up across ticks). A tick's step is its odometry's per-tick reading (design §5) times
    ``T_c``, from where it settled to where it settled, plus the change in where it read its
    rod end from there (the settled sensing's rod reading, weighted by its declared variance
    as :func:`agents.follower.at_rod_end` weighs its shift, :func:`beyond_noise`): where it
    landed off its rod end is its own error, which the path of its rod ends does not carry, so
    the goal heading fitted to it (:func:`goal_heading`) does not pass it down the column. A
    tick it missed breaks the track. It learns from the settled sensing as a policy does
    (``record``, ``skip``), so a restarted follower rebuilds it from its replay log."""

    def __init__(self, comm_period: float, length: int = 0, sigma_range: float = 0.0,
                 sigma_bearing: float = 0.0, spacing: float = 1.0,
                 chord_variance: float = 0.0, odometry_variance: float = 0.0,
                 side: int = 0) -> None:
        self.comm_period = comm_period
        self.side = side  # which hand the rods point to (+1 left, -1 right; 0 not said)
        self.length = length or TRACK
        self.sigma_range, self.sigma_bearing = sigma_range, sigma_bearing
        self.spacing, self.chord_variance = spacing, chord_variance
        self.steps: list[np.ndarray] = []
        self.landed = np.zeros(2)  # where the last rod end was from where it settled
        self.settled: Settled | None = None
        # under noise, the path filter and how the fit's and its tangents fared (Track.tangent)
        self.path = (PathFilter(sigma_range**2 + odometry_variance)
                     if chord_variance > 0.0 else None)
        self.proposed: tuple[float, float] | None = None
        self.reset()

    @classmethod
    def from_settings(cls, settings: AgentSettings) -> Track:
        return cls(settings.comm_period, 0, settings.noise_range, settings.noise_bearing,
                   settings.spacing, chord_variance(settings), move_variance(settings),
                   settings.side_sign)

    @classmethod
    def for_follower(cls, settings: AgentSettings) -> Track | None:
        """A follower's track if it drives; None for a teleporting one, which never uses it."""
        return cls.from_settings(settings) if settings.drives else None

    def chord_variance_angle(self) -> float:
        """The declared variance (rad²) of the chord's angle: the leader read at the rod's
        length across its line of sight, and the rod end from nearby."""
        d = self.spacing
        return self.sigma_bearing**2 + 2.0 * self.sigma_range**2 / (d * d)

    def skip(self) -> None:
        self.steps.clear()
        self.landed = np.zeros(2)
        self.settled = None
        self.proposed = None
        self.told = None  # the heading its leader told at the last tick recorded
        if self.path is not None:
            self.path.reset()

    def reset(self) -> None:
        """Forget everything learnt, the judged errors of the path's tangents and of the
        leader's told headings too (which a missed tick, :meth:`skip`, keeps: they describe the
        path's kind, not its last ticks): a rejoining follower rebuilds it all from its replay
        log."""
        self.skip()
        self.judged, self.errors = 0, np.zeros(2)
        self.told_judged, self.told_errors = 0, 0.0

    def record(self, settled: Sensing) -> None:
        if settled.velocity is None:
            self.skip()
            return
        landed = np.zeros(2)
        if settled.rod is not None:
            landed = np.asarray(settled.rod, dtype=float)
            landed = beyond_noise(landed, point_variance(
                self.sigma_range, self.sigma_bearing, math.sqrt(float(landed @ landed))))
        step = (self.comm_period * np.asarray(settled.velocity, dtype=float)
                + landed - self.landed)
        previous, compass = tuple(self.steps), settled.compass
        advanced = both = None
        if self.path is not None:  # the filter's state after this step, and both tangents
            advanced = self.path.advanced(step)
            if compass is not None and previous and self.path.state is not None:
                both = (goal_heading(compass, step, previous, self.chord_variance,
                                     self.spacing), self._filtered(compass, step, advanced))
        if compass is not None and settled.rod is not None:
            chord = -relative(settled)  # from the leader to the rod end
            self.settled = self.heading(compass, step, chord, previous, both,
                                        settled.shared_heading)
        if self.path is not None:
            self._judge(step, previous, both)
            self.path.state = advanced
        self.told = settled.shared_heading
        self.steps.append(step)
        self.landed = landed
        del self.steps[:-self.length]

    def _judge(self, step: np.ndarray, previous: tuple[np.ndarray, ...],
               both: tuple[float, tuple[float, float]] | None) -> None:
        """Judge the tangents the fit and the filter gave for the last tick's rod end against
        the lag-free one through it (:func:`middle_tangent`, now that the step beyond it is
        known), and remember this tick's, ``both`` (the fit's; the filter's with its
        variance), for the next; and the heading the leader told at that tick against the same
        tangent (:meth:`fuse` weighs it by what it erred so)."""
        if previous and (self.proposed is not None or self.told is not None):
            middle = middle_tangent(previous[-1], step)
            truth = math.atan2(middle[1], middle[0])
            if self.told is not None:
                off = float(axial(self.told[0] - truth))
                self.told_errors += off * off
                self.told_judged += 1
            if self.proposed is not None:
                off = axial(np.array(self.proposed) - truth)
                self.errors += off * off
                self.judged += 1
        self.proposed = None if both is None else (both[0], both[1][0])

    def _filtered(self, compass: float, step: np.ndarray,
                  state: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                  ) -> tuple[float, float]:
        """The path filter's tangent at the end of ``step``, on the heading's side and
        trusted as :func:`goal_heading` trusts its fit (a step within its noise turns
        nothing), and the filter's variance of it (rad²); ``state``: the filter's after
        ``step`` if already worked out (:meth:`PathFilter.advanced`)."""
        angle, variance = PathFilter.estimate(self.path.advanced(step) if state is None
                                              else state)
        weight = _trust(float(step @ step), _chord_floor(self.chord_variance, self.spacing))
        return wrap(compass + weight * axial(angle - compass)), variance

    def tangent(self, compass: float, step: np.ndarray, previous: tuple[np.ndarray, ...],
                both: tuple[float, tuple[float, float]] | None = None
                ) -> tuple[float, float | None]:
        """The path's tangent at the end of ``step`` and its variance (rad²; None for the
        fit's, which :meth:`fuse` declares): :func:`goal_heading`'s fit over the last ticks
        or, under noise, once both have been judged on :data:`JUDGED` ticks and the path
        filter's tangents erred less on average (against the lag-free tangent through each
        past rod end, :meth:`_judge`: the same noisy reference for both, so their difference
        is the lag and noise each adds), the filter's over the whole track
        (:class:`PathFilter`) with the filter's own variance: it has averaged the whole
        track, where the fit's declared variance is one chord's. ``both``: the two, if
        already worked out for this step (:meth:`record`)."""
        if (self.path is not None and self.path.state is not None and previous
                and self.judged >= JUDGED and self.errors[1] < self.errors[0]):
            return both[1] if both is not None else self._filtered(compass, step)
        if both is not None:
            return both[0], None
        return goal_heading(compass, step, previous, self.chord_variance, self.spacing), None

    def heading(self, compass: float, step: np.ndarray, chord: np.ndarray,
                previous: tuple[np.ndarray, ...],
                both: tuple[float, tuple[float, float]] | None = None,
                told: tuple[float, float] | None = None) -> Settled:
        """The heading to settle with at the end of ``step`` (from the last rod end), with
        ``chord`` the direction from the leader to it: the path's tangent (:meth:`tangent`;
        ``both`` as there) fused with the heading it settled with last time turned as the
        chord turned since (:class:`Settled`), and with what its leader ``told`` of its own
        (:meth:`fuse`)."""
        return self.fuse(*self.tangent(compass, step, previous, both), step, chord, told)

    def fuse(self, path: float, variance: float | None, step: np.ndarray,
             chord: np.ndarray, told: tuple[float, float] | None = None) -> Settled:
        """:meth:`heading` from the path's tangent ``path`` at the end of ``step`` and its
        ``variance`` (:meth:`tangent`, which a caller asking for one goal many times works out
        once; None: the fit's, the chord's declared variance over the step's squared length),
        then, under noise, with the heading its leader ``told`` it settled with (its heading
        filter's estimate, relayed by the world: :func:`told_heading`), one more reading of the
        same heading. Both are weighed by what they erred on this follower's own path: the
        mean squared error of its tangents and of the told headings against the lag-free
        tangent through each past rod end (:meth:`_judge`), so the told reading's variance
        holds the rod's transport in the chart, the leader's own error and the lag both share,
        none of which a declared variance says; it is used once the track has judged
        :data:`JUDGED` ticks and the told headings one. In formation a follower's heading is
        its leader's carried along the rod (design §3), which the leader knows far better
        than the follower can infer it from its path (docs/drive.md, *Stop 51*)."""
        own = self._fused(path, variance, step, chord)
        if told is None or self.judged < JUDGED or self.told_judged == 0:  # none without noise
            return own
        mine = float(np.min(self.errors)) / self.judged
        theirs = self.told_errors / self.told_judged
        total = mine + theirs
        gain = 0.0 if total == 0.0 else mine / total
        heading = wrap(own.heading + gain * wrap(told[0] - own.heading))
        return Settled(on_side(heading, own.chord, self.side), (1.0 - gain) * own.variance,
                       own.chord)

    def _fused(self, path: float, variance: float | None, step: np.ndarray,
               chord: np.ndarray) -> Settled:
        """:meth:`fuse` before the leader's told heading: the path with the prior."""
        angle = math.atan2(chord[1], chord[0])
        path = on_side(path, angle, self.side)
        length = float(step @ step)
        noise = 0.0 if self.chord_variance == 0.0 else (
            math.inf if length == 0.0 else self.chord_variance / length)
        if variance is not None and length > 0.0:
            noise = variance
        last = self.settled
        if last is None:
            return Settled(path, noise, angle)
        prior = on_side(wrap(last.heading + wrap(angle - last.chord)), angle, self.side)
        spread = last.variance + 2.0 * self.chord_variance_angle() + TRANSPORT**2 * length
        gain = 1.0 if noise == 0.0 else spread / (spread + noise)  # 0 for an infinite noise
        heading = path if gain == 1.0 else wrap(prior + gain * wrap(path - prior))
        return Settled(heading, (1.0 - gain) * spread, angle)

    def displacements(self) -> tuple[np.ndarray, ...]:
        return tuple(self.steps)


class HeadingFilter:
    """The robot's own heading (chart angle, rad) from its compass and odometry: a one-state
    Kalman filter, predicted by the chart turn each step commanded (variance:
    :data:`TURN_SLIP` of the turn and :data:`TRANSPORT` per metre driven), updated by the
    step's compass reading (variance ``σ_θ²``) and by the direction of the step's odometry plus half
    its turn (variance ``σ_odometry² / |step|²`` plus a quarter of the turn's, squared: the chord's
    direction is the mid-step heading only on a circular arc). Without noise the compass is
    exact and is taken as is.

    It also keeps how far the heading turned in the tick beyond the turns commanded, and the
    arc driven, for :meth:`drift`."""

    def __init__(self, compass: float, limits: Limits) -> None:
        self.limits = limits
        self.heading = compass
        self.variance = limits.sigma_bearing**2
        self.unexplained = 0.0  # rad: the heading's change beyond the commanded turns
        self.driven = 0.0  # m of arc, as commanded

    def drift(self) -> float:
        """How much the chart heading turns per metre of arc driven without a command
        (rad/m), as this tick's steps so far showed it: the terrain's parallel transport (on
        a slope a straight drive curves in the chart), which varies slowly along the way. The
        heading's unexplained change per metre of the arc driven, ``r``, kept by the weight
        ``1 − 9v / r²`` above three times its declared σ (``v``: the start's and the
        estimate's compass variance over the arc squared), 0 below (:func:`_trust`, as
        :func:`beyond_noise` keeps a shift): without noise it is exact; a rate within the
        compass noise is left out, since feeding forward noise put noisy columns further off
        (docs/drive.md)."""
        if self.driven <= 0.0:
            return 0.0
        rate = self.unexplained / self.driven
        spread = (self.limits.sigma_bearing**2 + self.variance) / self.driven**2
        return rate * _trust(rate * rate, 9.0 * spread)

    def _update(self, reading: float, variance: float) -> None:
        total = self.variance + variance
        gain = 1.0 if total == 0.0 else self.variance / total
        self.heading = wrap(self.heading + gain * wrap(reading - self.heading))
        self.variance *= 1.0 - gain

    def step(self, step: int, turn: float, speed: float, compass: float,
             odometry: np.ndarray) -> float:
        """Fold in control step ``step``: the chart ``turn`` it commanded (rad), the speed it
        commanded, and the compass and odometry read after it; return the new estimate."""
        limits = self.limits
        moved = math.hypot(odometry[0], odometry[1])
        before = self.heading
        self.heading = wrap(self.heading + turn)
        self.variance += (TURN_SLIP * turn) ** 2 + (TRANSPORT * moved) ** 2
        self._update(compass, limits.sigma_bearing**2)
        odometry_variance = limits.odometry_variance[step] if limits.odometry_variance else 0.0
        if speed != 0.0 and moved * moved > 9.0 * odometry_variance:  # so moved > 0
            # the robot moves along its heading's axis, forwards or backwards: which way is
            # the one nearer the heading, not the command's sign (a command slower than the
            # speed's actuation noise can be driven the other way, and an exact odometry
            # then flipped the heading by π: docs/drive.md, *Setting off*)
            direction = math.atan2(odometry[1], odometry[0])
            if math.cos(direction - self.heading) < 0.0:
                direction += math.pi
            self._update(wrap(direction + 0.5 * turn),
                         odometry_variance / (moved * moved) + (0.25 * turn) ** 2
                         + (TRANSPORT * moved) ** 2)
        self.unexplained += wrap(self.heading - before - turn)
        self.driven += abs(speed) * limits.durations[step]
        return self.heading


def _timed_speeds(distance: float, speed: float, step: int, end: int, limits: Limits,
                  stretch: float) -> np.ndarray:
    """The speeds (m of arc per time unit, along the way to the goal) of steps ``step`` to
    ``end - 1`` in the least-peak speed profile of the tick's steps left that covers
    ``distance`` (m of chart) and stops by the end of step ``end - 1``: each step's speed is
    the cruise speed ``V`` clipped to what the acceleration limit allows from ``speed`` (the
    last step's) and to what still stops in time (``accel_limit ×`` the time left, plus one
    step's). The covered distance is piecewise linear in ``V``: ``V`` is solved exactly. A
    distance the profile cannot cover gives the fastest steps; one it must overshoot, the
    slowest. ``stretch``: m of arc per m of chart."""
    dt = np.asarray(limits.durations[step:max(end, step + 1)])
    change = np.cumsum(limits.max_accel * dt) if math.isfinite(limits.max_accel) \
        else np.full(dt.shape, math.inf)
    left = np.cumsum(dt[::-1])[::-1] - dt + dt[-1]  # the time to stop after each step
    stop = limits.max_accel * np.minimum(left, limits.stops[step:step + dt.size])
    hi = np.minimum(np.minimum(limits.max_speed, speed + change), stop) / stretch
    lo = np.maximum(np.maximum(-limits.max_speed, speed - change), -stop) / stretch
    points = np.unique(np.concatenate([lo, hi]))
    points = points[np.isfinite(points)]
    if points.size == 0:
        cruise = distance / float(dt.sum())
    else:
        covered = np.clip(points[:, None], lo, hi) @ dt
        if distance <= covered[0]:
            slope = float(dt[np.isneginf(lo)].sum())
            cruise = points[0] - (covered[0] - distance) / slope if slope else points[0]
        elif distance >= covered[-1]:
            slope = float(dt[np.isposinf(hi)].sum())
            cruise = points[-1] + (distance - covered[-1]) / slope if slope else points[-1]
        else:
            j = int(np.searchsorted(covered, distance))
            share = (distance - covered[j - 1]) / (covered[j] - covered[j - 1])
            cruise = points[j - 1] + share * (points[j] - points[j - 1])
    return stretch * np.clip(cruise, lo, hi)


def step_command(position: np.ndarray, heading: float, slope: np.ndarray, goal: np.ndarray,
                 goal_heading: float, spread: float, speed: float, step: int,
                 limits: Limits, end: int | None = None,
                 drift: float = 0.0) -> tuple[float, float, float]:
    """The speed and turn rate of control step ``step`` (module docstring), within the limits,
    and the chart turn it means (for the heading filter).

    Parameters
    ----------
    position, goal : ndarray, shape (2,)
        Where the robot believes it is and where it is going (local frame, same origin).
    heading, goal_heading : float
        Compass angles (rad) of its heading now (filtered) and of the heading wanted at the
        goal.
    slope : ndarray, shape (2,)
        The slope reading ``(∂F/∂x, ∂F/∂y)`` under the robot.
    spread : float
        The σ of the goal's position (m, per coordinate): offsets within it are barely
        corrected.
    speed : float
        The speed the last step commanded (0 when the tick begins: a tick starts at rest).
    step : int
        The step's index in the tick.
    limits : Limits
    end : int, optional
        The step by which to be at the goal and at rest (default: the tick's end).
    drift : float
        How much the terrain turns the chart heading per metre of arc beyond what is
        commanded (rad/m, :meth:`HeadingFilter.drift`): the step commands that much less, so
        that it turns, and drives along, what the law wants.

    Returns
    -------
    v, omega, turn : float
        m of arc per time unit and rad per time unit (within the limits), and the chart turn
        (rad) over the step they command (the terrain's drift not included).
    """
    if not 0 <= step < len(limits.durations):
        raise ValueError(f"step must be in 0..{len(limits.durations) - 1}, got {step}")
    dt = limits.durations[step]
    end = len(limits.durations) if end is None else max(end, step + 1)
    time = sum(limits.durations[step:])  # to the tick's end
    offset = goal - position
    axis = polar(1.0, goal_heading)
    along, aside = float(offset @ axis), _cross(axis, offset)
    line = goal_heading if along >= 0.0 else goal_heading + math.pi
    if along < 0.0:
        along, aside = -along, -aside
    floor = 3.0 * spread + MIN_CHORD * limits.spacing
    aside *= _weight(aside * aside, floor * floor)
    ahead = max(0.5 * along, floor)
    bend = math.atan2(aside, ahead)
    left = max(time - dt, 0.0)  # turn out now, and back in time
    room = 0.5 * limits.max_turn * left if left > 0.0 else 0.0
    bend = max(-room, min(room, bend))
    course = wrap(line + bend)  # the direction to travel
    error = wrap(course - heading)
    # which way to travel: the nearer one for the heading, unless the heading is turned more
    # than a right angle from the goal's; then the one that ends on the goal's (turning first)
    ends = error if math.cos(wrap(goal_heading - heading)) >= 0.0 else wrap(course - goal_heading)
    direction = 1.0 if math.cos(ends) >= 0.0 else -1.0
    if direction < 0.0:
        error = wrap(error + math.pi)
    distance = math.hypot(offset[0], offset[1]) * max(math.cos(error), 0.0)
    along_slope = slope[0] * math.cos(heading) + slope[1] * math.sin(heading)
    stretch = math.sqrt(1.0 + along_slope * along_slope)  # m of arc per m of chart
    speeds = _timed_speeds(distance, direction * speed, step, end, limits, stretch)
    v = direction * float(speeds[0])
    v = max(-limits.max_speed, min(limits.max_speed, v))
    turn = error
    if end == len(limits.durations) and end - step == 2:  # the tick's last two arcs
        turn += _arc_turn(wrap((heading if direction > 0.0 else heading + math.pi) - line),
                          np.abs(speeds) * limits.durations[step:end] / stretch, floor)
    turn -= drift * abs(v) * dt  # the terrain turns it the rest of the way
    omega = metric_angle(slope, heading, heading + turn) / dt
    if abs(omega) > limits.max_turn:  # the chart turn of what it can turn
        omega = math.copysign(limits.max_turn, omega)
        turn = chart_turn(slope, heading, omega * dt)
    return float(v), float(omega), float(turn)


def slope_ahead(start: np.ndarray, slope: np.ndarray, driven: float, ahead: float,
                sigma: float) -> np.ndarray:
    """The slope ``ahead`` m of arc on (half-way along the next step, for
    :func:`step_command`): the reading ``slope`` plus its change per metre over the tick so
    far, from the reading ``start`` ``driven`` m of arc back, kept by its weight
    ``1 − 9v / |Δ|²`` above three times its declared spread (:func:`_trust`; ``v``: both
    readings' tilt noise ``σ`` through ``tan′ = 1 + s²``, both coordinates together). A step
    on a slope that steepens drives fewer metres of chart than its start slope says (0.6 mm in
    a 0.31 m step on the elliptic bowl, what the window's last step landed short by), and a
    slope changes steadily along a tick's way; without noise the change is exact, under noise
    one within it is left out, as :meth:`HeadingFilter.drift` leaves out a turn."""
    if driven <= 0.0 or ahead <= 0.0:
        return slope
    change = slope - start
    spread = sigma * sigma * float(np.sum((1.0 + start * start) ** 2 + (1.0 + slope * slope) ** 2))
    return slope + _trust(float(change @ change), 9.0 * spread) * change * (ahead / driven)


def _arc_turn(angle: float, lengths: np.ndarray, floor: float) -> float:
    """What the window's second-to-last step turns beyond :func:`step_command`'s law, whose
    last step turns onto the approach line from a heading of travel ``angle`` off it: a step
    that turns by ``τ`` drives along its start heading plus ``τ/2``, so that last arc lands
    ``L₂ angle / 2`` aside (small angles). The two steps, of chart ``lengths`` ``(L₁, L₂)``
    (the timed profile's), end on the line and along it if the first turns
    ``−angle L₁ / (L₁ + L₂)`` further (``1.5 angle`` in all for equal steps). The extra turn is
    kept by its Wiener weight, the aside it makes up against ``floor`` (three times the goal's
    spread): under noise it is millimetres against centimetres and changes next to nothing."""
    first, last = float(lengths[0]), float(lengths[-1])
    if not first + last > 0.0:
        return 0.0
    extra = -angle * first / (first + last)
    aside = 0.5 * last * angle
    return _weight(aside * aside, floor * floor) * extra


def metric_angle(slope: np.ndarray, start: float, end: float) -> float:
    """The signed angle, in the metric ``g = I + s sᵀ`` of the slope ``s``, from the chart
    direction ``start`` to the chart direction ``end`` (rad; the chart turn from one to the
    other, taken in ``(−π, π]``, fixes the way round)."""
    a, b = polar(1.0, start), polar(1.0, end)
    sa, sb = float(slope @ a), float(slope @ b)
    dot = float(a @ b) + sa * sb
    cross = _cross(a, b) * math.sqrt(1.0 + float(slope @ slope))
    angle = math.atan2(cross, dot)
    turn = wrap(end - start)
    if turn * angle < 0.0:  # the chart turn and the metric angle agree in sign
        angle += math.copysign(2.0 * math.pi, turn)
    return angle


def chart_turn(slope: np.ndarray, start: float, angle: float) -> float:
    """The chart turn from the chart direction ``start`` that is the metric angle ``angle``
    (|angle| < π; the inverse of :func:`metric_angle`)."""
    a = polar(1.0, start)
    g = np.eye(2) + np.outer(slope, slope)
    b = np.array([-a[1], a[0]])  # a chart normal, then made g-orthogonal to a, g-unit
    b = b - (a @ g @ b) / (a @ g @ a) * a
    a, b = a / math.sqrt(a @ g @ a), b / math.sqrt(b @ g @ b)
    direction = math.cos(angle) * a + math.sin(angle) * b
    return wrap(math.atan2(direction[1], direction[0]) - start)


class _Fixed:
    """Where a point that does not move within the tick is (the rod end), in the tick's frame,
    from every reading of it so far: each reading (dead-reckoned position plus the sensed offset)
    weighted by the inverse of its declared variance, the reading's (range and bearing at its
    distance) plus the dead
    reckoning's drift since it (the odometry's variance per step); without noise, the latest."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.points: list[tuple[np.ndarray, float]] = []

    def add(self, position: np.ndarray, offset: np.ndarray) -> None:
        """A reading ``offset`` (2,) taken from the dead-reckoned ``position`` (2,)."""
        distance = math.hypot(offset[0], offset[1])
        self.add_point(position + offset, self.limits.reading_variance(distance))

    def add_point(self, point: np.ndarray, variance: float) -> None:
        """An estimate ``point`` (2,) of the point, of ``variance`` (both coordinates)."""
        self.points.append((point, variance))

    def drift(self, step: int) -> None:
        """Step ``step`` was driven: every earlier reading drifts by its odometry noise."""
        if self.limits.odometry_variance:
            extra = 2.0 * self.limits.odometry_variance[step]
            self.points = [(p, v + extra) for p, v in self.points]

    def estimate(self) -> tuple[np.ndarray, float]:
        """The goal and its σ per coordinate."""
        if self.points[-1][1] == 0.0:
            return self.points[-1][0], 0.0
        weights = np.array([1.0 / v for _, v in self.points])
        goal = sum(w * p for w, (p, _) in zip(weights, self.points)) / weights.sum()
        return goal, math.sqrt(0.5 / weights.sum())

    def seen_from(self, position: np.ndarray) -> tuple[np.ndarray, float]:
        """:meth:`estimate` as an offset from ``position`` (2,), with its variance (both
        coordinates together)."""
        point, sigma = self.estimate()
        return point - position, 2.0 * sigma * sigma


@dataclass(frozen=True)
class Driven:
    """How a driving tick went: ``moved`` is the sensing after the move phase, ``travelled``
    the displacement the odometry summed over it (local frame, from the tick's start), and,
    when the rod end was in range, ``residual``: where the robot believes the rod end is from
    where it settled (its best estimate, after every reading) and that estimate's variance
    (both coordinates together); ``leader`` and ``leader_variance`` the same of the leader,
    from its ``pre`` reading and every step's (it stands still through the follower's tick);
    ``limits`` the follower's, which declare the settled readings' variance; ``told`` what it
    tells its successor of its heading as it settles (:func:`told_heading`; None without a
    track or noise)."""

    moved: Sensing
    travelled: np.ndarray
    residual: np.ndarray | None = None
    residual_variance: float = 0.0
    leader: np.ndarray | None = None
    leader_variance: float = 0.0
    limits: Limits | None = None
    told: tuple[float, float] | None = None

    def settled_leader(self, reading: np.ndarray) -> np.ndarray:
        """The leader's offset from where the follower settled (shape (2,)) from every look of
        the tick: the drive's estimate (``leader``) and the settled sensing's ``reading``
        (shape (2,)), fused as :class:`_Fixed` fuses the goal's (the leader stands still
        through the follower's tick); without noise, the reading as it is."""
        if self.leader is None or self.limits is None:
            return reading
        looks = _Fixed(self.limits)
        looks.add_point(self.leader, self.leader_variance)
        looks.add(np.zeros(2), reading)
        return looks.estimate()[0]


def drive_tick(act: Callable[[Control], ActSensing], pre: Sensing, goal: np.ndarray,
               settings: AgentSettings, limits: Limits, track: Track | None = None) -> Driven:
    """Drive one tick's control steps: towards ``goal`` (an offset from where the follower
    stands at ``pre``), then onto the rod end read after the move phase (re-read after every
    step), ending at rest when the tick's comm interval ends. ``act`` sends one
    :class:`Control` and returns the world's reply; ``limits`` are the follower's
    (:meth:`Limits.from_settings`); ``track`` its last displacements (without one, the
    ``pre`` sensing's odometry reading is the only one known)."""
    if pre.compass is None or pre.slope is None:
        raise ValueError("a driving follower's sensing must carry its compass and slope")
    landed = np.zeros(2)
    if track is not None and track.steps:
        previous, landed = track.displacements(), track.landed
    elif pre.velocity is not None:
        previous = (settings.comm_period * np.asarray(pre.velocity, dtype=float),)
    else:
        previous = ()
    filtered = HeadingFilter(pre.compass, limits)
    rod = _Fixed(limits)
    start_slope = np.asarray(pre.slope)  # what slope_ahead measures the slope's change from
    position, slope, speed = np.zeros(2), start_slope, 0.0
    target, spread = np.asarray(goal, dtype=float), math.sqrt(0.5 * limits.chord_variance)

    leader = _Fixed(limits)
    leader.add(np.zeros(2), relative(pre))

    owner = limits if track is None else track  # whose declared chord variance and rod length
    # the path's tangent and its variance per goal (Track.tangent): the move phase keeps one
    paths: dict[bytes, tuple[float, float | None]] = {}

    def heading_at(point: np.ndarray) -> float:
        step = point - landed
        path = paths.get(key := step.tobytes())
        if path is None:
            path = paths[key] = ((goal_heading(pre.compass, step, previous,
                                               owner.chord_variance, owner.spacing), None)
                                 if track is None else track.tangent(pre.compass, step, previous))
        if track is None:
            return path[0]
        return track.fuse(*path, step, point - leader.estimate()[0], pre.shared_heading).heading

    moved, travelled = pre, np.zeros(2)
    reserve = settings.control_steps + settings.snap_steps // 2  # the move phase's end
    for step in range(settings.tick_steps):
        wanted, end = heading_at(target), reserve if step < settings.control_steps else None
        ahead = slope_ahead(start_slope, slope, filtered.driven,
                            0.5 * abs(speed) * limits.durations[step], limits.sigma_bearing)
        v, omega, turn = step_command(position, filtered.heading, ahead, target, wanted,
                                      spread, speed, step, limits, end, filtered.drift())
        given = (float(target[0]), float(target[1])) if step == 0 else None
        reply = act(Control(tick=pre.tick, step=step, speed=v, turn=omega, goal=given))
        odometry = np.asarray(reply.odometry)
        position, slope, speed = position + odometry, np.asarray(reply.slope), v
        filtered.step(step, turn, v, reply.compass, odometry)
        rod.drift(step)
        leader.drift(step)
        if step == settings.control_steps - 1:
            moved, travelled = reply.sensing, position.copy()
        leader.add(position, relative(reply))
        if step >= settings.control_steps - 1 and moved.rod is not None:
            if reply.rod is not None:
                rod.add(position, np.asarray(reply.rod))
            target, spread = rod.estimate()
    seen, variance = leader.seen_from(position)
    residual, residual_variance = (rod.seen_from(position) if moved.rod is not None
                                   and rod.points else (None, 0.0))
    told = (told_heading(filtered) if track is not None and track.chord_variance > 0.0
            else None)
    return Driven(moved, travelled, residual, residual_variance, seen, variance, limits, told)


def told_heading(filtered: HeadingFilter) -> tuple[float, float]:
    """What a driving follower tells its successor of its heading as it settles (its
    :class:`protocol.messages.Snap`): its heading filter's estimate and that filter's variance,
    what it knows of its own heading. Its successor weighs it as one more reading of its own
    by what it erred against its own path (:meth:`Track.fuse`), which holds what the
    filter's variance cannot: how the heading turns along the rod, and the leader's own
    error against the formation."""
    return filtered.heading, filtered.variance
