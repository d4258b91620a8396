"""The run configuration shared by every process (SPEC §9), read from and written to TOML.

``RunConfig`` holds every option of ``python -m swarm run``; :func:`load_config` reads a TOML
file, :func:`dump_config` writes one (atomically), and :meth:`RunConfig.replace` applies CLI
overrides with validation. Agents read only :class:`AgentSettings` (via
:func:`load_agent_settings`): the estimator, the timing and their rods, never the surface.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.keys import check_run_id

ESTIMATORS = ("edmd", "stay", "persist", "auto", "cv", "kalman", "arx", "gp")
# Your own estimator (SPEC §6): imported by the follower process only, never checked here
# beyond its shape.
PLUGIN_ESTIMATOR = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
DICTIONARIES = ("a", "b", "c", "d", "e", "f", "g")
GPS_DICTIONARIES = ("d", "e", "f", "g")
VELOCITY_VARIANTS = ("oracle", "lagged", "estimated")
SIDES = {"left": 1, "right": -1}
MODES = ("lockstep", "realtime")


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
    seed: int = 0
    sensing_range: float = math.inf
    mode: str = "lockstep"
    time_scale: float = 1.0
    agent_timeout: float = 10.0
    start_timeout: float = 30.0

    def __post_init__(self) -> None:
        check_run_id(self.run_id)
        if not (isinstance(self.estimator, str) and PLUGIN_ESTIMATOR.match(self.estimator)):
            _check_choice("estimator", self.estimator, ESTIMATORS + ("package.module:Name",))
        _check_choice("dictionary", self.dictionary, DICTIONARIES)
        _check_choice("velocity", self.velocity, VELOCITY_VARIANTS)
        _check_choice("side", self.side, tuple(SIDES))
        _check_choice("mode", self.mode, MODES)
        if not isinstance(self.surface, str) or not self.surface:
            raise ValueError(f"surface must be a preset name or 'package.module:name', got {self.surface!r}")
        _check_int("followers", self.followers, 1, 10_000)
        _check_int("ticks", self.ticks, 2, 1_000_000)
        _check_int("init_ticks", self.init_ticks, 2, self.ticks)
        _check_int("delays", self.delays, 0, 1000)
        _check_int("window", self.window, 0, 10_000_000)
        _check_int("arx_order", self.arx_order, 1, 100)
        _check_int("arx_window", self.arx_window, 0, 10_000_000)
        _check_int("gp_samples", self.gp_samples, 3, 1000)
        _check_int("seed", self.seed, 0, 2**63 - 1)
        for name in ("comm_period", "spacing", "time_scale", "agent_timeout", "start_timeout",
                     "kalman_accel"):
            _check_float(name, getattr(self, name), positive=True)
        for name in ("ridge", "noise_range", "noise_bearing", "noise_velocity", "noise_move"):
            _check_float(name, getattr(self, name), positive=False)
        _check_float("forget", self.forget, positive=True)
        if self.forget > 1.0:
            raise ValueError(f"forget must be in (0, 1], got {self.forget}")
        if not (isinstance(self.sensing_range, (int, float)) and self.sensing_range > 0
                and not math.isnan(self.sensing_range)):
            raise ValueError(f"sensing_range must be positive (inf allowed), got {self.sensing_range!r}")
        for name in ("online", "affine", "gps"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.estimator == "edmd" and self.dictionary in GPS_DICTIONARIES and not self.gps:
            raise ValueError(f"dictionary {self.dictionary!r} uses absolute positions: enable gps")
        if self.leader_start is not None:
            if len(self.leader_start) != 4:
                raise ValueError(f"leader_start must be X,Y,VX,VY, got {self.leader_start!r}")
            for i, x in enumerate(self.leader_start):
                _check_float(f"leader_start[{i}]", x, positive=False, signed=True)
            if self.leader_start[2] == 0 and self.leader_start[3] == 0:
                raise ValueError("leader_start velocity must not be zero")
            object.__setattr__(self, "leader_start", tuple(float(x) for x in self.leader_start))
        if not isinstance(self.surface_params, dict):
            raise ValueError("surface_params must be a table of numbers")
        for key, value in self.surface_params.items():
            _check_float(f"surface_params.{key}", value, positive=False, signed=True)

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
    gps: bool
    mode: str
    time_scale: float
    agent_timeout: float
    start_timeout: float

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
    if "leader_start" in data and data["leader_start"] is not None:
        data["leader_start"] = tuple(data["leader_start"])
    return RunConfig(**data)


def load_config(path: str | os.PathLike[str]) -> RunConfig:
    """Read a TOML run configuration; errors name the file and the problem."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ValueError(f"config file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config file {path} is not valid TOML: {exc}") from None
    data.pop("meta", None)
    try:
        return config_from_dict(data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"config file {path}: {exc}") from None


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
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {value!r}")


def _check_int(name: str, value: Any, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


def _check_float(name: str, value: Any, *, positive: bool, signed: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    if not positive and not signed and value < 0:
        raise ValueError(f"{name} must be non-negative, got {value!r}")
