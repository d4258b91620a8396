"""The run configuration shared by every process (SPEC §9), read from and written to TOML.

``RunConfig`` holds every option of ``python -m swarm run``; :func:`load_config` reads a TOML
file, :func:`dump_config` writes one (atomically), and :meth:`RunConfig.replace` applies CLI
overrides with validation. Agents read only :class:`AgentSettings` (via
:func:`load_agent_settings`): the estimator, the timing and their rods, never the surface.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.keys import check_run_id

CLASSICAL = ("cv", "kalman", "arx", "gp")  # the classical tracking baselines (SPEC §6)
OWN_MOTION = ("gp-motion", "gp-ratio")  # extrapolations of the follower's own displacement
AUTO = ("auto", "auto-mix")  # candidates side by side: the lowest score, or their mixture
ESTIMATORS = ("edmd", "stay", "persist", *AUTO, *CLASSICAL, *OWN_MOTION)
# Your own estimator (SPEC §6): imported by the follower process only, never checked here
# beyond its shape.
PLUGIN_ESTIMATOR = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
DICTIONARIES = ("a", "b", "c", "d", "e", "f", "g")
GPS_DICTIONARIES = ("d", "e", "f", "g")
VELOCITY_VARIANTS = ("oracle", "lagged", "estimated")
SIDES = {"left": 1, "right": -1}
MODES = ("lockstep", "realtime")
MOTIONS = ("teleport", "drive")  # SPEC §4 "Motion"

# Sane ranges of every number of a run (inclusive; a float range's low end is exclusive when
# the option must be positive). Timeouts are seconds; a day-long wait is never meant.
INT_RANGES = {
    "followers": (1, 1000),
    "ticks": (2, 1_000_000),
    "delays": (0, 1000),
    "window": (0, 1_000_000),
    "arx_order": (1, 100),
    "arx_window": (0, 1_000_000),
    "gp_samples": (3, 1000),
    "seed": (0, 2**63 - 1),
    # --motion drive (SPEC §4): control steps per comm interval, steps of the correction window
    "control_steps": (1, 10_000),
    "snap_steps": (0, 10_000),
}
FLOAT_RANGES = {  # name: (low, high, low end exclusive)
    "comm_period": (0.0, 1e4, True),
    "spacing": (0.0, 1e4, True),
    "time_scale": (0.0, 1e3, True),
    "agent_timeout": (0.0, 3600.0, True),
    "start_timeout": (0.0, 3600.0, True),
    "forget": (0.0, 1.0, True),
    "kalman_accel": (0.0, 1e6, True),
    "ridge": (0.0, 1e12, False),
    "noise_range": (0.0, 1e3, False),
    "noise_bearing": (0.0, 10.0, False),
    "noise_velocity": (0.0, 1e3, False),
    "noise_move": (0.0, 1e3, False),
    "noise_gps": (0.0, 1e6, False),
    "sensing_range": (0.0, math.inf, True),
    # --motion drive (SPEC §4): limits (m of arc / time unit, rad / time unit; inf: unbounded)
    # and the actuation noise σ of v and ω per control step
    "max_speed": (0.0, math.inf, True),
    "max_turn": (0.0, math.inf, True),
    "noise_speed": (0.0, 1e3, False),
    "noise_turn": (0.0, 1e3, False),
}
DRIVE_OPTIONS = ("max_speed", "max_turn", "control_steps", "snap_steps", "noise_speed",
                 "noise_turn")
"""Options that only matter with ``motion = "drive"``."""
TELEPORT_OPTIONS = ("noise_move",)
"""Options that only matter with ``motion = "teleport"`` (drive has noise_speed, noise_turn)."""
UNSET_DEFAULT = ("max_speed",)
"""Options whose default (None) the world resolves: ``max_speed`` is twice the leader's speed."""
MAX_COORDINATE = 1e9  # bound on a leader start component and on a surface parameter
MAX_SURFACE_PARAMS = 32
MAX_SURFACE_NAME = 4096  # room for a 'dem:PATH' with a long path (Linux PATH_MAX)
_PARAM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}")
MAX_CONFIG_BYTES = 64 * 1024  # a real run.toml is under 2 KiB
MAX_CONFIG_DEPTH = 3  # real files have 2: the file's table, and surface_params or leader_start


@dataclass(frozen=True)
class RunConfig:
    """Every option of a run; defaults are the paper's type I case (SPEC §4, §9)."""

    run_id: str = "run"
    surface: str = "elliptic"
    surface_params: dict[str, float] = field(default_factory=dict)
    leader_start: tuple[float, float, float, float] | None = None
    followers: int = 1
    comm_period: float = 1.28
    spacing: float = 3.57
    ticks: int = 40
    init_ticks: int = 4
    side: str = "left"
    estimator: str = "edmd"
    dictionary: str = "b"
    velocity: str = "lagged"
    online: bool = False
    delays: int = 0
    affine: bool = False
    forget: float = 1.0
    window: int = 0
    ridge: float = 0.0
    arx_order: int = 1
    arx_window: int = 10
    gp_samples: int = 8
    kalman_accel: float = 1e-3
    gps: bool = False
    noise_range: float = 0.0
    noise_bearing: float = 0.0
    noise_velocity: float = 0.0
    noise_move: float = 0.0
    noise_gps: float = 0.0
    seed: int = 0
    sensing_range: float = math.inf
    mode: str = "lockstep"
    pipelined: bool = True
    time_scale: float = 1.0
    agent_timeout: float = 10.0
    start_timeout: float = 30.0
    motion: str = "teleport"
    max_speed: float | None = None
    max_turn: float = 2.0
    control_steps: int = 8
    snap_steps: int = 4
    noise_speed: float = 0.0
    noise_turn: float = 0.0

    def __post_init__(self) -> None:
        check_run_id(self.run_id)
        if not (isinstance(self.estimator, str) and PLUGIN_ESTIMATOR.match(self.estimator)):
            _check_choice("estimator", self.estimator, ESTIMATORS + ("package.module:Name",))
        _check_choice("dictionary", self.dictionary, DICTIONARIES)
        _check_choice("velocity", self.velocity, VELOCITY_VARIANTS)
        _check_choice("side", self.side, tuple(SIDES))
        _check_choice("mode", self.mode, MODES)
        _check_choice("motion", self.motion, MOTIONS)
        if (not isinstance(self.surface, str) or not 0 < len(self.surface) <= MAX_SURFACE_NAME
                or not self.surface.isprintable()):
            raise ValueError("surface must be a preset name, 'package.module:name' or 'dem:PATH' "
                             f"(at most {MAX_SURFACE_NAME} printable characters), "
                             f"got {_show(self.surface)}")
        for name, (low, high) in INT_RANGES.items():
            _check_int(name, getattr(self, name), low, high)
        _check_int("init_ticks", self.init_ticks, 2, INT_RANGES["ticks"][1])
        if self.init_ticks > self.ticks:
            raise ValueError(f"init_ticks ({self.init_ticks}) must be at most ticks "
                             f"({self.ticks}): raise ticks or lower init_ticks")
        for name, bounds in FLOAT_RANGES.items():
            if not (name in UNSET_DEFAULT and getattr(self, name) is None):
                _check_range(name, getattr(self, name), *bounds)
        check_motion_options(self)
        for name in ("online", "affine", "gps", "pipelined"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.estimator == "edmd" and self.dictionary in GPS_DICTIONARIES and not self.gps:
            raise ValueError(f"dictionary {self.dictionary!r} uses absolute positions: enable gps")
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

    @property
    def side_sign(self) -> int:
        """+1 for a rod on the left of the heading, -1 on the right."""
        return SIDES[self.side]

    def replace(self, **changes: Any) -> RunConfig:
        """A copy with ``changes`` applied (unknown names raise ValueError)."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(f"unknown configuration option(s): {sorted(unknown)}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML-ready: ``leader_start`` a list, None omitted)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out


def check_motion_options(config: RunConfig) -> None:
    """Refuse an option set away from its default that the run's motion model ignores
    (ValueError naming it): the drive options with ``teleport``, ``noise_move`` with
    ``drive``."""
    ignored = DRIVE_OPTIONS if config.motion == "teleport" else TELEPORT_OPTIONS
    for name in ignored:
        default = RunConfig.__dataclass_fields__[name].default
        if getattr(config, name) != default:
            other = "drive" if config.motion == "teleport" else "teleport"
            raise ValueError(f"{name} applies only to motion {other!r} (this run's motion is "
                             f"{config.motion!r})")


@dataclass(frozen=True)
class AgentSettings:
    """What an agent process is told: timing, rods and its estimator. Never the surface."""

    run_id: str
    followers: int
    comm_period: float
    spacing: float
    ticks: int
    init_ticks: int
    side: int
    estimator: str
    dictionary: str
    velocity: str
    online: bool
    delays: int
    affine: bool
    forget: float
    window: int
    ridge: float
    arx_order: int
    arx_window: int
    gp_samples: int
    kalman_accel: float
    noise_range: float
    noise_bearing: float
    noise_move: float
    gps: bool
    mode: str
    time_scale: float
    agent_timeout: float
    start_timeout: float
    noise_velocity: float
    motion: str
    max_speed: float | None
    max_turn: float
    control_steps: int
    snap_steps: int

    @property
    def step_timeout(self) -> float:
        """How long an agent waits for its next step before concluding the run is stuck:
        the whole chain's time budget, and in realtime at least two wall-clock ticks."""
        budget = self.agent_timeout * (self.followers + 2)
        if self.mode == "realtime":
            budget = max(budget, 2 * self.comm_period * self.time_scale)
        return max(budget, 10.0)

    @classmethod
    def from_config(cls, config: RunConfig) -> AgentSettings:
        names = {f.name for f in dataclasses.fields(cls)} - {"side"}
        return cls(side=config.side_sign, **{n: getattr(config, n) for n in names})


def config_from_dict(data: dict[str, Any]) -> RunConfig:
    """Build a RunConfig from a plain dict (e.g. parsed TOML); unknown keys raise ValueError."""
    known = {f.name for f in dataclasses.fields(RunConfig)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"unknown configuration option(s): {sorted(unknown)}")
    data = dict(data)
    if isinstance(data.get("leader_start"), list):
        data["leader_start"] = tuple(data["leader_start"])
    return RunConfig(**data)


def load_config(path: str | os.PathLike[str]) -> RunConfig:
    """Read a TOML run configuration; every error is one line naming the file and the problem.

    A file over ``MAX_CONFIG_BYTES`` or nesting tables/arrays deeper than ``MAX_CONFIG_DEPTH``
    is refused before its values are looked at.
    """
    path = Path(path)
    return config_from_file(read_toml(path, "config file"), path)


def config_from_file(data: dict[str, Any], path: str | os.PathLike[str]) -> RunConfig:
    """The run configuration in ``data``, a TOML table read from ``path`` (its ``meta`` table
    ignored); errors name the file."""
    data = {k: v for k, v in data.items() if k != "meta"}
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


def load_agent_settings(path: str | os.PathLike[str]) -> AgentSettings:
    """What an agent may read of a run configuration."""
    return AgentSettings.from_config(load_config(path))


def dump_config(config: RunConfig, path: str | os.PathLike[str]) -> None:
    """Write ``config`` as TOML, atomically (temporary file, then rename)."""
    lines = ["# Fully resolved run configuration: `python -m swarm run --config` repeats it."]
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


def json_checksum(body: dict) -> str:
    """SHA-256 (hex) of ``body``'s canonical JSON (sorted keys, no spaces): the checksum of
    every state file (the world's checkpoint, a follower's replay log lines)."""
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


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


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number here")


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
