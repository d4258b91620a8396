"""Protocol: keys, codec round trips, and every kind of malformed payload rejected clearly."""
from __future__ import annotations

import math
import os
import subprocess
import sys

import msgpack
import pytest

from protocol import keys
from protocol.config import (
    AgentBrief,
    RunConfig,
    config_from_dict,
    dump_config,
    load_config,
)
from protocol.messages import (
    MESSAGE_TYPES,
    ActResult,
    ActSensing,
    Control,
    Done,
    Drive,
    ErrorReply,
    Joined,
    JoinRequest,
    Missed,
    Move,
    Observation,
    ProtocolError,
    Rod,
    SenseRequest,
    Sensing,
    Snap,
    TickStart,
    decode,
    encode,
    from_body,
    to_body,
)
from protocol.session import free_tcp_endpoint, zenoh_config

SAMPLES = [
    TickStart(tick=3, t=3.84),
    SenseRequest(tick=4, look=True),
    Sensing(tick=4, r=3.5, theta=-1.2, rod=(0.1, -0.2), velocity=None, oracle_velocity=(1.0, 0.0),
            gps=(1.0, 2.0, 3.0), leader_gps=(4.0, 5.0, 6.0)),
    Drive(tick=5, t=6.4),
    Move(tick=5, offset=(0.5, -0.25)),
    Snap(tick=5),
    ActResult(tick=5, moved=True),
    ActSensing(tick=5, r=3.5, theta=0.3, rod=None, velocity=(0.1, 0.2), oracle_velocity=None,
               gps=(1.0, 2.0, 3.0), leader_gps=(4.0, 5.0, 6.0), moved=False),
    Rod(tick=7, length=3.57, side=-1),
    Observation(tick=7, estimator="edmd-b", measurement=(3.5, 0.1), prediction=None, lost=True),
    Done(tick=39, results="runs/x", complete=True, reason=""),
    ErrorReply(tick=0, error="bad", code="missed"),
    Missed(tick=3, agent=2),
    JoinRequest(tick=0),
    Joined(tick=12, settled=False, ready=True, until=14, world=15, start="9f3a"),
    Joined(tick=0, settled=False, ready=False, until=0, world=0, start="9f3a",
           max_speed=math.inf),
    Control(tick=6, step=0, speed=1.5, turn=-0.25, goal=(1.2, 0.1)),
    Control(tick=6, step=7, speed=-0.5, turn=2.0, goal=None),
    ActSensing(tick=6, r=3.5, theta=0.3, rod=(0.1, 0.0), compass=-3.1, slope=(3.3, -0.6),
               odometry=(0.16, 0.01), moved=True),
]


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: m.TYPE)
def test_plain_map_round_trip(msg):
    """to_body/from_body (the follower's state file) give back the same message, validated."""
    import json

    assert from_body(json.loads(json.dumps(to_body(msg))), type(msg)) == msg
    with pytest.raises(ProtocolError):
        from_body({**to_body(msg), "v": 2}, type(msg))


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: m.TYPE)
def test_round_trip(msg):
    assert decode(encode(msg), type(msg)) == msg


def test_every_message_type_is_sampled():
    assert {type(m) for m in SAMPLES} == set(MESSAGE_TYPES.values())


def _raw(**body):
    return msgpack.packb(body, use_bin_type=True)


GOOD_ROD = {"v": 1, "type": "rod", "tick": 2, "length": 3.57, "side": 1}


@pytest.mark.parametrize("payload, fragment", [
    (b"\xc1", "not valid msgpack"),
    (msgpack.packb([1, 2]), "must be a msgpack map"),
    (_raw(**{**GOOD_ROD, "v": 2}), "unsupported schema version 2"),
    (_raw(**{k: v for k, v in GOOD_ROD.items() if k != "v"}), "unsupported schema version None"),
    (_raw(**{**GOOD_ROD, "type": "obs"}), "message type 'obs' not accepted"),
    (_raw(**{k: v for k, v in GOOD_ROD.items() if k != "length"}), "missing field 'length'"),
    (_raw(**{**GOOD_ROD, "extra": 1}), "unknown field(s) ['extra']"),
    (_raw(**{**GOOD_ROD, "length": "3"}), "'length' must be a number"),
    (_raw(**{**GOOD_ROD, "length": math.nan}), "'length' must be finite"),
    (_raw(**{**GOOD_ROD, "length": math.inf}), "'length' must be finite"),
    (_raw(**{**GOOD_ROD, "length": -1.0}), "'length' must be positive"),
    (_raw(**{**GOOD_ROD, "side": 0}), "'side' must be 1 or -1"),
    (_raw(**{**GOOD_ROD, "side": True}), "'side' must be 1 or -1"),
    (_raw(**{**GOOD_ROD, "tick": -1}), "'tick' must be in"),
    (_raw(**{**GOOD_ROD, "tick": 1.5}), "'tick' must be an integer"),
    (_raw(**{**GOOD_ROD, "tick": True}), "'tick' must be an integer"),
])
def test_malformed_rod_rejected(payload, fragment):
    with pytest.raises(ProtocolError) as err:
        decode(payload, Rod)
    assert fragment in str(err.value)


@pytest.mark.parametrize("body, fragment", [
    ({"rod": [1.0]}, "'rod' must have length 2"),
    ({"rod": [1.0, "x"]}, "'rod[1]' must be a number"),
    ({"gps": [1.0, 2.0]}, "'gps' must have length 3"),
    ({"velocity": "fast"}, "'velocity' must be a list"),
    ({"theta": math.inf}, "'theta' must be finite"),
])
def test_malformed_sensing_rejected(body, fragment):
    good = {"v": 1, "type": "sensing", "tick": 1, "r": 1.0, "theta": 0.0, "rod": None,
            "velocity": None, "oracle_velocity": None, "gps": None, "leader_gps": None}
    with pytest.raises(ProtocolError) as err:
        decode(_raw(**{**good, **body}), Sensing)
    assert fragment in str(err.value)


def test_bad_choice_and_tick_order():
    req = {"v": 1, "type": "error", "tick": 1, "error": "x", "code": "later"}
    with pytest.raises(ProtocolError, match="'code' must be one of"):
        decode(_raw(**req), ErrorReply)
    with pytest.raises(ProtocolError, match="older than tick 5"):
        decode(encode(Rod(tick=4, length=1.0, side=1)), Rod, min_tick=5)


def test_an_act_reply_carries_the_sensing():
    """A move or snap reply is the sensing after the action plus whether it moved (design §8)."""
    reply = ActSensing(tick=4, r=3.5, theta=0.1, rod=(0.2, 0.3), velocity=None,
                       oracle_velocity=None, gps=None, leader_gps=None, moved=False)
    sensing = decode(encode(reply), ActSensing).sensing
    assert type(sensing) is Sensing and sensing.rod == (0.2, 0.3) and sensing.r == 3.5
    with pytest.raises(ProtocolError, match="not accepted here"):
        decode(encode(reply), Sensing)
    with pytest.raises(ProtocolError, match="missing field 'moved'"):
        decode(_raw(**{k: v for k, v in to_body(reply).items() if k != "moved"}), ActSensing)


def test_encode_refuses_invalid_message():
    with pytest.raises(ProtocolError, match="'length' must be positive"):
        encode(Rod(tick=1, length=0.0, side=1))
    with pytest.raises(ProtocolError, match="not a protocol message"):
        encode("rod")  # type: ignore[arg-type]


def test_keys():
    assert keys.sense("r1", 3) == "swarm/r1/world/sense/3"
    assert keys.rod("r1") == "swarm/r1/agent/*/rod"
    assert keys.alive("r1", 2) == "swarm/r1/alive/agent/2"
    assert keys.agent_from_key("swarm/r1/agent/12/obs") == 12
    assert keys.agent_from_key("swarm/r1/world/act/0") == 0
    with pytest.raises(ValueError, match="names no agent id"):
        keys.agent_from_key("swarm/r1/world/act/x")
    with pytest.raises(ValueError, match="run_id"):
        keys.tick("bad/id")
    with pytest.raises(ValueError, match="agent id"):
        keys.obs("r", -1)


def test_zenoh_config_helper():
    ep = free_tcp_endpoint()
    conf = zenoh_config("router", listen=[ep])
    assert '"router"' in conf.get_json("mode")
    assert conf.get_json("scouting/multicast/enabled") == "false"
    with pytest.raises(ValueError, match="mode must be one of"):
        zenoh_config("bogus")
    with pytest.raises(ValueError, match="client mode needs"):
        zenoh_config("client")
    with pytest.raises(ValueError, match="listen endpoint"):
        zenoh_config("peer", listen=["7447"])


def test_config_round_trip_and_errors(tmp_path):
    cfg = RunConfig(run_id="abc", surface="wavy", followers=3, sensing_range=math.inf,
                    leader_start=(1.0, 2.0, 1.0, 0.0), surface_params={"a": 0.5})
    dump_config(cfg, tmp_path / "c.toml")
    assert load_config(tmp_path / "c.toml") == cfg
    settings = AgentBrief.load(AgentBrief.of(cfg, 2).write(tmp_path / "a.toml")).settings
    assert not hasattr(settings, "surface") and settings.followers == 3
    with pytest.raises(ValueError, match="unknown configuration option"):
        config_from_dict({"surfaec": "wavy"})
    with pytest.raises(ValueError, match="forget must be in"):
        RunConfig(forget=1.5)
    with pytest.raises(ValueError, match="enable gps"):
        RunConfig(dictionary="d")
    with pytest.raises(ValueError, match="estimator must be one of"):
        RunConfig(estimator="magic")
    (tmp_path / "bad.toml").write_text("followers = [")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_config(tmp_path / "bad.toml")


def test_credentials_from_flags_or_file(tmp_path):
    import argparse

    from protocol.session import add_connection_flags, credentials

    p = argparse.ArgumentParser()
    add_connection_flags(p)
    assert credentials(p.parse_args(["--user", "u", "--password", "pw"])) == ("u", "pw")
    (tmp_path / "secret").write_text("s3cret  \nignored\n")
    args = p.parse_args(["--user", "u", "--password-file", str(tmp_path / "secret")])
    assert credentials(args) == ("u", "s3cret")
    with pytest.raises(ValueError, match="cannot read a password"):
        credentials(p.parse_args(["--password-file", str(tmp_path / "missing")]))
    with pytest.raises(SystemExit):  # both at once is refused by argparse
        p.parse_args(["--password", "a", "--password-file", "b"])


@pytest.mark.parametrize("body, fragment", [
    ({"step": 0, "speed": math.nan, "turn": 0.0, "goal": None}, "'speed' must be finite"),
    ({"step": 0, "speed": 1.0, "turn": math.inf, "goal": None}, "'turn' must be finite"),
    ({"step": -1, "speed": 1.0, "turn": 0.0, "goal": None}, "'step' must be in"),
    ({"step": 0, "speed": 1.0, "turn": 0.0, "goal": [1.0]}, "'goal' must have length 2"),
    ({"step": 0, "speed": "fast", "turn": 0.0, "goal": None}, "'speed' must be a number"),
])
def test_malformed_control_rejected(body, fragment):
    with pytest.raises(ProtocolError, match=fragment):
        decode(_raw(v=1, type="control", tick=5, **body), Control)


@pytest.mark.parametrize("value", [0.0, -2.0, math.nan, "2"])
def test_a_joined_top_speed_must_be_positive(value):
    with pytest.raises(ProtocolError, match="max_speed"):
        decode(_raw(v=1, type="joined", tick=0, settled=False, ready=False, until=0, world=0,
                    start="ab", max_speed=value), Joined)


FREED_BLOCKS = """
import resource, numpy as np
import protocol
def temporaries():  # three 1 MiB arrays alive at once, over glibc's default mmap threshold
    arrays = [np.ones(1 << 17) for _ in range(3)]
temporaries()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    temporaries()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_importing_the_project_keeps_freed_blocks_for_reuse_unless_the_environment_tunes_them():
    """Numpy temporaries of 1 MiB made again and again, three at a time: with the project
    imported their pages are reused (no new page faults); with the environment's own setting
    (which the project leaves alone) they are mapped afresh, up to 256 pages each."""
    def faults(**env):
        out = subprocess.run([sys.executable, "-c", FREED_BLOCKS], capture_output=True,
                             text=True, timeout=60, env={**os.environ, **env}, check=True)
        return int(out.stdout)
    kept, own = faults(), faults(MALLOC_MMAP_THRESHOLD_="131072")
    assert own >= 20 * 256, own
    assert kept < own / 20, (kept, own)
