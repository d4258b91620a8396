"""ROS 2 naming on Zenoh, as rmw_zenoh writes it (design §10): the one owner of every key
expression, liveliness token, QoS string, GID and attachment this project shows ROS 2.

The layout follows ``rmw_zenoh_cpp`` of ROS 2 Jazzy, release 0.2.5 (jazzy branch, June 2025;
``docs/design.md``, ``src/detail/liveliness_utils.cpp``, ``attachment_helpers.cpp``,
``rmw_publisher_data.cpp``, ``qos.cpp``):

- **data key** ``<domain>/<topic without its leading and trailing '/'>/<dds type>/<hash>``,
  e.g. ``0/swarm/agent_1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3…``; the
  DDS type name of ``pkg/msg/Type`` is ``pkg::msg::dds_::Type_``, the hash the RIHS01 type
  hash of the message definition;
- **liveliness tokens** ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node name>[/<topic>/<dds type>/<hash>/<qos>]``, kind ``NN`` (node; its entity
  id is its node id) or ``MP`` (publisher), every ``/`` inside a name (enclave ``/``,
  namespace ``/``, the topic) replaced by ``%``; the zid is the session id as Zenoh prints it;
- **QoS** ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
  <liveliness>,<lease s>,<ns>``, each field empty where it equals rmw_zenoh's default
  (reliable, volatile, keep last, depth 42, infinite durations, automatic liveliness), the
  numbers being the ``rmw/types.h`` enum values: depth 10 otherwise default is ``::,10:,:,:,,``;
- **GID** of an entity: XXH3-128 of its liveliness token, low 64 bits then high 64 bits, each
  little-endian (16 bytes; ``xxhash``, the ``[ros]`` extra);
- **attachment** of every sample (0.2.4 and later, "Change serialization format in
  attachment_helpers.cpp"): zenoh-ext serialisation of ``int64 sequence number`` (per
  publisher, from 1), ``int64 source timestamp`` (ns since the Unix epoch) and the GID as
  ``std::array<uint8_t, 16>`` (a sequence: LEB128 length 16, then the bytes): 33 bytes,
  ``<q q B 16s`` with the length byte ``0x10``;
- **payload**: CDR with its 4-byte encapsulation header (``rosbags``' ``serialize_cdr``).

Types, CDR and hashes come from ``rosbags``, the GID's XXH3 from ``xxhash`` (both the ``[ros]``
extra), imported only where they are needed (:func:`typestore`, :func:`gid`).
"""
from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache

from protocol.distribution import needs

ADMIN_SPACE = "@ros2_lv"
DOMAIN_RANGE = (0, 232)
DOMAIN_ENV = "ROS_DOMAIN_ID"
NODE_NAME = "swarm_world"
NAMESPACE = "/"
ENCLAVE = "/"
FRAME = "map"
NODE_KIND, PUBLISHER_KIND = "NN", "MP"
ENTITY_KINDS = (NODE_KIND, PUBLISHER_KIND, "MS", "SS", "SC")  # ... subscription, service, client
GID_SIZE = 16
ATTACHMENT = struct.Struct("<qqB16s")
_SLASH = "%"

# rmw/types.h enum values
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1
DURATION_INFINITE = (9223372036, 854775807)  # RMW_DURATION_INFINITE as (s, ns)


@dataclass(frozen=True)
class Qos:
    """The QoS fields a liveliness token carries (durations as (s, ns); None = infinite)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10
    deadline: tuple[int, int] | None = None
    lifespan: tuple[int, int] | None = None
    liveliness: int = AUTOMATIC
    lease: tuple[int, int] | None = None


RMW_ZENOH_DEFAULT = Qos(depth=42)
"""rmw_zenoh's default profile (``qos.cpp``): fields equal to it are left empty in a token."""
PUBLISHER_QOS = Qos()
"""What the world's publishers offer: reliable, volatile, keep last 10 (rclcpp's default)."""


def qos_keyexpr(qos: Qos) -> str:
    """The QoS chunk of a token (``qos_to_keyexpr``).

    >>> qos_keyexpr(Qos(depth=7))
    '::,7:,:,:,,'
    >>> qos_keyexpr(Qos(reliability=BEST_EFFORT, durability=TRANSIENT_LOCAL, depth=42))
    '2:1:,:,:,:,,'
    """
    d = RMW_ZENOH_DEFAULT

    def field(value, default) -> str:
        return "" if value == default else str(value)

    def duration(value, default) -> str:
        sec, nsec = value or (None, None)
        dsec, dnsec = default or (None, None)
        return f"{field(sec, dsec)},{field(nsec, dnsec)}"

    return ":".join([
        field(qos.reliability, d.reliability), field(qos.durability, d.durability),
        f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}",
        duration(qos.deadline, d.deadline), duration(qos.lifespan, d.lifespan),
        f"{field(qos.liveliness, d.liveliness)},{duration(qos.lease, d.lease)}",
    ])


def parse_qos(text: str) -> Qos:
    """Inverse of :func:`qos_keyexpr` (ValueError on a malformed chunk)."""
    parts = text.split(":")
    if len(parts) != 6:
        raise ValueError(f"QoS chunk must have 6 ':'-separated fields, got {text!r}")
    d = RMW_ZENOH_DEFAULT
    pieces = [p.split(",") for p in parts[2:]]
    if [len(p) for p in pieces] != [2, 2, 2, 3]:
        raise ValueError(f"malformed QoS chunk {text!r}")

    def number(value: str, default):
        if value == "":
            return default
        if not value.isdigit():
            raise ValueError(f"malformed QoS number {value!r} in {text!r}")
        return int(value)

    def duration(sec: str, nsec: str, default):
        if sec == nsec == "":
            return default
        return (number(sec, None), number(nsec, None))

    history, deadline, lifespan, live = pieces
    return Qos(reliability=number(parts[0], d.reliability),
               durability=number(parts[1], d.durability),
               history=number(history[0], d.history), depth=number(history[1], d.depth),
               deadline=duration(*deadline, d.deadline), lifespan=duration(*lifespan, d.lifespan),
               liveliness=number(live[0], d.liveliness), lease=duration(*live[1:], d.lease))


def check_domain(domain: int, name: str = "ros_domain") -> int:
    """``domain`` if it is a ROS 2 domain id (an integer in 0–232), else ValueError."""
    low, high = DOMAIN_RANGE
    if isinstance(domain, bool) or not isinstance(domain, int) or not low <= domain <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {domain!r}")
    return domain


def domain_from_env(environ: Mapping[str, str] = os.environ) -> int:
    """The domain id ``ROS_DOMAIN_ID`` names, 0 if it is unset or empty (ValueError if bad)."""
    text = environ.get(DOMAIN_ENV, "").strip()
    if not text:
        return 0
    try:
        value = int(text, 10)
    except ValueError:
        raise ValueError(f"{DOMAIN_ENV} must be an integer in [{DOMAIN_RANGE[0]}, "
                         f"{DOMAIN_RANGE[1]}], got {text!r}") from None
    return check_domain(value, DOMAIN_ENV)


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` becomes ``%`` (``mangle_name``)."""
    return name.replace("/", _SLASH)


def demangle(chunk: str) -> str:
    return chunk.replace(_SLASH, "/")


def dds_type(msgtype: str) -> str:
    """``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_`` (the type name in keys and tokens).

    >>> dds_type("geometry_msgs/msg/PoseStamped")
    'geometry_msgs::msg::dds_::PoseStamped_'
    """
    package, kind, name = _split_type(msgtype)
    return f"{package}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """Inverse of :func:`dds_type`."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise ValueError(f"not a DDS type name: {dds!r}")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _split_type(msgtype: str) -> tuple[str, str, str]:
    parts = msgtype.split("/") if isinstance(msgtype, str) else []
    if len(parts) != 3 or not all(p.isidentifier() for p in parts):
        raise ValueError(f"message type must be 'package/msg/Name', got {msgtype!r}")
    return parts[0], parts[1], parts[2]


def check_topic(topic: str) -> str:
    """``topic`` if it is an absolute ROS 2 topic name (``/a/b_c``), else ValueError."""
    chunks = topic.split("/") if isinstance(topic, str) else []
    if (len(chunks) < 2 or chunks[0] != ""
            or not all(c and (c[0].isalpha() or c[0] == "_") and c.replace("_", "a").isalnum()
                       and c.isascii() for c in chunks[1:])):
        raise ValueError(f"topic must be an absolute ROS 2 name like /a/b, got {topic!r}")
    return topic


def topic_key(domain: int, topic: str, msgtype: str, type_hash: str) -> str:
    """The Zenoh key a ROS 2 topic's samples travel on (``TopicInfo::topic_keyexpr_``).

    >>> topic_key(0, "/chatter", "std_msgs/msg/String", "RIHS01_ab")
    '0/chatter/std_msgs::msg::dds_::String_/RIHS01_ab'
    """
    return (f"{check_domain(domain)}/{check_topic(topic).strip('/')}/{dds_type(msgtype)}/"
            f"{type_hash}")


def node_token(domain: int, zid: str, node_id: int, name: str = NODE_NAME,
               namespace: str = NAMESPACE, enclave: str = ENCLAVE) -> str:
    """A node's liveliness token (its entity id is its node id)."""
    return "/".join([ADMIN_SPACE, str(check_domain(domain)), zid, str(node_id), str(node_id),
                     NODE_KIND, mangle(enclave), mangle(namespace), mangle(name)])


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, topic: str,
                    msgtype: str, type_hash: str, qos: Qos = PUBLISHER_QOS,
                    name: str = NODE_NAME, namespace: str = NAMESPACE,
                    enclave: str = ENCLAVE) -> str:
    """A publisher's liveliness token."""
    return "/".join([ADMIN_SPACE, str(check_domain(domain)), zid, str(node_id), str(entity_id),
                     PUBLISHER_KIND, mangle(enclave), mangle(namespace), mangle(name),
                     mangle(check_topic(topic)), dds_type(msgtype), type_hash,
                     qos_keyexpr(qos)])


@dataclass(frozen=True)
class Entity:
    """What a liveliness token says (``Entity::make(keyexpr)``); topic fields None for a node."""

    domain: int
    zid: str
    node_id: int
    entity_id: int
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str | None = None
    msgtype: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None


def parse_token(token: str) -> Entity:
    """The entity a liveliness token describes (ValueError if it is not one)."""
    parts = token.split("/")
    if len(parts) not in (9, 13) or parts[0] != ADMIN_SPACE or not all(parts):
        raise ValueError(f"not an rmw_zenoh liveliness token: {token!r}")
    kind = parts[5]
    if (kind == NODE_KIND) != (len(parts) == 9) or kind not in ENTITY_KINDS:
        raise ValueError(f"liveliness token with kind {kind!r} and {len(parts)} parts")
    for i in (1, 3, 4):
        if not parts[i].isdigit():
            raise ValueError(f"liveliness token part {i} must be a number: {token!r}")
    topic = {}
    if len(parts) == 13:
        topic = {"topic": demangle(parts[9]), "msgtype": ros_type(parts[10]),
                 "type_hash": parts[11], "qos": parse_qos(parts[12])}
    return Entity(domain=int(parts[1]), zid=parts[2], node_id=int(parts[3]),
                  entity_id=int(parts[4]), kind=kind, enclave=demangle(parts[6]),
                  namespace=demangle(parts[7]), node=demangle(parts[8]), **topic)


def gid(token: str) -> bytes:
    """An entity's 16-byte GID: XXH3-128 (seed 0) of its token, low then high half, each
    little-endian: the 128-bit value as 16 little-endian bytes (:mod:`xxhash`, the ``[ros]``
    extra: :class:`protocol.distribution.MissingExtra` without it)."""
    with needs("ros"):
        import xxhash
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(sequence_number: int, source_timestamp: int, source_gid: bytes) -> bytes:
    """The 33-byte attachment of one sample (see the module docstring)."""
    if len(source_gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(source_gid)}")
    return ATTACHMENT.pack(sequence_number, source_timestamp, GID_SIZE, bytes(source_gid))


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source timestamp, GID)`` of an attachment (ValueError if malformed)."""
    data = bytes(data)
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"an attachment has {ATTACHMENT.size} bytes, got {len(data)}")
    sequence, stamp, length, source = ATTACHMENT.unpack(data)
    if length != GID_SIZE:
        raise ValueError(f"attachment GID length byte is {length}, expected {GID_SIZE}")
    return sequence, stamp, source


# --- the run's topics (design §10) --------------------------------------------------------------

CLOCK = ("/clock", "rosgraph_msgs/msg/Clock")
TF = ("/tf", "tf2_msgs/msg/TFMessage")
MARKERS = ("/swarm/markers", "visualization_msgs/msg/MarkerArray")
DIAGNOSTICS = ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
"""Every follower's formation health, one ``DiagnosticStatus`` each (docs/ros2.md): on the
topic ROS 2's diagnostic tools (the aggregator, rqt's monitors, Foxglove's panels) read."""
AGENT_TOPICS = {  # per agent: name -> (type, leader too)
    "pose": ("geometry_msgs/msg/PoseStamped", True),
    "path": ("nav_msgs/msg/Path", True),
    "ideal": ("geometry_msgs/msg/PointStamped", False),
    "estimate": ("geometry_msgs/msg/PointStamped", False),
    "required_range": ("std_msgs/msg/Float64", False),
    "cmd_vel": ("geometry_msgs/msg/Twist", False),
}
DRIVE_TOPICS = ("cmd_vel",)
"""Per-agent topics of driving followers only (``--motion drive``): the world's other runs
neither publish nor declare them."""


def agent_topic(agent: int, name: str) -> str:
    """``/swarm/agent_<k>/<name>``."""
    if isinstance(agent, bool) or not isinstance(agent, int) or agent < 0:
        raise ValueError(f"agent id must be a non-negative integer, got {agent!r}")
    if name not in AGENT_TOPICS:
        raise ValueError(f"unknown agent topic {name!r} (one of {', '.join(AGENT_TOPICS)})")
    return f"/swarm/agent_{agent}/{name}"


def run_topics(followers: int, drive: bool = False) -> list[tuple[str, str]]:
    """Every ``(topic, type)`` of a run with ``followers`` followers, in a fixed order (the
    order of the world's publisher entity ids). ``drive`` (driving followers) appends each
    follower's :data:`DRIVE_TOPICS` after all the others, so the other entity ids are those
    of a teleport run."""
    if isinstance(followers, bool) or not isinstance(followers, int) or followers < 0:
        raise ValueError(f"followers must be a non-negative integer, got {followers!r}")
    topics = [CLOCK, TF, MARKERS, DIAGNOSTICS]
    for k in range(followers + 1):
        topics += [(agent_topic(k, name), msgtype)
                   for name, (msgtype, leader) in AGENT_TOPICS.items()
                   if (k > 0 or leader) and name not in DRIVE_TOPICS]
    if drive:
        topics += [(agent_topic(k, name), AGENT_TOPICS[name][0])
                   for k in range(1, followers + 1) for name in DRIVE_TOPICS]
    return topics


def any_hash(msgtype: str) -> str:
    """``*``: a key expression chunk matching any type hash (for access-control rules, which
    are written without rosbags)."""
    _split_type(msgtype)
    return "*"


def world_keys(domain: int, followers: int, digest=None, drive: bool = False) -> list[str]:
    """The data keys the world publishes on (one per topic of :func:`run_topics`), with the
    type hashes ``digest(msgtype)`` (default :func:`type_hash`; :func:`any_hash` for rules)."""
    digest = digest or type_hash
    return [topic_key(domain, topic, msgtype, digest(msgtype))
            for topic, msgtype in run_topics(followers, drive)]


def world_tokens(domain: int, followers: int, zid: str = "*", digest=None,
                 drive: bool = False) -> list[str]:
    """The world's liveliness tokens: its node's, then one per publisher (entity ids 1, 2, …
    in the order of :func:`run_topics`). ``zid`` ``*`` and ``digest`` :func:`any_hash` give
    the key expressions that match them whatever the session id and the hashes (a router's
    access-control rules)."""
    digest = digest or type_hash
    return [node_token(domain, zid, 0)] + [
        publisher_token(domain, zid, 0, entity, topic, msgtype, digest(msgtype))
        for entity, (topic, msgtype) in enumerate(run_topics(followers, drive), start=1)]


def graph_keys(domain: int) -> tuple[str, str]:
    """``(<domain>/**, @ros2_lv/<domain>/**)``: every ROS 2 data key and liveliness token of a
    domain (what an observer, or a ROS 2 router joining as one, may watch)."""
    return f"{check_domain(domain)}/**", f"{ADMIN_SPACE}/{domain}/**"


# --- rosbags, lazily ---------------------------------------------------------------------------


@cache
def typestore():
    """rosbags' ROS 2 Jazzy type store (:class:`protocol.distribution.MissingExtra` if the
    ``[ros]`` extra is not installed)."""
    with needs("ros"):
        from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


@cache
def type_hash(msgtype: str) -> str:
    """The RIHS01 hash of ``msgtype``'s Jazzy definition, e.g. ``RIHS01_10f3…``."""
    _split_type(msgtype)
    return typestore().hash_rihs01(msgtype)
