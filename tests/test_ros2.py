"""ROS 2 naming without ROS (design §10): key expressions, liveliness tokens, QoS chunks, GIDs,
attachments and type hashes, against literals from rmw_zenoh's ``docs/design.md`` (jazzy),
rosbags' RIHS01 hashes, zenoh-ext's serializer, known XXH3-128 vectors and the system's
libxxhash; the pose frame."""
from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import math
import random
from pathlib import Path

import numpy as np
import pytest
import xxhash
import zenoh
import zenoh.ext

from protocol import ros2
from protocol.config import RunConfig
from world.ros2 import quaternion, stamp_ns, stamp_parts, surface_quaternion

ROOT = Path(__file__).resolve().parents[1]

# Literal examples of docs/design.md in ros2/rmw_zenoh (jazzy branch)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
LISTENER_NODE = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
TALKER_PUBLISHER = ("@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                    f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
LISTENER_SUBSCRIPTION = ("@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/"
                         f"%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
CHATTER_KEY = f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"


def test_type_hashes_are_rosbags_rihs01():
    store = ros2.typestore()
    assert ros2.type_hash("std_msgs/msg/String") == STRING_HASH  # the design.md literal
    for _, msgtype in ros2.run_topics(2):
        digest = ros2.type_hash(msgtype)
        assert digest == store.hash_rihs01(msgtype)
        assert digest.startswith("RIHS01_") and len(digest) == 7 + 64
    # a known Jazzy value, so a changed definition in rosbags would be noticed
    assert ros2.type_hash("geometry_msgs/msg/PoseStamped") == (
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8")
    assert ros2.type_hash(ros2.DIAGNOSTICS[1]) == (  # the value other ROS 2 stacks list too
        "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e")


def test_data_keys():
    assert ros2.topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == CHATTER_KEY
    digest = ros2.type_hash("geometry_msgs/msg/PoseStamped")
    assert ros2.topic_key(3, "/swarm/agent_1/pose", "geometry_msgs/msg/PoseStamped", digest) == (
        f"3/swarm/agent_1/pose/geometry_msgs::msg::dds_::PoseStamped_/{digest}")
    assert ros2.dds_type("visualization_msgs/msg/MarkerArray") == (
        "visualization_msgs::msg::dds_::MarkerArray_")
    assert ros2.ros_type("nav_msgs::msg::dds_::Path_") == "nav_msgs/msg/Path"
    keys = ros2.world_keys(7, 2)
    assert len(keys) == len(set(keys)) == 4 + 2 * 3 + 3 * 2  # run-wide, leader, followers
    assert all(key.startswith("7/") and key.count("/RIHS01_") == 1 for key in keys)
    for bad in ("chatter", "/a//b", "/1a", "/a b", "/"):
        with pytest.raises(ValueError):
            ros2.topic_key(0, bad, "std_msgs/msg/String", STRING_HASH)
    with pytest.raises(ValueError):
        ros2.dds_type("std_msgs/String")


def test_liveliness_tokens_match_design_literals():
    assert ros2.node_token(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener") == LISTENER_NODE
    assert ros2.publisher_token(0, "8b20917502ee955ac4476e0266340d5c", 0, 10, "/chatter",
                                "std_msgs/msg/String", STRING_HASH, ros2.Qos(depth=7),
                                name="talker") == TALKER_PUBLISHER
    talker = ros2.parse_token(TALKER_PUBLISHER)
    assert (talker.kind, talker.node, talker.namespace, talker.enclave) == (
        "MP", "talker", "/", "/")
    assert (talker.topic, talker.msgtype, talker.type_hash) == (
        "/chatter", "std_msgs/msg/String", STRING_HASH)
    assert talker.qos == ros2.Qos(depth=7) and talker.entity_id == 10 and talker.domain == 0
    listener = ros2.parse_token(LISTENER_SUBSCRIPTION)
    assert listener.kind == "MS" and listener.qos == ros2.Qos(depth=10)
    node = ros2.parse_token(LISTENER_NODE)
    assert node.kind == "NN" and node.topic is None
    assert node.zid == "aac3178e146ba6f1fc6e6a4085e77f21"
    for bad in ("@ros2_lv/0/z/0/0/NN/%/%", LISTENER_NODE.replace("@ros2_lv", "@other"),
                LISTENER_NODE + "/extra/x/y/z", TALKER_PUBLISHER.replace("/MP/", "/NN/"),
                LISTENER_NODE.replace("/0/0/", "/x/0/")):
        with pytest.raises(ValueError):
            ros2.parse_token(bad)


def test_world_tokens_round_trip():
    tokens = ros2.world_tokens(5, 2, "0123abcd")
    node, *publishers = (ros2.parse_token(t) for t in tokens)
    assert (node.kind, node.node, node.node_id, node.entity_id) == ("NN", ros2.NODE_NAME, 0, 0)
    assert [(p.topic, p.msgtype) for p in publishers] == ros2.run_topics(2)
    assert [p.entity_id for p in publishers] == list(range(1, len(publishers) + 1))
    assert all(p.qos == ros2.PUBLISHER_QOS and p.domain == 5 for p in publishers)
    assert [ros2.publisher_token(5, "0123abcd", 0, p.entity_id, p.topic, p.msgtype,
                                 p.type_hash) for p in publishers] == tokens[1:]


def test_a_drive_run_adds_one_cmd_vel_twist_per_follower():
    """``cmd_vel`` (``geometry_msgs/msg/Twist``, the Jazzy hash) for each follower of a drive
    run, after every other topic: the other publishers keep a teleport run's entity ids."""
    assert ros2.type_hash("geometry_msgs/msg/Twist") == (
        "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a")
    drive, teleport = ros2.run_topics(2, drive=True), ros2.run_topics(2)
    assert drive == teleport + [(f"/swarm/agent_{k}/cmd_vel", "geometry_msgs/msg/Twist")
                                for k in (1, 2)]
    keys = ros2.world_keys(7, 2, drive=True)
    assert keys[-1] == ("7/swarm/agent_2/cmd_vel/geometry_msgs::msg::dds_::Twist_/"
                        + ros2.type_hash("geometry_msgs/msg/Twist"))
    tokens = ros2.world_tokens(7, 2, "0123abcd", drive=True)
    assert tokens[:-2] == ros2.world_tokens(7, 2, "0123abcd")
    assert [(p.topic, p.msgtype, p.entity_id) for p in map(ros2.parse_token, tokens[1:])] == [
        (topic, msgtype, entity) for entity, (topic, msgtype) in enumerate(drive, start=1)]


def test_qos_chunks():
    assert ros2.qos_keyexpr(ros2.PUBLISHER_QOS) == "::,10:,:,:,,"
    assert ros2.qos_keyexpr(ros2.RMW_ZENOH_DEFAULT) == "::,:,:,:,,"
    odd = ros2.Qos(reliability=ros2.BEST_EFFORT, durability=ros2.TRANSIENT_LOCAL,
                   history=ros2.KEEP_ALL, depth=3, deadline=(1, 500), lifespan=(2, 0),
                   liveliness=3, lease=(4, 5))
    assert ros2.qos_keyexpr(odd) == "2:1:2,3:1,500:2,0:3,4,5"
    assert ros2.parse_qos(ros2.qos_keyexpr(odd)) == odd
    for bad in ("::,10:,:,:", "::10:,:,:,,", "::,x:,:,:,,"):
        with pytest.raises(ValueError):
            ros2.parse_qos(bad)


def test_attachment_layout():
    gid = bytes(range(16))
    data = ros2.attachment(7, -2, gid)
    assert data == bytes.fromhex("0700000000000000" "feffffffffffffff" "10") + gid
    # zenoh-ext's serializer writes the same bytes for (int64, int64, std::array<uint8, 16>)
    assert data == zenoh.ext.z_serialize(
        (zenoh.ext.Int64(7), zenoh.ext.Int64(-2), [zenoh.ext.UInt8(b) for b in gid])).to_bytes()
    assert ros2.parse_attachment(data) == (7, -2, gid)
    for bad in (data[:-1], data + b"\0", data[:16] + b"\x0f" + gid):
        with pytest.raises(ValueError):
            ros2.parse_attachment(bad)
    with pytest.raises(ValueError):
        ros2.attachment(1, 1, b"short")


def test_attachment_of_rmw_zenoh_0_2_3_and_earlier_differs():
    """rmw_zenoh_cpp 0.2.0-0.2.3 wrote each field's name before it (docs/ros2.md, Versions):
    their subscribers read ours as a name and find none (they throw), and theirs is no
    attachment of ours."""
    gid = bytes(range(16))
    ours = zenoh.ZBytes(ros2.attachment(7, -2, gid))
    old_layout = tuple[str, zenoh.ext.Int64, str, zenoh.ext.Int64, str, list[zenoh.ext.UInt8]]
    theirs = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(7), "source_timestamp",
                                    zenoh.ext.Int64(-2), "source_gid",
                                    [zenoh.ext.UInt8(b) for b in gid]))
    assert zenoh.ext.z_deserialize(old_layout, theirs)[0] == "sequence_number"
    assert zenoh.ext.z_deserialize(str, ours) != "sequence_number"
    with pytest.raises(zenoh.ext.ZDeserializeError):
        zenoh.ext.z_deserialize(old_layout, ours)
    with pytest.raises(ValueError, match="33 bytes"):
        ros2.parse_attachment(theirs.to_bytes())


def _libxxhash():
    path = ctypes.util.find_library("xxhash")
    if path is None:
        pytest.skip("the system has no libxxhash to compare with")
    lib = ctypes.CDLL(path)

    class Hash(ctypes.Structure):
        _fields_ = [("low64", ctypes.c_uint64), ("high64", ctypes.c_uint64)]

    lib.XXH3_128bits.restype = Hash
    lib.XXH3_128bits.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
    return lib


# XXH3-128 (seed 0) of a few inputs, as the 128-bit value (high half first): b"" is the
# specification's own test value; the others were computed with the system's libxxhash 0.8
# (and agreed with the pure-Python implementation this project kept before using xxhash).
KNOWN_XXH3_128 = {
    b"": 0x99AA06D3014798D86001C324468D497F,
    b"a": 0xA96FAF705AF16834E6C632B61E964E1F,
    b"abc": 0x06B05AB6733A618578AF5F94892F3950,
    bytes(range(20)): 0x21773A7052C02D6CCD7648AFA6F388D9,
    bytes(range(200)): 0xCB0395310643BA0EDD97E9AF3609D9F5,
    bytes(range(256)) * 3: 0xA9EE10CBF43517E44066A57F4496584A,
}
TALKER_PUBLISHER_GID = "eb85fa883b7846dc448a4501890ad062"  # by the rule above (the pure-Python
# XXH3 this project had before gave the same)


def test_xxh3_known_vectors():
    for data, value in KNOWN_XXH3_128.items():
        assert xxhash.xxh3_128_intdigest(data) == value, len(data)


def test_xxh3_matches_libxxhash_at_every_length_class():
    lib = _libxxhash()
    rng = random.Random(22)
    lengths = [*range(0, 260), 511, 512, 1023, 1024, 1025, 2048, 4097]
    for n in lengths:
        data = bytes(rng.randrange(256) for _ in range(n))
        expected = lib.XXH3_128bits(data, n)
        value = xxhash.xxh3_128_intdigest(data)
        assert (value & (2**64 - 1), value >> 64) == (expected.low64, expected.high64), n


def test_gid_is_the_tokens_xxh3_halves_little_endian():
    value = xxhash.xxh3_128_intdigest(TALKER_PUBLISHER.encode())
    low, high = value & (2**64 - 1), value >> 64
    gid = ros2.gid(TALKER_PUBLISHER)
    assert gid == low.to_bytes(8, "little") + high.to_bytes(8, "little")
    assert gid.hex() == TALKER_PUBLISHER_GID
    assert ros2.gid(LISTENER_NODE) != gid


def test_domains():
    assert ros2.domain_from_env({}) == 0
    assert ros2.domain_from_env({"ROS_DOMAIN_ID": " 42 "}) == 42
    for bad in ("233", "-1", "x", "1.5"):
        with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
            ros2.domain_from_env({"ROS_DOMAIN_ID": bad})
    assert RunConfig(ros2=True, ros_domain=232).ros_domain == 232
    for bad in (233, -1, True, 1.0):
        with pytest.raises(ValueError, match="ros_domain"):
            RunConfig(ros2=True, ros_domain=bad)
    with pytest.raises(ValueError, match="ros_domain = 5 does nothing"):
        RunConfig(ros_domain=5)  # a domain without ROS 2 publishing
    with pytest.raises(ValueError, match="ros2"):
        RunConfig(ros2="yes")


def test_world_ros_options(tmp_path, monkeypatch):
    """``python -m world``: flags override; with ROS 2 on, a file without the domain takes
    ROS_DOMAIN_ID; without it the domain is not looked at."""
    from world.main import ros_options

    bare = tmp_path / "bare.toml"
    bare.write_text('run_id = "r"\n')
    pinned = tmp_path / "pinned.toml"
    pinned.write_text('run_id = "r"\nros2 = true\nros_domain = 9\n')

    def args(path, ros2=None, domain=None):
        return argparse.Namespace(resume=None, config=str(path), ros2=ros2, ros_domain=domain)

    monkeypatch.setenv("ROS_DOMAIN_ID", "17")
    config = RunConfig(run_id="r")
    assert ros_options(config, args(bare)) == config  # no ROS 2: the environment is not read
    assert ros_options(config, args(bare, True)) == config.replace(ros2=True, ros_domain=17)
    on = config.replace(ros2=True, ros_domain=9)
    assert ros_options(on, args(pinned)).ros_domain == 9
    assert ros_options(config, args(bare, True, 3)) == config.replace(ros2=True, ros_domain=3)
    with pytest.raises(ValueError, match="ros_domain = 3 does nothing"):
        ros_options(config, args(bare, None, 3))
    monkeypatch.setenv("ROS_DOMAIN_ID", "300")
    with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
        ros_options(config, args(bare, True))


def test_swarm_run_domain_defaults_to_the_environment(monkeypatch):
    from swarm.cli import build_parser, config_from_args

    parser = build_parser()
    monkeypatch.setenv("ROS_DOMAIN_ID", "12")
    assert config_from_args(parser.parse_args(["run", "--ros2"])).ros_domain == 12
    assert config_from_args(parser.parse_args(["run", "--ros2", "--ros-domain", "4"])
                            ).ros_domain == 4
    assert config_from_args(parser.parse_args(["run"])).ros_domain == 0  # no ROS 2: not read
    with pytest.raises(ValueError, match="ros_domain = 4 does nothing"):
        config_from_args(parser.parse_args(["run", "--ros-domain", "4"]))


def _rotation(q: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_pose_frame_heading_in_the_tangent_plane_normal_up():
    rng = np.random.default_rng(3)
    for _ in range(200):
        gradient, heading = rng.normal(size=2) * 2, rng.normal(size=2)
        q = surface_quaternion(gradient, heading)
        assert math.isclose(sum(c * c for c in q), 1.0, rel_tol=1e-12) and q[3] >= 0
        m = _rotation(q)
        fx, fy = gradient
        tangent = np.array([heading[0], heading[1], fx * heading[0] + fy * heading[1]])
        normal = np.array([-fx, -fy, 1.0])
        np.testing.assert_allclose(m[:, 0], tangent / np.linalg.norm(tangent), atol=1e-12)
        np.testing.assert_allclose(m[:, 2], normal / np.linalg.norm(normal), atol=1e-12)
        yaw = math.atan2(m[1, 0], m[0, 0])
        assert math.isclose(yaw, math.atan2(heading[1], heading[0]), abs_tol=1e-12)
    # flat ground: the quaternion is the yaw alone
    q = surface_quaternion((0.0, 0.0), (0.0, 2.0))
    np.testing.assert_allclose(q, (0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)), atol=1e-15)
    # every branch of the matrix-to-quaternion conversion
    for angle, axis in ((3.0, 0), (3.0, 1), (3.0, 2), (0.3, 0)):
        m = np.eye(3)
        i, j = [k for k in range(3) if k != axis]
        m[i, i] = m[j, j] = math.cos(angle)
        m[j, i], m[i, j] = math.sin(angle), -math.sin(angle)
        np.testing.assert_allclose(_rotation(quaternion(m.tolist())), m, atol=1e-12)
    with pytest.raises(ValueError):
        surface_quaternion((0.0, 0.0), (0.0, 0.0))


def test_stamps():
    assert stamp_parts(0.0) == (0, 0)
    assert stamp_parts(3 * 1.28) == (3, 840000000)
    assert stamp_parts(2 - 1e-12) == (2, 0)
    assert stamp_ns(1.28) == 1_280_000_000
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            stamp_parts(bad)


def test_shipped_rviz_config_shows_run_topics():
    """deploy/rviz/swarm.rviz: fixed frame map, and every topic it shows is one the world
    publishes, with a display for its type."""
    import yaml

    config = yaml.safe_load((ROOT / "deploy" / "rviz" / "swarm.rviz").read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == ros2.FRAME
    topics = dict(ros2.run_topics(3))
    display_for = {"visualization_msgs/msg/MarkerArray": "rviz_default_plugins/MarkerArray",
                   "nav_msgs/msg/Path": "rviz_default_plugins/Path",
                   "geometry_msgs/msg/PoseStamped": "rviz_default_plugins/Pose"}
    shown = {d["Topic"]["Value"]: d["Class"] for d in manager["Displays"] if "Topic" in d}
    assert set(shown) == {"/swarm/markers", "/swarm/agent_1/pose",
                          *(f"/swarm/agent_{k}/path" for k in range(4))}
    assert all(display_for[topics[topic]] == kind for topic, kind in shown.items())
    assert "rviz_default_plugins/TF" in {d["Class"] for d in manager["Displays"]}


def test_geodesic_points_follow_one_geodesic():
    """The rods' samples (world.geometry.geodesic_points): piece by piece, the same geodesic
    as one integration over the whole length, and refused arguments."""
    from world import geometry
    from world.surfaces import make_surface

    surface = make_surface("wavy")
    p, v = np.array([30.0, 5.0]), np.array([0.3, 0.9])
    points = geometry.geodesic_points(surface, p, v, 3.57, 8)
    assert points.shape == (9, 2) and (points[0] == p).all()
    end, _ = geometry.integrate_geodesic(surface, p, v, 3.57)
    np.testing.assert_allclose(points[-1], end, atol=1e-9)
    middle, _ = geometry.integrate_geodesic(surface, p, v, 3.57 * 3 / 8)
    np.testing.assert_allclose(points[3], middle, atol=1e-9)
    for bad in ({"t": -1.0}, {"pieces": 0}):
        args = {"t": 1.0, "pieces": 2, **bad}
        with pytest.raises(ValueError):
            geometry.geodesic_points(surface, p, v, args["t"], args["pieces"])
