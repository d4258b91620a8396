"""Typed messages and the one msgpack codec that validates them (design §8).

Every payload is a msgpack map ``{"v": 1, "type": <name>, "tick": j, ...}``. Each message is a
small frozen dataclass whose fields carry a *kind* (see ``_KINDS``); :func:`decode` refuses a
payload larger than 4 KiB before decoding it, decodes with bounded msgpack lengths and nesting
(:mod:`protocol.limits`), then checks the schema version, the type tag, unknown or missing
fields, every field's type, length and finiteness, and optionally the tick order, and raises
:class:`ProtocolError` with a message naming the problem. Text fields hold printable characters
only, and names (an estimator's) start with a letter and use a small safe alphabet, so nothing
a peer sends can become a control sequence in a log or a formula in a results file. The field
checks (:func:`check_finite`, :func:`check_count`, :func:`check_text`) and the bounded codec
(:func:`pack_bounded`, :func:`unpack_bounded`) serve the observers' payloads
(:mod:`protocol.view`) too. Transport code lives elsewhere (``protocol.session``).

>>> msg = decode(encode(Rod(tick=3, length=3.57, side=1)), Rod)
>>> msg.length
3.57
>>> decode(b"\\x81\\xa1v\\x02", Rod)
Traceback (most recent call last):
...
protocol.messages.ProtocolError: unsupported schema version 2 (this build speaks 1)
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import msgpack

from protocol.limits import (
    MAX_DEPTH,
    MAX_NAME,
    MAX_PAYLOAD_BYTES,
    MAX_TEXT,
    MAX_TICK,
    MAX_VECTOR,
    MSGPACK_BOUNDS,
    NAME_PATTERN,
    NAME_RULE,
)

SCHEMA_VERSION = 1


class ProtocolError(ValueError):
    """A payload that does not follow the protocol; the message names the problem."""


# --- field kinds -------------------------------------------------------------------------------


def check_finite(name: str, value: Any, label: str = "field") -> float:
    """``value`` as a finite float, else a ProtocolError naming ``label`` and ``name``
    (``label`` tells the payload kind: ``"field"`` in a message, ``"view field"`` in a view)."""
    if type(value) is float and math.isfinite(value):  # the common case, checked first
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProtocolError(f"{label} {name!r} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ProtocolError(f"{label} {name!r} must be finite, got {value}")
    return value


def _positive(name: str, value: Any) -> float:
    value = check_finite(name, value)
    if value <= 0:
        raise ProtocolError(f"field {name!r} must be positive, got {value}")
    return value


def _limit(name: str, value: Any) -> float:
    """A bound: a positive number, infinity (unbounded) included."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProtocolError(f"field {name!r} must be a number, got {type(value).__name__}")
    if not value > 0:  # NaN fails too
        raise ProtocolError(f"field {name!r} must be positive (or inf), got {value}")
    return float(value)


def check_count(name: str, value: Any, label: str = "field") -> int:
    """``value`` as an integer in [0, ``MAX_TICK``] (a tick, a count, an index), else a
    ProtocolError naming ``label`` and ``name``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError(f"{label} {name!r} must be an integer, got {type(value).__name__}")
    if not 0 <= value <= MAX_TICK:
        raise ProtocolError(f"{label} {name!r} must be in [0, {MAX_TICK}], got {value}")
    return value


def _side(name: str, value: Any) -> int:
    if isinstance(value, bool) or value not in (1, -1):
        raise ProtocolError(f"field {name!r} must be 1 or -1, got {value!r}")
    return int(value)


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise ProtocolError(f"field {name!r} must be a boolean, got {type(value).__name__}")
    return value


def check_text(name: str, value: Any, label: str = "field", limit: int = MAX_TEXT) -> str:
    """``value`` as a string of at most ``limit`` printable characters, else a ProtocolError
    naming ``label`` and ``name``."""
    if not isinstance(value, str):
        raise ProtocolError(f"{label} {name!r} must be a string, got {type(value).__name__}")
    if len(value) > limit:
        raise ProtocolError(f"{label} {name!r} is longer than {limit} characters")
    if not value.isprintable():
        raise ProtocolError(f"{label} {name!r} holds a control or non-printable character")
    return value


def _name(name: str, value: Any) -> str:
    if not isinstance(value, str):
        raise ProtocolError(f"field {name!r} must be a string, got {type(value).__name__}")
    if not NAME_PATTERN.fullmatch(value):
        raise ProtocolError(f"field {name!r} must be {NAME_RULE}, got {value[:MAX_NAME]!r}")
    return value


def _vector(length: int | None):
    def check(name: str, value: Any) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)):
            raise ProtocolError(f"field {name!r} must be a list, got {type(value).__name__}")
        if length is not None and len(value) != length:
            raise ProtocolError(f"field {name!r} must have length {length}, got {len(value)}")
        if len(value) > MAX_VECTOR:
            raise ProtocolError(f"field {name!r} is longer than {MAX_VECTOR}")
        for x in value:  # fast path: plain finite floats
            if type(x) is not float or not math.isfinite(x):
                return tuple(check_finite(f"{name}[{i}]", x) for i, x in enumerate(value))
        return tuple(value)

    return check


def _optional(check):
    def optional(name: str, value: Any):
        return None if value is None else check(name, value)

    return optional


def _choice(*allowed: str):
    def check(name: str, value: Any) -> str:
        if value not in allowed:
            raise ProtocolError(f"field {name!r} must be one of {allowed}, got {value!r}")
        return value

    return check


_KINDS = {
    "finite": check_finite,
    "positive": _positive,
    "count": check_count,
    "side": _side,
    "flag": _flag,
    "text": check_text,
    "name": _name,
    "finite?": _optional(check_finite),
    "limit?": _optional(_limit),
    "vec2": _vector(2),
    "vec2?": _optional(_vector(2)),
    "vec3?": _optional(_vector(3)),
    "vec?": _optional(_vector(None)),
    "error-code": _choice("bad-request", "missed", "ended", "wait", "stale"),
}


def _kind(name: str, default: Any = ..., optional: bool = False, compare: bool = True) -> Any:
    """A message field of kind ``name`` (a key of the checks), with ``default`` if given;
    ``optional``: a decoder fills in the default when a sender omits the field; ``compare``:
    whether the field counts when two messages are compared (``==``)."""
    if name not in _KINDS:
        raise ValueError(f"unknown field kind {name!r}")
    metadata = {"kind": name, "optional": True} if optional else {"kind": name}
    if default is ...:
        return field(metadata=metadata, compare=compare)
    return field(default=default, metadata=metadata, compare=compare)


# --- messages ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Message:
    """Base of all messages: the tick they belong to."""

    TYPE: ClassVar[str] = ""
    tick: int = _kind("count")


@dataclass(frozen=True)
class TickStart(Message):
    """``world/tick``: tick j starts at time t."""

    TYPE: ClassVar[str] = "tick"
    t: float = _kind("finite", 0.0)


@dataclass(frozen=True)
class Request(Message):
    """Base of an agent's requests to the world (:class:`SenseRequest` and the actions).

    ``epoch`` is the number of the agent's latest join (:attr:`Joined.epoch`): a request sent
    before a join that reaches the world after it (it was in flight when the session was cut)
    carries an older one, and the world refuses it unread with code ``stale`` (design §8).
    0, the default, is an unnumbered request (optional on the wire: older senders omit it),
    which the world takes as it comes. Two requests that differ only in their epoch are equal
    (``==``): a tick redone after a join repeats the undone attempt's requests (design §5)."""

    epoch: int = _kind("count", 0, optional=True, compare=False)


@dataclass(frozen=True)
class SenseRequest(Request):
    """Query to ``world/sense/<id>``: the follower's pre-move sensing at ``tick``, served once,
    before any action (the readings after its move and after it settled are the replies to
    those actions, :class:`ActSensing`; design §5). ``look``: it looks for its rod end from
    where it stands (the reading then carries it, if in range, and the distance counts in the
    tick's required range; always in an initial tick)."""

    TYPE: ClassVar[str] = "sense"
    look: bool = _kind("flag", False)


@dataclass(frozen=True)
class Sensing(Message):
    """Reply of ``world/sense/<id>``; every vector is xy in the agent's local frame (§5).

    ``r``/``theta``: Euclidean distance and bearing (rad, wrapped to (-pi, pi]) to the leader.
    ``rod``: offset to the leader's rod end, read by the same range/bearing sensor (its own
    noise draws) when the follower looks for it (after its move, when settled, before moving if
    it asks), or None: it did not look, or the rod end is beyond the sensing range.
    ``velocity``: odometry of the last completed interval (None before one exists).
    ``oracle_velocity``: the velocity to the next ideal position, the paper's idealisation
    (only to dictionary c with ``velocity = "oracle"``; with velocity noise).
    ``gps``/``leader_gps``: absolute (x, y, z) of agent and leader (only with GPS enabled;
    with GPS noise).
    ``compass``, ``slope``, ``odometry`` (``--motion drive`` only; optional on the wire): the
    robot's compass heading (rad, the angle of its heading in the local frame), the slope of
    the ground under it read by its tilt sensor (``(∂F/∂x, ∂F/∂y)`` in the local frame), and
    in the reply to a :class:`Control` the displacement its odometry measured over that
    control step (xy, local frame). Every field passes through its noise channel (design §5).
    ``shared_heading`` (``--motion drive``, optional on the wire): what the leader told of its
    own heading when it settled at this tick (:class:`Snap`'s ``heading``), relayed as it was
    sent: no reading of the world's, so no noise of the world's; None when the leader told
    nothing (the column's leader, a teleporting run, a missed tick).
    """

    TYPE: ClassVar[str] = "sensing"
    r: float = _kind("finite", 0.0)
    theta: float = _kind("finite", 0.0)
    rod: tuple[float, float] | None = _kind("vec2?", None)
    velocity: tuple[float, float] | None = _kind("vec2?", None)
    oracle_velocity: tuple[float, float] | None = _kind("vec2?", None)
    gps: tuple[float, float, float] | None = _kind("vec3?", None)
    leader_gps: tuple[float, float, float] | None = _kind("vec3?", None)
    compass: float | None = _kind("finite?", None, optional=True)
    slope: tuple[float, float] | None = _kind("vec2?", None, optional=True)
    odometry: tuple[float, float] | None = _kind("vec2?", None, optional=True)
    shared_heading: tuple[float, float] | None = _kind("vec2?", None, optional=True)


@dataclass(frozen=True)
class Drive(Request):
    """Query to ``world/act/0``: the leader follows its geodesic to time ``t``; the reply is
    :class:`ActResult`."""

    TYPE: ClassVar[str] = "drive"
    t: float = _kind("finite", 0.0)


@dataclass(frozen=True)
class Move(Request):
    """Query to ``world/act/<id>`` (followers): move by the xy ``offset`` in the local frame,
    keeping the heading; the reply is :class:`ActSensing` with the ``moved`` sensing."""

    TYPE: ClassVar[str] = "move"
    offset: tuple[float, float] = _kind("vec2", (0.0, 0.0))


@dataclass(frozen=True)
class Snap(Request):
    """Query to ``world/act/<id>`` (followers): move onto the leader's rod end if it is visible
    and take the §3 heading; the reply is :class:`ActSensing` with the ``settled`` sensing.
    With ``--motion drive`` it ends the tick instead: the follower settles where its control
    steps took it, with its own heading; ``heading`` (optional on the wire) is then what it
    tells its successor of that heading: ``(angle, variance)``, its own estimate (chart angle,
    rad, local frame) and that estimate's variance (rad²), which the world relays to the
    successor with its pre-move and settled readings of the tick (``Sensing.shared_heading``,
    design §5)."""

    TYPE: ClassVar[str] = "snap"
    heading: tuple[float, float] | None = _kind("vec2?", None, optional=True)


@dataclass(frozen=True)
class Control(Request):
    """Query to ``world/act/<id>`` (followers, ``--motion drive``): drive at forward speed
    ``speed`` (v: m of arc per time unit along the surface, negative reversing) turning at
    ``turn`` (ω: rad per time unit, in the metric, positive to the left) for control step
    ``step`` of the
    tick (steps ``0 … control_steps-1`` drive to the estimate, the next ``snap_steps`` onto
    the rod end). ``goal`` is given with step 0 only: where the move phase is heading, as an
    offset (local frame) from where the follower stood when the tick began (the world records
    it as the estimate and measures the shortfall against it, design §7). The reply is
    :class:`ActSensing` with the sensing after the step, its ``odometry`` included. A
    :class:`Snap` after the last step settles the follower where it stands."""

    TYPE: ClassVar[str] = "control"
    step: int = _kind("count", 0)
    speed: float = _kind("finite", 0.0)
    turn: float = _kind("finite", 0.0)
    goal: tuple[float, float] | None = _kind("vec2?", None)


ACTIONS = (Drive, Move, Snap, Control)
"""The typed requests of ``world/act/<id>`` (besides :class:`JoinRequest`)."""


@dataclass(frozen=True)
class JoinRequest(Message):
    """Query to ``world/act/<id>`` when an agent process starts: where does the run stand?

    ``tick`` is ignored (0); the reply is :class:`Joined`.
    """

    TYPE: ClassVar[str] = "join"


@dataclass(frozen=True)
class Joined(Message):
    """Reply to :class:`JoinRequest`: this agent is at ``tick``; ``settled``: the world has it
    through that tick (its rod, or a miss, is recorded; then ``tick`` is the world's newest);
    else it must do ``tick`` next (whatever it did later is not recorded: it redoes it);
    ``ready``: it may act at ``tick`` now, and at every tick up to ``until`` (they have started
    and, for a follower, its predecessor is through them); ``world``: the newest tick the world
    started; ``start``: the run's start nonce, which the agent's state file must carry;
    ``max_speed``: a ``--motion drive`` run's top speed as the world resolved it (its default
    is twice the leader's speed on the hidden surface, which no agent can work out), else
    None (optional on the wire); ``epoch``: the number of this join (1 for an agent's first,
    counted by the world), which the agent's requests carry until it joins again
    (:attr:`Request.epoch`; optional on the wire, 0 from an older world: unnumbered)."""

    TYPE: ClassVar[str] = "joined"
    settled: bool = _kind("flag", False)
    ready: bool = _kind("flag", False)
    until: int = _kind("count", 0)
    world: int = _kind("count", 0)
    start: str = _kind("text", "")
    max_speed: float | None = _kind("limit?", None, optional=True)
    epoch: int = _kind("count", 0, optional=True)

    @property
    def through(self) -> int:
        """The last tick the world has this agent through (-1: none yet)."""
        return self.tick if self.settled else self.tick - 1


@dataclass(frozen=True)
class ActResult(Message):
    """Reply of ``world/act/0`` to :class:`Drive`: the leader is at its new pose."""

    TYPE: ClassVar[str] = "acted"
    moved: bool = _kind("flag", True)


@dataclass(frozen=True)
class ActSensing(Sensing):
    """Reply of ``world/act/<id>`` to :class:`Move`, :class:`Control` and :class:`Snap`: the
    sensing right after the action (after a move or a control step, or settled after a snap:
    each a reading of its own, design §5, §8), so a follower tick needs at most three round trips
    (with ``--motion drive``, two more than its control steps). ``moved`` is False when a
    snap found no visible rod end (a lost tick)."""

    TYPE: ClassVar[str] = "acted-sensing"
    moved: bool = _kind("flag", True)

    @property
    def sensing(self) -> Sensing:
        """The sensing fields alone, without ``moved``."""
        return Sensing(**{f.name: getattr(self, f.name) for f in fields(Sensing)})


@dataclass(frozen=True)
class Rod(Message):
    """``agent/<id>/rod``: the agent settled at ``tick`` and holds its rod out."""

    TYPE: ClassVar[str] = "rod"
    length: float = _kind("positive", 1.0)
    side: int = _kind("side", 1)


@dataclass(frozen=True)
class Observation(Message):
    """``agent/<id>/obs``: the agent's settled measurement and what it had predicted for it.

    ``followed`` names the policy whose estimate was followed (``auto``'s candidate, or
    ``persist`` on a fallback); ``fallback`` is true when the estimator could not predict yet
    and ``persist`` stood in. Both are optional on the wire (older senders omit them).
    """

    TYPE: ClassVar[str] = "obs"
    estimator: str = _kind("name", "policy")
    measurement: tuple[float, ...] | None = _kind("vec?", None)
    prediction: tuple[float, ...] | None = _kind("vec?", None)
    lost: bool = _kind("flag", False)
    followed: str = _kind("text", "", optional=True)
    fallback: bool = _kind("flag", False, optional=True)


@dataclass(frozen=True)
class Missed(Message):
    """``world/missed``: agent ``agent`` did not settle at ``tick``; it keeps its pose, and the
    agent behind it goes on from where it stands."""

    TYPE: ClassVar[str] = "missed"
    agent: int = _kind("count", 0)


@dataclass(frozen=True)
class Done(Message):
    """``world/done``: the run ended; ``results`` is the results folder."""

    TYPE: ClassVar[str] = "done"
    results: str = _kind("text", "")
    complete: bool = _kind("flag", True)
    reason: str = _kind("text", "")


@dataclass(frozen=True)
class ErrorReply(Message):
    """Error reply of a queryable: ``error`` names the problem; ``code`` classifies it
    (``bad-request``, ``missed``: the agent missed this tick, ``ended``: the run is over,
    ``wait``: not yet, ask again shortly, ``stale``: the request was sent before the agent's
    latest join and was not read; :attr:`Request.epoch`)."""

    TYPE: ClassVar[str] = "error"
    error: str = _kind("text", "")
    code: str = _kind("error-code", "bad-request")


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (TickStart, SenseRequest, Sensing, Drive, Move, Snap, JoinRequest, Joined,
                ActResult, ActSensing, Rod, Observation, Missed, Done, ErrorReply, Control)
}


# --- codec -------------------------------------------------------------------------------------


def encode(msg: Message, *, check: bool = True) -> bytes:
    """Serialise ``msg`` to msgpack, validating it first (a bad message is never sent).

    ``check=False`` skips that sender-side check, for hot paths whose receiver decodes with
    full validation anyway (the world's sensing replies). A message over the size limit is
    refused either way.
    """
    if not isinstance(msg, Message) or type(msg) not in MESSAGE_TYPES.values():
        raise ProtocolError(f"cannot encode {type(msg).__name__}: not a protocol message")
    body: dict[str, Any] = {"v": SCHEMA_VERSION, "type": msg.TYPE}
    for name, _ in _spec(type(msg))[0]:
        value = getattr(msg, name)
        body[name] = list(value) if isinstance(value, tuple) else value
    if check:
        _validate(type(msg), body)
    return pack_bounded(body, MAX_PAYLOAD_BYTES, msg.TYPE)


def pack_bounded(body: dict[str, Any], max_bytes: int, kind: str) -> bytes:
    """``body`` as msgpack, refused (ProtocolError naming ``kind``) when over ``max_bytes``:
    every receiver would refuse it."""
    data = msgpack.packb(body, use_bin_type=True)
    if len(data) > max_bytes:
        raise ProtocolError(f"{kind}: encodes to {len(data)} bytes, over the "
                            f"{max_bytes}-byte limit")
    return data


def decode(
    data: bytes | bytearray | memoryview | Any,
    expected: type[Message] | tuple[type[Message], ...],
    *,
    min_tick: int | None = None,
) -> Message:
    """Parse and validate a payload.

    Parameters
    ----------
    data : bytes-like
        The msgpack payload (bytes, or anything with ``len`` that ``bytes()`` accepts, such as
        a ``zenoh.ZBytes``: its size is checked before it is copied).
    expected : Message subclass or tuple of them
        The message type(s) this channel carries.
    min_tick : int, optional
        Reject a message whose tick is lower (tick monotonicity on a channel).

    Raises
    ------
    ProtocolError
        With a message naming the problem. A payload over ``MAX_PAYLOAD_BYTES`` is refused
        without being decoded, so a huge one costs no more than its length.
    """
    body = unpack_bounded(data, MAX_PAYLOAD_BYTES, MSGPACK_BOUNDS, MAX_DEPTH)
    version = body.get("v")
    if version != SCHEMA_VERSION:
        raise ProtocolError(
            f"unsupported schema version {version!r} (this build speaks {SCHEMA_VERSION})"
        )
    allowed = expected if isinstance(expected, tuple) else (expected,)
    tag = body.get("type")
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls not in allowed:
        names = ", ".join(repr(c.TYPE) for c in allowed)
        raise ProtocolError(f"message type {str(tag)[:40]!r} not accepted here (want {names})")
    values = _validate(cls, body)
    if min_tick is not None and values["tick"] < min_tick:
        raise ProtocolError(f"tick {values['tick']} is older than tick {min_tick} already seen")
    return cls(**values)


def unpack_bounded(data: bytes | bytearray | memoryview | Any, max_bytes: int,
                   bounds: dict[str, int], max_depth: int, what: str = "payload") -> dict:
    """Decode a peer's msgpack map within bounds (the messages' and the view payloads').

    A payload over ``max_bytes`` is refused before it is copied or decoded; msgpack decodes it
    with the length ``bounds`` (keyword arguments of ``msgpack.unpackb``), and a map nested
    deeper than ``max_depth`` is refused. Every refusal is a ProtocolError starting with
    ``what``.
    """
    size = len(data)
    if size > max_bytes:
        raise ProtocolError(f"{what} of {size} bytes refused: the limit is {max_bytes}")
    try:
        body = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, **bounds)
    except msgpack.StackError:
        raise ProtocolError(f"{what} nests deeper than {max_depth} levels") from None
    except ValueError as exc:  # msgpack's bound checks and format errors (many subclasses)
        raise ProtocolError(_unpack_problem(exc, bounds, what)) from None
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise ProtocolError(f"{what} is not valid msgpack ({type(exc).__name__})") from None
    if not isinstance(body, dict):
        raise ProtocolError(f"{what} must be a msgpack map, got {type(body).__name__}")
    _check_depth(body, max_depth, what)
    return body


def _unpack_problem(exc: ValueError, bounds: dict[str, int], what: str) -> str:
    """One line for a msgpack refusal: a length over a bound, or malformed bytes."""
    text = str(exc)
    for bound, limit in bounds.items():
        if bound in text:
            kind = bound.removeprefix("max_").removesuffix("_len")
            return f"{what} exceeds the protocol's {kind} length bound ({limit})"
    detail = text.removeprefix("Unpack failed: ")[:60] or type(exc).__name__
    return f"{what} is not valid msgpack ({detail})"


def _check_depth(body: dict, max_depth: int, what: str) -> None:
    """Refuse containers nested deeper than ``max_depth`` (the map itself is level 1).

    msgpack builds plain lists and dicts only, hence the exact type tests (the fast path).
    """
    level, inner = 1, [v for v in body.values() if type(v) is list or type(v) is dict]
    while inner:
        if level == max_depth:
            raise ProtocolError(f"{what} nests deeper than {max_depth} levels")
        level += 1
        inner = [x for c in inner for x in (c.values() if type(c) is dict else c)
                 if type(x) is list or type(x) is dict]


@functools.cache
def _spec(cls: type[Message]) -> tuple[tuple[tuple[str, Any], ...], frozenset[str], dict[str, Any]]:
    """Per message class: (field name, checker) pairs, the set of allowed keys, and the
    defaults of the optional fields (which an older sender may omit)."""
    pairs = tuple((f.name, _KINDS[f.metadata["kind"]]) for f in fields(cls))
    optional = {f.name: f.default for f in fields(cls) if f.metadata.get("optional")}
    return pairs, frozenset(name for name, _ in pairs) | {"v", "type"}, optional


def _validate(cls: type[Message], body: dict[str, Any]) -> dict[str, Any]:
    pairs, allowed, optional = _spec(cls)
    if not allowed.issuperset(body):
        unknown = set(body) - allowed
        raise ProtocolError(f"{cls.TYPE}: unknown field(s) {sorted(map(str, unknown))}")
    values = {}
    for name, check in pairs:
        if name not in body and name in optional:
            values[name] = optional[name]
            continue
        if name not in body:
            raise ProtocolError(f"{cls.TYPE}: missing field {name!r}")
        values[name] = check(name, body[name])
    return values


def safe_text(text: str) -> str:
    """``text`` made fit for a text field: non-printable characters replaced by ``?`` and
    clipped to ``MAX_TEXT`` characters (for messages built from exceptions or peer input)."""
    return "".join(c if c.isprintable() else "?" for c in str(text)[:MAX_TEXT])


def error_payload(tick: int, problem: str, code: str = "bad-request") -> bytes:
    """An encoded :class:`ErrorReply` (tick clamped and text made safe so it always encodes)."""
    tick = tick if isinstance(tick, int) and 0 <= tick <= MAX_TICK else 0
    return encode(ErrorReply(tick=tick, error=safe_text(problem), code=code))


def to_body(msg: Message, *, check: bool = True) -> dict[str, Any]:
    """``msg`` as the plain map the codec sends (JSON-ready: lists, floats, str, bool, None);
    ``check=False`` as for :func:`encode` (a message already decoded with full validation)."""
    return msgpack.unpackb(encode(msg, check=check), raw=False)


def from_body(body: Any, expected: type[Message]) -> Message:
    """The message of a plain map made by :func:`to_body`, validated like :func:`decode`."""
    if not isinstance(body, dict):
        raise ProtocolError(f"expected a map, got {type(body).__name__}")
    return decode(msgpack.packb(body, use_bin_type=True), expected)
