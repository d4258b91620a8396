"""The run configuration shared by every process (design §9): each option declared once.

Every option of a run is one field of :class:`RunConfig`, declared with :func:`option`: its
name (the TOML key; the CLI flag is derived from it), type and default (the field's), unit,
one-line meaning, allowed range or choices, and whether the agents see it. Everything else is
derived from those declarations (:data:`OPTIONS`): the validation in
:meth:`RunConfig.__post_init__`, the TOML keys (:func:`load_config`, :func:`dump_config`), the
flags and ``--help`` of ``swarm run``/``compare`` (:mod:`swarm.cli`), :class:`AgentSettings`
(the agent-visible subset: never the surface, the leader start, the seed or any other
world-only option), :class:`AgentBrief` (what an agent process is given: its id and those
settings) and the table of ``docs/options.md`` (:func:`options_table`).

An option that does nothing in a run is refused, not ignored: which estimator uses which
option is declared once in :data:`ESTIMATOR_OPTIONS`, other dependencies in each option's
``needs`` (:func:`idle_reason`). A value equal to the default is never refused, so a
``config.toml`` that lists every option loads back.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.folder import write_atomic
from protocol.keys import check_agent_id, check_run_id
from protocol.limits import MAX_RUN_ID
from protocol.ros2 import DOMAIN_RANGE, domain_from_env

CLASSICAL = ("cv", "kalman", "arx", "gp")  # the classical tracking baselines (design §6)
FILTERS = ("ekf",)  # model-based trackers of the leader and its rod (auto's with noise only)


def filterable(sigma_range: float, sigma_bearing: float) -> bool:
    """Whether the model-based filters (:data:`FILTERS`) can take a sensor of these σ: noisy
    on both axes, or exact on both. Exact on one axis only, a reading's covariance is rank one,
    and against the filters' diffuse start their update loses positive-definiteness in floating
    point (NaN predictions, seen in driving columns): ``auto`` then leaves them out, and
    ``--estimator ekf`` is refused.

    >>> filterable(0.02, 0.01), filterable(0.0, 0.0), filterable(0.02, 0.0)
    (True, True, False)
    """
    return (sigma_range > 0.0) == (sigma_bearing > 0.0)
OWN_MOTION = ("gp-motion", "gp-ratio")  # extrapolations of the follower's own displacement
AUTO = ("auto", "auto-mix")  # candidates side by side: the lowest score, or their mixture
ESTIMATORS = ("edmd", "stay", "persist", *AUTO, *CLASSICAL, *FILTERS, *OWN_MOTION)
# Your own estimator (design §6): imported by the follower process only, never checked here
# beyond its shape.
PLUGIN_ESTIMATOR = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
DICTIONARIES = ("a", "b", "c", "d", "e", "f", "g")
GPS_DICTIONARIES = ("d", "e", "f", "g")
VELOCITY_VARIANTS = ("oracle", "lagged", "estimated")
SIDES = {"left": 1, "right": -1}
MODES = ("lockstep", "realtime")
MOTIONS = ("teleport", "drive")  # how a follower moves (design §4 "Motion")

_EDMD = ("dictionary", "velocity", "online", "delays", "affine", "forget", "window", "ridge")
_AUTO = ("arx_order", "arx_window", "gp_samples", "kalman_accel")  # its candidates' options
ESTIMATOR_OPTIONS: dict[str, tuple[str, ...]] = {
    "edmd": _EDMD, "arx": ("arx_order", "arx_window"), "gp": ("gp_samples",),
    "gp-motion": ("gp_samples",), "gp-ratio": ("gp_samples",), "kalman": ("kalman_accel",),
    "auto": _AUTO, "auto-mix": _AUTO,
}
"""The options only some estimators use, by estimator (the others use none of them). Your own
estimator (``package.module:Name``) may read any of them from its settings."""

LENGTH, TIME = "m", "s"
"""The units of every length and time, in options, tables, figures and output. Lengths are
metres: a DEM's coordinates and heights are metres, and the paper's analytic surfaces
(dimensionless, "3.57 units" in the paper) are read as metres. Times are seconds of the
simulation's clock: ``T_c = 1.28 s`` is simulated time, which realtime mode paces by the
wall clock (``time_scale`` wall-clock seconds per simulated second) and lockstep mode runs
as fast as it can; timeouts are wall-clock seconds."""
SPEED, TURN = f"{LENGTH}/{TIME}", f"rad/{TIME}"
"""A speed (along the surface) and a turn rate (in its metric)."""
ACCEL = f"{LENGTH}/{TIME}²"
"""An acceleration (along the surface)."""

MAX_COORDINATE = 1e9  # bound on a leader start component and on a surface parameter
MAX_SURFACE_PARAMS = 32
MAX_SURFACE_NAME = 4096  # room for a 'dem:PATH' with a long path (Linux PATH_MAX)
_PARAM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}")
MAX_CONFIG_BYTES = 64 * 1024  # a real run.toml is under 2 KiB
MAX_CONFIG_DEPTH = 3  # real files have 2: the file's table, and surface_params or leader_start
MAX_TIMEOUT = 3600.0  # seconds: a day-long wait is never meant
CORRECTION_SHARE = 0.5
"""The share of a comm interval a driving follower's correction window takes (design §4): the
move phase has the rest, so the rod end is read at the same time whatever the step counts.

Half, so that the window can undo an estimate's error sideways, not only along the way: a
unicycle under way at ``v`` that turns out at its top rate ``ω`` and back within a window of
``T`` shifts sideways by about ``v ω T² / 4``. At the defaults (``ω`` = 2 rad/s, ``T_c`` = 1.28
s, under way at about 1.3 m/s when it looks) that is 0.13 m in a third of ``T_c`` and 0.27 m in
half, and the landings that broke 5-follower columns at σ 0.05/0.03 with a third were
0.27–0.30 m off sideways (docs/drive.md). The cost is an earlier look, from about twice as far
(the drive study's default robot, noise-free: mean required range 0.31–0.81 m against
0.16–0.44 m), still under a quarter of the rod along which the follower reads its leader at
every step."""
ACCEL_FACTOR = 4.0
"""``max_accel``'s default, in ``max_speed / comm_period``: top speed from rest in a quarter
of a comm period (docs/drive.md)."""
FORMATION_TOLERANCE = 1.0
"""``formation_tolerance``'s default, metres (docs/drive.md)."""


@dataclass(frozen=True)
class Option:
    """The declaration of one run option (the metadata of its :class:`RunConfig` field).

    Attributes
    ----------
    meaning : str
        One line for ``--help`` and the options table.
    unit : str
        :data:`LENGTH`, :data:`TIME`, :data:`SPEED`, ``"rad"``, ``"ticks"``...; ``"1"`` for a
        dimensionless number, ``""`` for a name or a choice.
    low, high : float, optional
        Allowed range of a number, inclusive (``low`` exclusive with ``low_open``).
    choices : tuple of str
        Allowed values of a choice.
    agents : bool
        The agent processes see it (in :class:`AgentSettings`); else only the world does.
    needs : (str, value), optional
        The option does something only when option ``needs[0]`` has value ``needs[1]``.
    value_type : type, optional
        The type of its values where the default's is not it (a default of None, left to
        the world to resolve; a tuple given as a list in TOML); see :attr:`kind`.
    flag : str or None
        Its flag of ``swarm run`` (default ``--`` and the name with dashes; None for none).
    metavar : str, optional
        How ``--help`` shows the flag's value.
    name, default :
        Filled in from the field.
    """

    meaning: str
    unit: str = ""
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: tuple[str, ...] = ()
    agents: bool = False
    needs: tuple[str, Any] | None = None
    value_type: type | None = None
    flag: str | None = ""
    metavar: str | None = None
    name: str = ""
    default: Any = None

    @property
    def kind(self) -> type:
        """The option's type: bool, int, float, str, tuple or dict; ``value_type`` where it is
        declared, else the default's type."""
        return self.value_type or type(self.default)

    @property
    def estimators(self) -> tuple[str, ...]:
        """The built-in estimators that use it; empty if every run uses it."""
        return tuple(e for e, names in ESTIMATOR_OPTIONS.items() if self.name in names)

    def show(self, value: Any) -> str:
        """``value`` as written in a TOML file (``inf``, ``true``, ``"c"``)."""
        if isinstance(value, dict):
            return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
        return _toml_value(list(value) if isinstance(value, tuple) else value)


def option(default: Any, meaning: str, **declaration: Any) -> Any:
    """A :class:`RunConfig` field declaring one option (see :class:`Option`)."""
    metadata = {"option": Option(meaning, **declaration)}
    if isinstance(default, dict):
        return field(default_factory=dict, metadata=metadata)
    return field(default=default, metadata=metadata)


@dataclass(frozen=True)
class RunConfig:
    """Every option of a run; defaults are the paper's type I case (design §4, §9).

    Lengths in metres, times in seconds (:data:`LENGTH`, :data:`TIME`).
    """

    run_id: str = option("run", f"the run's id (1-{MAX_RUN_ID} of A-Z a-z 0-9 _ . -): its "
                         "Zenoh key prefix and results folder",
                         agents=True, metavar="ID")
    surface: str = option("elliptic", "the hidden surface: a preset (elliptic, hyperbolic, "
                          "wavy, plane, gaussian-hill, ripple, hemisphere), dem:PATH or "
                          "package.module:name", metavar="NAME")
    surface_params: dict[str, float] = option({}, "the surface's parameters (a TOML table)",
                                              flag=None)
    leader_start: tuple[float, float, float, float] | None = option(
        None, "the leader's start position and velocity", value_type=tuple,
        unit=f"{LENGTH}, {SPEED}", metavar="X,Y,VX,VY")
    followers: int = option(1, "followers in the column", unit="agents", low=1, high=1000,
                            agents=True)
    comm_period: float = option(1.28, "T_c, simulated time between messages", unit=TIME, low=0.0,
                                high=1e4, low_open=True, agents=True)
    spacing: float = option(3.57, "rod length d (Riemannian)", unit=LENGTH, low=0.0, high=1e4,
                            low_open=True, agents=True)
    ticks: int = option(40, "ticks of the run", unit="ticks", low=2, high=1_000_000,
                        agents=True)
    init_ticks: int = option(4, "initial ticks that only sense (estimation starts after)",
                             unit="ticks", low=2, high=1_000_000, agents=True)
    side: str = option("left", "side of the heading the rods point to", choices=tuple(SIDES),
                       agents=True)
    estimator: str = option("edmd", "the followers' estimator: a built-in one, edmd-<letter> "
                            "(edmd on that dictionary) or your own package.module:Name",
                            choices=ESTIMATORS, agents=True, metavar="NAME")
    dictionary: str = option("b", "EDMD dictionary (d-g need gps)", choices=DICTIONARIES,
                             agents=True)
    velocity: str = option("lagged", "the velocity dictionary c lifts", agents=True,
                           choices=VELOCITY_VARIANTS, needs=("dictionary", "c"))
    online: bool = option(False, "EDMD: recursive update instead of a refit per tick",
                          agents=True)
    delays: int = option(0, "EDMD: delay embeddings", unit="ticks", low=0, high=1000,
                         agents=True)
    affine: bool = option(False, "EDMD: a constant in the dictionary", agents=True)
    forget: float = option(1.0, "EDMD: forgetting factor λ per pair", unit="1", low=0.0,
                           high=1.0, low_open=True, agents=True)
    window: int = option(0, "EDMD: sliding window of pairs (0 = all)", unit="pairs", low=0,
                         high=1_000_000, agents=True)
    ridge: float = option(0.0, "EDMD: ridge regularisation α", unit="1", low=0.0, high=1e12,
                          agents=True)
    arx_order: int = option(1, "arx: past (x, u) pairs per regressor", unit="pairs", low=1,
                            high=100, agents=True)
    arx_window: int = option(10, "arx: pairs fitted (0 = all)", unit="pairs", low=0,
                             high=1_000_000, agents=True)
    gp_samples: int = option(8, "gp: samples fitted", unit="samples", low=3, high=1000,
                             agents=True)
    kalman_accel: float = option(1e-3, "kalman: process noise", unit=f"{LENGTH}²/tick⁴",
                                 low=0.0, high=1e6, low_open=True, agents=True)
    gps: bool = option(False, "agents read their absolute position (GPS)", agents=True)
    noise_range: float = option(0.0, "σ of a range reading", unit=LENGTH, low=0.0, high=1e3,
                                agents=True)
    noise_bearing: float = option(0.0, "σ of a bearing reading", unit="rad", low=0.0,
                                  high=10.0, agents=True)
    noise_velocity: float = option(0.0, "σ of a velocity (odometry) reading", unit=SPEED,
                                   low=0.0, high=1e3, agents=True)
    noise_move: float = option(0.0, "σ of a move's actuation, per coordinate", unit=LENGTH,
                               low=0.0, high=1e3, agents=True, needs=("motion", "teleport"))
    noise_gps: float = option(0.0, "σ of a GPS reading, per coordinate", unit=LENGTH, low=0.0,
                              high=1e6, agents=True, needs=("gps", True))
    seed: int = option(0, "seed of every noise stream", low=0, high=2**63 - 1)
    sensing_range: float = option(math.inf, "R_s: how far a follower sees its leader's rod "
                                  "end (inf = unlimited)", unit=LENGTH, low=0.0, high=math.inf,
                                  low_open=True)
    mode: str = option("lockstep", "lockstep, or realtime (paced by the wall clock)",
                       choices=MODES, agents=True)
    pipelined: bool = option(True, "agents overlap ticks as a wavefront (--unpipelined: one "
                             "agent at a time, for comparison)", flag="--unpipelined",
                             needs=("mode", "lockstep"))
    time_scale: float = option(1.0, "realtime: wall-clock seconds per simulated second",
                               unit="1", low=0.0, high=1e3, low_open=True, agents=True,
                               needs=("mode", "realtime"))
    agent_timeout: float = option(10.0, "how long (wall clock) an agent may take to settle",
                                  unit=TIME, low=0.0, high=MAX_TIMEOUT, low_open=True, agents=True)
    start_timeout: float = option(30.0, "how long (wall clock) the world waits for every agent "
                                  "to start, and an agent for its world (at start, and after "
                                  "it vanished: a paused or restarted world)",
                                  unit=TIME, low=0.0, high=MAX_TIMEOUT, low_open=True,
                                  agents=True)
    ros2: bool = option(False, "the world also publishes the run's ROS 2 topics (design §10)")
    ros_domain: int = option(0, "ROS 2 domain id of those topics (swarm run: ROS_DOMAIN_ID "
                             "when --ros2 is given without it)", low=DOMAIN_RANGE[0],
                             high=DOMAIN_RANGE[1],
                             needs=("ros2", True))

    motion: str = option("teleport", "how a follower moves: teleport (relocated by the "
                         "commanded offset) or drive (a unicycle robot on the surface, design §4)",
                         choices=MOTIONS, agents=True)
    max_speed: float | None = option(None, "drive: top forward speed along the surface",
                                     value_type=float, unit=SPEED, low=0.0, high=math.inf,
                                     low_open=True, agents=True, needs=("motion", "drive"))
    max_turn: float = option(2.0, "drive: top turn rate, in the surface's metric", unit=TURN,
                             low=0.0, high=math.inf, low_open=True, agents=True,
                             needs=("motion", "drive"))
    control_steps: int = option(8, "drive: control steps per comm interval (to the estimate)",
                                unit="steps", low=1, high=10_000, agents=True,
                                needs=("motion", "drive"))
    snap_steps: int = option(4, "drive: control steps of the correction onto the sensed rod "
                             "end", unit="steps", low=0, high=10_000, agents=True,
                             needs=("motion", "drive"))
    noise_speed: float = option(0.0, "drive: σ of the forward speed's actuation per control "
                                "step", unit=SPEED, low=0.0, high=1e3, agents=True,
                                needs=("motion", "drive"))
    noise_turn: float = option(0.0, "drive: σ of the turn rate's actuation per control step",
                               unit=TURN, low=0.0, high=1e3, agents=True,
                               needs=("motion", "drive"))
    max_accel: float | None = option(None, "drive: top forward acceleration along the "
                                     f"surface; unset: {ACCEL_FACTOR:g} × max speed / comm "
                                     "period, top speed from rest in a quarter comm period",
                                     value_type=float, unit=ACCEL, low=0.0, high=math.inf,
                                     low_open=True, agents=True, needs=("motion", "drive"))
    formation_tolerance: float = option(FORMATION_TOLERANCE, "how far a follower may stand "
                                        "from its place in the ideal formation, settled in time "
                                        "or not, before the tick counts as broken formation (a "
                                        "run with one fails)",
                                        unit=LENGTH, low=0.0, high=math.inf, low_open=True)

    def __post_init__(self) -> None:
        check_run_id(self.run_id)
        if (not isinstance(self.surface, str) or not 0 < len(self.surface) <= MAX_SURFACE_NAME
                or not self.surface.isprintable()):
            raise ValueError("surface must be a preset name, 'package.module:name' or 'dem:PATH' "
                             f"(at most {MAX_SURFACE_NAME} printable characters), "
                             f"got {_show(self.surface)}")
        for name, declared in OPTIONS.items():
            _check_declared(declared, getattr(self, name))
        if self.init_ticks > self.ticks:
            raise ValueError(f"init_ticks ({self.init_ticks}) must be at most ticks "
                             f"({self.ticks}): raise ticks or lower init_ticks")
        if self.estimator == "edmd" and self.dictionary in GPS_DICTIONARIES and not self.gps:
            raise ValueError(f"dictionary {self.dictionary!r} uses absolute positions: enable gps")
        if self.estimator in FILTERS and not filterable(self.noise_range, self.noise_bearing):
            raise ValueError(f"estimator {self.estimator!r} models a range/bearing sensor noisy on "
                             "both axes or on neither: set noise_range and noise_bearing both "
                             f"above 0 or both 0, got {self.noise_range:g} and "
                             f"{self.noise_bearing:g}")
        if self.leader_start is not None:
            if not isinstance(self.leader_start, (tuple, list)) or len(self.leader_start) != 4:
                raise ValueError(f"leader_start must be X,Y,VX,VY, got {_show(self.leader_start)}")
            for i, x in enumerate(self.leader_start):
                _check_range(f"leader_start[{i}]", x, -MAX_COORDINATE, MAX_COORDINATE)
            if self.leader_start[2] == 0 and self.leader_start[3] == 0:
                raise ValueError("leader_start velocity must not be zero")
            object.__setattr__(self, "leader_start", tuple(float(x) for x in self.leader_start))
        params = self.surface_params
        if not isinstance(params, dict) or len(params) > MAX_SURFACE_PARAMS:
            raise ValueError(f"surface_params must be a table of at most {MAX_SURFACE_PARAMS} "
                             "numbers")
        for key, value in params.items():
            if not isinstance(key, str) or not _PARAM_NAME.fullmatch(key):
                raise ValueError("surface_params names must be identifiers of at most 32 "
                                 f"characters, got {_show(key)}")
            _check_range(f"surface_params.{key}", value, -MAX_COORDINATE, MAX_COORDINATE)
        check_effective({name: getattr(self, name) for name in OPTIONS})

    @property
    def side_sign(self) -> int:
        """+1 for a rod on the left of the heading, -1 on the right."""
        return SIDES[self.side]

    @property
    def drives(self) -> bool:
        """Whether the followers drive (``motion = "drive"``) instead of being relocated."""
        return self.motion == "drive"

    @property
    def accel_limit(self) -> float:
        """A driving follower's top forward acceleration: ``max_accel``, by default
        :data:`ACCEL_FACTOR` × ``max_speed`` / ``comm_period`` (``max_speed`` resolved)."""
        if self.max_accel is not None:
            return self.max_accel
        if self.max_speed is None:
            raise ValueError("max_speed must be resolved before the default max_accel")
        return ACCEL_FACTOR * self.max_speed / self.comm_period

    @property
    def tick_steps(self) -> int:
        """A driving follower's control steps per tick: the move phase's, then the
        correction window's."""
        return self.control_steps + self.snap_steps

    @property
    def correction_share(self) -> float:
        """The share of a comm interval a driving follower's correction window takes:
        :data:`CORRECTION_SHARE`, or 0 without one (``snap_steps = 0``)."""
        return CORRECTION_SHARE if self.snap_steps else 0.0

    def step_duration(self, step: int) -> float:
        """How long control step ``step`` of a tick lasts (design §4 "Motion"): the tick's
        steps fill its comm interval, the move phase's ``control_steps`` its first
        ``1 − CORRECTION_SHARE`` (all of it without a correction window) and the correction
        window's ``snap_steps`` the rest."""
        if not 0 <= step < self.tick_steps:
            raise ValueError(f"step must be in 0..{self.tick_steps - 1}, got {step}")
        share = self.correction_share
        if step < self.control_steps:
            return self.comm_period * (1.0 - share) / self.control_steps
        return self.comm_period * share / self.snap_steps

    def step_start(self, step: int) -> float:
        """When control step ``step`` begins, from the start of its tick's comm interval
        (``step = tick_steps``: the interval's end)."""
        share = self.correction_share
        move = self.comm_period * (1.0 - share)
        if step <= self.control_steps:
            return move * step / self.control_steps
        return move + self.comm_period * share * (step - self.control_steps) / self.snap_steps

    def stop_time(self, step: int) -> float:
        """The time a driving robot has to come to rest after control step ``step``: the
        steps after it, then the settle, a stop within one last step's time (the speed a step
        may hold is at most ``accel_limit`` × this)."""
        last = self.tick_steps - 1
        return self.step_start(self.tick_steps) - self.step_start(step + 1) \
            + self.step_duration(last)

    def replace(self, **changes: Any) -> RunConfig:
        """A copy with ``changes`` applied (unknown names raise ValueError)."""
        unknown = set(changes) - set(OPTIONS)
        if unknown:
            raise ValueError(f"unknown configuration option(s): {sorted(unknown)}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML-ready: ``leader_start`` a list, an option left None omitted)."""
        out = {}
        for name in OPTIONS:
            value = getattr(self, name)
            if value is not None:
                out[name] = list(value) if isinstance(value, tuple) else value
        return out


OPTIONS: dict[str, Option] = {
    f.name: dataclasses.replace(f.metadata["option"], name=f.name,
                                default={} if f.default is dataclasses.MISSING else f.default)
    for f in dataclasses.fields(RunConfig)
}
"""Every option's declaration, by name, in the order of :class:`RunConfig`."""


def idle_reason(name: str, values: Mapping[str, Any]) -> str | None:
    """Why option ``name`` does nothing in a run whose options are ``values`` (every one),
    e.g. ``"with estimator persist (only edmd uses it)"``; None if it does something. Your own
    estimator may read any estimator option from its settings: none is idle with it."""
    declared, estimator = OPTIONS[name], values["estimator"]
    users = declared.estimators
    if users and estimator not in ESTIMATORS:
        return None
    if users and estimator not in users:
        verb = "uses" if len(users) == 1 else "use"
        return f"with estimator {estimator} (only {', '.join(users)} {verb} it)"
    if declared.needs is not None:
        other, wanted = declared.needs
        if values[other] != wanted:
            return (f"with {other} = {OPTIONS[other].show(values[other])} (only with "
                    f"{other} = {OPTIONS[other].show(wanted)})")
    return None


def check_effective(values: Mapping[str, Any]) -> None:
    """Refuse (ValueError, one line naming the option, its value and why) an option set to
    something other than its default in a run where it does nothing (:func:`idle_reason`)."""
    for name, declared in OPTIONS.items():
        value = values[name]
        if value != declared.default and (why := idle_reason(name, values)) is not None:
            raise ValueError(f"{name} = {declared.show(value)} does nothing {why}: leave it out")


def estimator_options(label: str) -> dict[str, Any]:
    """The options an estimator label names: ``edmd-<letter>`` is ``edmd`` on that
    dictionary (with gps for d-g); any other label is the ``estimator`` itself (a built-in
    name or ``package.module:Name``). The one reader of this form, for ``run``, TOML files and
    the estimator axis of grids."""
    letter = label[5:] if isinstance(label, str) and label.startswith("edmd-") else None
    if letter in DICTIONARIES:
        options = {"estimator": "edmd", "dictionary": letter}
        return {**options, "gps": True} if letter in GPS_DICTIONARIES else options
    return {"estimator": label}


def _agent_settings() -> type:
    """:class:`AgentSettings`, derived from the declarations of the agent-visible options."""

    def step_timeout(self) -> float:
        """How long an agent waits for its next step before concluding the run is stuck:
        the whole chain's time budget, and in realtime at least two wall-clock ticks."""
        budget = self.agent_timeout * (self.followers + 2)
        if self.mode == "realtime":
            budget = max(budget, 2 * self.comm_period * self.time_scale)
        return max(budget, 10.0)

    def from_config(cls, config: RunConfig) -> AgentSettings:
        """What an agent of ``config``'s run is told."""
        return cls(**{name: getattr(config, name) for name in AGENT_OPTIONS})

    fields = [(f.name, f.type) for f in dataclasses.fields(RunConfig) if f.name in AGENT_OPTIONS]
    return dataclasses.make_dataclass("AgentSettings", fields, frozen=True, namespace={
        "__module__": __name__,
        "__doc__": "What a robot knows of its run: the agent-visible options of "
                   ":class:`RunConfig` (timing, rods, its estimator, its own limits and "
                   "noise σ; never the seed, the surface, the leader start or any other "
                   "world option). :class:`AgentBrief` adds the agent's id.",
        "side_sign": RunConfig.side_sign,
        "drives": RunConfig.drives,
        "accel_limit": RunConfig.accel_limit,
        "tick_steps": RunConfig.tick_steps,
        "correction_share": RunConfig.correction_share,
        "step_duration": RunConfig.step_duration,
        "step_start": RunConfig.step_start,
        "stop_time": RunConfig.stop_time,
        "step_timeout": property(step_timeout),
        "from_config": classmethod(from_config),
    })


DEFAULTS: dict[str, Any] = {name: declared.default for name, declared in OPTIONS.items()}
"""Every option's default (``surface_params``: an empty table)."""
AGENT_OPTIONS = tuple(name for name, declared in OPTIONS.items() if declared.agents)
AgentSettings = _agent_settings()


def options_table() -> str:
    """The Markdown table of every option, from the declarations (``docs/options.md`` holds
    it verbatim; a test keeps the two equal)."""
    lines = ["| option (TOML key) | flag | default | unit | allowed | seen by | meaning |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, declared in OPTIONS.items():
        flag, where = flag_of(declared), applies_to(declared)
        cells = [f"`{name}`", f"`{flag}`" if flag else "—",
                 "—" if declared.default is None else f"`{declared.show(declared.default)}`",
                 declared.unit or "—", allowed(declared),
                 "world, agents" if declared.agents else "world",
                 f"{declared.meaning}; {where}" if where else declared.meaning]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def flag_of(declared: Option) -> str | None:
    """The option's flag of ``swarm run`` (None if it has none)."""
    if declared.flag is None:
        return None
    return declared.flag or "--" + declared.name.replace("_", "-")


def allowed(declared: Option) -> str:
    """The allowed values in words: ``[1, 1000]``, ``(0, 1]``, ``a, b, c``, ``true, false``,
    or ``see meaning`` for an option checked by a rule of its own (the run id, the surface,
    its parameters, the leader start)."""
    if declared.choices:
        return ", ".join(declared.choices) + (
            ", edmd-<letter>, package.module:Name" if declared.name == "estimator" else "")
    if declared.kind is bool:
        return "true, false"
    if declared.low is None:
        return "see meaning"
    left = "(" if declared.low_open else "["
    return f"{left}{declared.low:g}, {declared.high:g}]"


def applies_to(declared: Option) -> str:
    """Where the option does something, in words (empty if in every run)."""
    where = []
    if declared.estimators:
        where.append("estimator " + ", ".join(declared.estimators))
    if declared.needs is not None:
        other, wanted = declared.needs
        where.append(f"{other} = {OPTIONS[other].show(wanted)}")
    return ("only with " + " and ".join(where)) if where else ""


def config_from_dict(data: Mapping[str, Any]) -> RunConfig:
    """Build a RunConfig from the options a user gave (e.g. parsed TOML, flags): see
    :func:`given_options`."""
    return RunConfig(**given_options(data))


def given_options(data: Mapping[str, Any]) -> dict[str, Any]:
    """The options in ``data`` as :class:`RunConfig` takes them: an estimator label
    (:func:`estimator_options`) replaced by the options it names, ``leader_start`` a tuple.
    ValueError for an unknown key, or a label that contradicts an option given."""
    unknown = set(data) - set(OPTIONS)
    if unknown:
        raise ValueError(f"unknown configuration option(s): {sorted(unknown)}")
    data = dict(data)
    if "estimator" in data:
        named = estimator_options(data["estimator"])
        for key, value in named.items():
            if key != "estimator" and data.get(key, value) != value:
                raise ValueError(f"estimator {data['estimator']} means {key} = "
                                 f"{OPTIONS[key].show(value)}, but {key} = "
                                 f"{OPTIONS[key].show(data[key])} is given")
        data.update(named)
    if isinstance(data.get("leader_start"), list):
        data["leader_start"] = tuple(data["leader_start"])
    return data


def load_config(path: str | os.PathLike[str]) -> RunConfig:
    """Read a TOML run configuration; every error is one line naming the file and the problem.

    A file over ``MAX_CONFIG_BYTES`` or nesting tables/arrays deeper than ``MAX_CONFIG_DEPTH``
    is refused before its values are looked at.
    """
    return config_from_file(file_options(path), path)


def with_env_domain(options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` with ``ros_domain`` from ``ROS_DOMAIN_ID`` (:func:`protocol.ros2.
    domain_from_env`) when they turn ROS 2 publishing on and leave the domain out: the rule of
    every command that reads a run's options. The environment is read only then (ValueError if
    it is bad)."""
    if options.get("ros2") and "ros_domain" not in options:
        return {**options, "ros_domain": domain_from_env()}
    return dict(options)


def file_options(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The run options of the TOML file ``path``, read under the input limits
    (:func:`read_toml`; ValueError naming the file), its ``meta`` table left out."""
    data = read_toml(Path(path), "config file")
    return {k: v for k, v in data.items() if k != "meta"}


def config_from_file(data: Mapping[str, Any], path: str | os.PathLike[str]) -> RunConfig:
    """The run configuration in ``data``, the options :func:`file_options` read from ``path``;
    errors name the file."""
    try:
        return config_from_dict(data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"config file {path}: {exc}") from None


def read_toml(path: Path, what: str, max_depth: int = MAX_CONFIG_DEPTH) -> dict[str, Any]:
    """The TOML table in ``path`` (a ``what``, e.g. ``"config file"``), read under the input
    limits: a file over ``MAX_CONFIG_BYTES`` or nesting tables/arrays deeper than
    ``max_depth`` is refused before its values are looked at. ValueError: one line naming the
    file and the problem."""
    try:
        with path.open("rb") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError:
        raise ValueError(f"{what} {path} does not exist") from None
    except OSError as exc:
        raise ValueError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ValueError(f"{what} {path} is larger than {MAX_CONFIG_BYTES // 1024} KiB; "
                         "a real one is far smaller")
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"{what} {path} is not UTF-8 text") from None
    except ValueError as exc:  # TOMLDecodeError, or a number too long to convert
        raise ValueError(f"{what} {path} is not valid TOML: {exc}") from None
    except RecursionError:
        raise ValueError(f"{what} {path} nests tables or arrays too deeply") from None
    if _depth(data) > max_depth:
        raise ValueError(f"{what} {path} nests tables or arrays deeper than {max_depth} levels")
    return data


def _depth(value: Any) -> int:
    """Nesting depth of tables and arrays (a scalar is 0), without recursion."""
    depth, level = 0, [value]
    while containers := [c for c in level if isinstance(c, (dict, list))]:
        depth += 1
        level = [x for c in containers for x in (c.values() if isinstance(c, dict) else c)]
    return depth


BRIEF_COMMAND = "python -m swarm agent-config"
"""The command that writes an agent's brief from a run configuration (hand assembly)."""


@dataclass(frozen=True)
class AgentBrief:
    """Everything an agent process is told (design §5, §9): which agent it is (0 the leader,
    K follower K) and what that robot knows, :class:`AgentSettings` — its estimator and its
    options, its own limits, the declared σ of its own sensors and actuators, the comm period,
    the rod's length and side, the tick counts and timeouts, and the run id its keys live
    under. Never the seed, the surface or its parameters, the leader start, the sensing range
    or any other world option. How to connect (endpoint, user, password file, TLS) is given on
    the agent's command line: it belongs to the host it runs on, not to the run.

    The launcher (``swarm run``), ``swarm deploy`` and ``swarm agent-config`` write it with
    :meth:`write`; ``python -m agents.leader``/``agents.follower --config`` read it with
    :meth:`load`, which refuses a run configuration.
    """

    agent: int
    settings: AgentSettings

    def __post_init__(self) -> None:
        check_agent_id(self.agent)
        if self.agent > self.settings.followers:
            raise ValueError(f"agent id must be in 0..{self.settings.followers} (the run's "
                             f"followers), got {self.agent}")

    @classmethod
    def of(cls, config: RunConfig, agent: int) -> AgentBrief:
        """Agent ``agent``'s brief in the run ``config``."""
        return cls(agent, AgentSettings.from_config(config))

    @property
    def role(self) -> str:
        """``"leader"`` or ``"follower K"``."""
        return "leader" if self.agent == 0 else f"follower {self.agent}"

    def text(self) -> str:
        """The brief as TOML: ``agent = K`` and a ``[settings]`` table (an option left None,
        e.g. a drive run's top speed that the world resolves, is left out)."""
        settings = {name: getattr(self.settings, name) for name in AGENT_OPTIONS}
        program = "python -m agents." + ("leader" if self.agent == 0 else "follower")
        lines = [f"# What the {self.role} of run {self.settings.run_id} is told (design §5): "
                 "no seed, surface or other world option.",
                 f"# `{program} --config THIS_FILE` reads it; made by `swarm run`, "
                 f"`swarm deploy` or `{BRIEF_COMMAND}`.",
                 f"agent = {self.agent}", "", "[settings]"]
        lines += [f"{name} = {OPTIONS[name].show(value)}" for name, value in settings.items()
                  if value is not None]
        return "\n".join(lines) + "\n"

    def write(self, path: str | os.PathLike[str]) -> Path:
        """Write :meth:`text` to ``path`` atomically; return the path."""
        write_atomic(Path(path), self.text())
        return Path(path)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> AgentBrief:
        """Read an agent's brief (under the input limits of :func:`read_toml`). ValueError, one
        line naming the file: for a run configuration (it holds the world's secrets; the line
        says what to pass instead), an option no agent is told, or a bad value."""
        data = read_toml(Path(path), "agent brief")
        if "agent" not in data and "settings" not in data:
            raise ValueError(
                f"{path} is a run configuration, which holds what only the world may know (the "
                f"seed, the surface, the leader start): give an agent its brief instead, made by "
                f"`{BRIEF_COMMAND} {path} --id K --out agent-K.toml`")
        unknown = sorted(set(data) - {"agent", "settings"})
        settings = data.get("settings")
        if unknown or not isinstance(settings, dict):
            raise ValueError(f"agent brief {path} must hold `agent = K` and a [settings] table"
                             + (f", not {unknown}" if unknown else ""))
        secret = sorted(set(settings) - set(AGENT_OPTIONS))
        if secret:
            raise ValueError(f"agent brief {path}: {', '.join(secret)} is not something an "
                             "agent is told (unknown, or known only to the world)")
        try:
            return cls(data["agent"], AgentSettings.from_config(config_from_dict(settings)))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"agent brief {path}: {exc}") from None


def dump_config(config: RunConfig, path: str | os.PathLike[str]) -> None:
    """Write ``config`` as TOML, atomically (temporary file, then rename)."""
    lines = ["# Fully resolved run configuration: `python -m swarm run --config` repeats it.",
             "# It holds the world's secrets (seed, surface): agents are given their brief "
             f"(`{BRIEF_COMMAND}`)."]
    tables = []
    for key, value in config.to_dict().items():
        if isinstance(value, dict):
            tables.append((key, value))
        else:
            lines.append(f"{key} = {_toml_value(value)}")
    for key, table in tables:
        lines.append(f"\n[{key}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in sorted(table.items()))
    write_atomic(Path(path), "\n".join(lines) + "\n")


def canonical_json(body: dict) -> str:
    """``body``'s canonical JSON: sorted keys, no spaces, no NaN or infinity."""
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _digest(canonical: str) -> str:
    return hashlib.sha256(canonical.encode()).hexdigest()


def json_checksum(body: dict) -> str:
    """SHA-256 (hex) of ``body``'s canonical JSON (sorted keys, no spaces): the checksum of
    every state file (the world's checkpoint, a follower's replay log lines)."""
    return _digest(canonical_json(body))


def checked_text(body: dict, key: str) -> str:
    """``body`` as canonical JSON with its :func:`json_checksum` added under ``key`` (last),
    encoded once: what :func:`checked_json` reads back (a state file, or one line of a state
    log). ``key`` must not be one of ``body``'s."""
    if key in body:
        raise ValueError(f"the checksum's key {key!r} is already in the body")
    return checked_canonical(canonical_json(body), key)


def checked_canonical(canonical: str, key: str) -> str:
    """:func:`checked_text` of the map whose canonical JSON is ``canonical`` (for a writer that
    composes it itself, on a hot path; ``key`` not among its keys)."""
    empty = canonical == "{}"
    return f'{canonical[:-1]}{"" if empty else ","}{json.dumps(key)}:"{_digest(canonical)}"}}'


def checked_json(text: str | bytes, key: str) -> dict:
    """The JSON map in ``text`` whose field ``key`` (removed) holds :func:`json_checksum` of
    the rest: how every state file is read back. ValueError saying what is wrong: ``is not
    JSON (...)`` (NaN and infinities included: canonical JSON has none), ``is not a
    checksummed map``, ``fails its checksum (corrupt or edited)``."""
    try:
        body = json.loads(text, parse_constant=_no_constant)
    except ValueError as exc:  # UnicodeDecodeError included
        raise ValueError(f"is not JSON ({exc})") from None
    if not isinstance(body, dict) or not isinstance(body.get(key), str):
        raise ValueError("is not a checksummed map")
    given = body.pop(key)
    if json_checksum(body) != given:
        raise ValueError("fails its checksum (corrupt or edited)")
    return body


def checked_line(body: dict, key: str = "sum") -> str:
    """One line of a state log: ``body`` with its :func:`json_checksum` under ``key``, and a
    newline (what :func:`checked_lines` reads back)."""
    return checked_text(body, key) + "\n"


def checked_lines(raw: bytes, max_line: int, key: str = "sum") -> list[dict]:
    """The maps of a state log's lines (:func:`checked_line`), in order. A torn last line (an
    append cut by a crash: no final newline) is dropped — whatever it recorded was never
    answered or reported to anyone; any other defect is a ValueError starting ``line N``."""
    lines = raw.split(b"\n")
    if lines[-1]:  # a torn last append
        lines = lines[:-1]
    lines = lines[:-1] if lines and lines[-1] == b"" else lines
    bodies = []
    for number, line in enumerate(lines, start=1):
        if len(line) > max_line:
            raise ValueError(f"line {number} is longer than {max_line} bytes")
        try:
            bodies.append(checked_json(line, key))
        except ValueError as exc:
            raise ValueError(f"line {number} {exc}") from None
    return bodies


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number here")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ValueError(f"cannot write {type(value).__name__} to TOML")


def _check_declared(declared: Option, value: Any) -> None:
    """ValueError unless ``value`` is of the option's type and within its range or choices
    (run id, surface, leader start and surface parameters have checks of their own)."""
    name = declared.name
    if value is None and declared.default is None:  # left to the world to resolve
        return
    if declared.kind is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be true or false, got {_show(value)}")
    elif declared.choices:
        if name == "estimator" and isinstance(value, str) and PLUGIN_ESTIMATOR.match(value):
            return
        plugin = ("package.module:Name",) if name == "estimator" else ()
        _check_choice(name, value, declared.choices + plugin)
    elif declared.kind is int and declared.low is not None:
        _check_int(name, value, declared.low, declared.high)
    elif declared.kind is float and declared.low is not None:
        _check_range(name, value, declared.low, declared.high, declared.low_open)


def _check_choice(name: str, value: Any, allowed: tuple[str, ...]) -> None:
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {_show(value)}")


def _check_int(name: str, value: Any, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {_show(value)}")


def _check_range(name: str, value: Any, low: float, high: float, low_open: bool = False) -> None:
    """``value`` must be a number in ``[low, high]`` (``(low, high]`` with ``low_open``);
    infinity passes only when ``high`` is infinite, NaN never."""
    ok = (not isinstance(value, bool) and isinstance(value, (int, float)) and not math.isnan(value)
          and (value > low if low_open else value >= low) and value <= high)
    if not ok:
        left = "(" if low_open else "["
        raise ValueError(f"{name} must be in {left}{low:g}, {high:g}], got {_show(value)}")


def _show(value: Any) -> str:
    """``repr(value)`` clipped to one short line (values from a file may be huge)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
