"""Bad input never crashes a process nor changes a run: codec fuzzing, error replies that name
the problem, and a live flood of malformed queries and garbage samples during a run."""
from __future__ import annotations

import math
import threading
import time

import msgpack
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.link import AgentLink, Rejoin
from protocol import keys
from protocol.config import RunConfig
from protocol.messages import (
    MESSAGE_TYPES,
    ActSensing,
    Drive,
    ErrorReply,
    Joined,
    JoinRequest,
    Message,
    ProtocolError,
    Rod,
    SenseRequest,
    Sensing,
    Snap,
    decode,
    encode,
)
from protocol.session import free_tcp_endpoint, zenoh_config
from tests.attacking import run_under_attack, same_results, wait_for_world
from world.main import resolve
from world.service import WorldService
from world.surfaces import make_surface

ALL_TYPES = tuple(MESSAGE_TYPES.values())
scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(),
                    st.text(max_size=20), st.binary(max_size=20))
values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=5)),
    max_leaves=20)


FUZZ_EXAMPLES = [100, pytest.param(1000, marks=pytest.mark.slow)]
"""Examples per fuzz test: a hundred in the fast tier, a thousand in the slow one."""
MAPS = st.dictionaries(st.sampled_from(["v", "type", "tick", "r", "theta", "rod", "look",
                                        "action", "offset", "t", "length", "side", "error",
                                        "code", "agent", "x"]), values, max_size=8)


@pytest.mark.parametrize("examples", FUZZ_EXAMPLES)
def test_fuzz_random_bytes(examples):
    @settings(max_examples=examples, deadline=None)
    @given(st.binary(max_size=200))
    def check(data):
        try:
            decode(data, ALL_TYPES)
        except ProtocolError:
            pass

    check()


@pytest.mark.parametrize("examples", FUZZ_EXAMPLES)
def test_fuzz_structured_maps(examples):
    """Plausible-looking maps: either a valid message that re-encodes identically, or a
    ProtocolError; nothing else ever escapes."""
    @settings(max_examples=examples, deadline=None)
    @given(MAPS, st.sampled_from(list(MESSAGE_TYPES)))
    def check(body, type_name):
        body = {"v": 1, "type": type_name, **body}
        try:
            msg = decode(msgpack.packb(body, use_bin_type=True), ALL_TYPES)
        except ProtocolError:
            return
        assert decode(encode(msg), type(msg)) == msg

    check()


@pytest.fixture
def world():
    """A world service on an embedded router at tick 0 (leader settled), and a client."""
    config = resolve(RunConfig(run_id="bad", followers=2))
    endpoint = free_tcp_endpoint()
    with zenoh.open(zenoh_config("router", listen=[endpoint])) as wsession, \
            zenoh.open(zenoh_config("client", connect=[endpoint])) as client:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            service = WorldService(wsession, config, make_surface(config.surface), tmp)
            service.sim.start_tick(0)
            service.sim.drive(0, 0, 0.0)
            # the leader's rod, as the leader would publish it: follower 1's turn
            client.put(keys.rod("bad", 0), encode(Rod(tick=0, length=config.spacing, side=1)))
            deadline = time.monotonic() + 10.0
            while not _joined(client, 1).ready:
                assert time.monotonic() < deadline, "the world never counted the leader's rod"
                time.sleep(0.01)
            yield service, client
            service.close()


def _ask(client, key, payload) -> str:
    replies = list(client.get(key, payload=payload, timeout=5.0))
    assert len(replies) == 1
    assert replies[0].ok is None, "a malformed request was answered as if valid"
    return decode(replies[0].err.payload.to_bytes(), ErrorReply).error


def _joined(client, agent: int, run: str = "bad") -> Joined:
    replies = list(client.get(keys.act(run, agent), payload=encode(JoinRequest(tick=0)),
                              timeout=5.0))
    return decode(replies[0].ok.payload.to_bytes(), Joined)


def _raw(**body):
    return msgpack.packb(body, use_bin_type=True)


GOOD_SENSE = {"v": 1, "type": "sense", "tick": 0, "look": False}
GOOD_MOVE = {"v": 1, "type": "move", "tick": 0, "offset": [0.1, 0.0]}
GOOD_DRIVE = {"v": 1, "type": "drive", "tick": 0, "t": 0.0}


@pytest.mark.parametrize("key_agent, payload, fragment", [
    (1, b"", "not valid msgpack"),
    (1, msgpack.packb([1, 2]), "must be a msgpack map"),
    (1, _raw(**{**GOOD_SENSE, "v": 7}), "unsupported schema version 7"),
    (1, _raw(**{**GOOD_SENSE, "type": "act"}), "message type 'act' not accepted"),
    (1, _raw(**{**GOOD_SENSE, "look": "never"}), "'look' must be a boolean"),
    (1, _raw(**{**GOOD_SENSE, "phase": "settled"}), "unknown field"),
    (1, _raw(**{**GOOD_SENSE, "tick": 5}), "request for tick 5, but the world is at tick 0"),
    (1, _raw(**{**GOOD_SENSE, "tick": -3}), "'tick' must be in"),
    (99, _raw(**GOOD_SENSE), "unknown agent id 99"),
    (0, _raw(**GOOD_SENSE), "agent 0 is the leader"),
])
def test_sense_errors_name_the_problem(world, key_agent, payload, fragment):
    service, client = world
    before = service.rejected
    assert fragment in _ask(client, keys.sense("bad", key_agent), payload)
    assert service.rejected == before + 1


def test_a_reading_asked_again_or_out_of_order_is_refused_over_zenoh(world):
    """The world serves the pre-move sensing once per tick, and an initial tick's snap only
    after a look (design §5): a client that re-asks, or acts out of order, is refused."""
    service, client = world
    assert "must look for its rod end" in _ask(client, keys.act("bad", 1),
                                               encode(Snap(tick=0)))
    replies = list(client.get(keys.sense("bad", 1), payload=encode(SenseRequest(tick=0)),
                              timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is not None
    assert decode(replies[0].ok.payload.to_bytes(), Sensing).rod is None  # did not look
    before = service.rejected
    for look in (False, True):
        assert "each reading comes once" in _ask(client, keys.sense("bad", 1),
                                                 encode(SenseRequest(tick=0, look=look)))
    assert service.rejected == before + 2


def _reply(client, key, request) -> ErrorReply | Message:
    """The world's one reply to ``request``: the message if answered, else the refusal."""
    replies = list(client.get(key, payload=encode(request), timeout=5.0))
    assert len(replies) == 1
    if replies[0].ok is not None:
        return decode(replies[0].ok.payload.to_bytes(), (Sensing, ActSensing))
    return decode(replies[0].err.payload.to_bytes(), ErrorReply)


def test_a_request_sent_before_a_join_is_not_read_after_it(world):
    """The race of a paused world (design §8): a follower's pre-move sensing query, sent before
    its session was cut, reaches the world after the follower joined again. The world refuses
    it unread (code ``stale``), so the redo's own request gets the tick's one pre-move reading;
    a re-ask within the latest join is still refused, and so is any act of the earlier join."""
    service, client = world
    sense, act = keys.sense("bad", 1), keys.act("bad", 1)
    first = _joined(client, 1)
    assert first.epoch >= 1
    in_flight = SenseRequest(tick=0, look=True, epoch=first.epoch)  # sent, not yet arrived
    again = _joined(client, 1)  # the cut: it joins again and gives the query up
    assert again.epoch == first.epoch + 1
    before = service.rejected
    stale = _reply(client, sense, in_flight)  # ...which reaches the world only now
    assert isinstance(stale, ErrorReply) and stale.code == "stale", stale
    assert f"join {first.epoch} came after its join {again.epoch}" in stale.error
    redo = _reply(client, sense, SenseRequest(tick=0, look=True, epoch=again.epoch))
    assert isinstance(redo, Sensing) and redo.rod is not None, redo
    ask = _reply(client, sense, SenseRequest(tick=0, look=True, epoch=again.epoch))
    assert isinstance(ask, ErrorReply) and "each reading comes once" in ask.error
    late = _reply(client, act, Snap(tick=0, epoch=first.epoch))
    assert isinstance(late, ErrorReply) and late.code == "stale", late
    ahead = _reply(client, sense, SenseRequest(tick=0, look=True, epoch=again.epoch + 1))
    assert isinstance(ahead, ErrorReply) and ahead.code == "stale", ahead
    settled = _reply(client, act, Snap(tick=0, epoch=again.epoch))
    assert isinstance(settled, ActSensing) and settled.moved, settled
    assert service.rejected == before + 1  # the re-ask; stale leftovers are not refusals


def _at_tick_zero(service, client, run: str, spacing: float) -> None:
    """Begin tick 0 with the leader settled and its rod counted: follower 1's turn."""
    service.sim.start_tick(0)
    service.sim.drive(0, 0, 0.0)
    client.put(keys.rod(run, 0), encode(Rod(tick=0, length=spacing, side=1)))
    deadline = time.monotonic() + 10.0
    while not _joined(client, 1, run).ready:
        assert time.monotonic() < deadline, "the world never counted the leader's rod"
        time.sleep(0.01)


def test_a_resumed_world_holds_a_redo_to_what_it_answered_before(tmp_path):
    """A world killed mid-tick and resumed runs the tick again with the same noise, so what it
    answered before its death is journalled (``world_requests.jsonl``) and a redo must ask it
    again (design §5): a follower that looked before moving cannot redo the tick without
    looking (reading the same draw from elsewhere), and the redo that asks the same gets the
    same reading."""
    config = resolve(RunConfig(run_id="bad", followers=2, noise_range=0.02,
                               noise_bearing=0.01))
    endpoint = free_tcp_endpoint()
    sense = keys.sense("bad", 1)
    with zenoh.open(zenoh_config("router", listen=[endpoint])) as wsession, \
            zenoh.open(zenoh_config("client", connect=[endpoint])) as client:
        service = WorldService(wsession, config, make_surface(config.surface), tmp_path)
        try:
            _at_tick_zero(service, client, "bad", config.spacing)
            epoch = _joined(client, 1).epoch
            first = _reply(client, sense, SenseRequest(tick=0, look=True, epoch=epoch))
            assert isinstance(first, Sensing) and first.rod is not None, first
        finally:
            service.close()  # the world dies before the tick completes
        assert (tmp_path / "world_requests.jsonl").exists()
        resumed = WorldService(wsession, config, make_surface(config.surface), tmp_path,
                               resume=True)
        try:
            _at_tick_zero(resumed, client, "bad", config.spacing)
            epoch = _joined(client, 1).epoch
            other = _reply(client, sense, SenseRequest(tick=0, look=False, epoch=epoch))
            assert isinstance(other, ErrorReply), other
            assert "redoes tick 0" in other.error and "must repeat" in other.error
            same = _reply(client, sense, SenseRequest(tick=0, look=True, epoch=epoch))
            assert isinstance(same, Sensing) and (same.r, same.theta, same.rod) == (
                first.r, first.theta, first.rod)
        finally:
            resumed.close()


def test_a_link_told_its_request_is_stale_joins_again(world):
    """An agent whose request the world calls stale (it has the agent joined again since, as a
    world started again with --resume would) joins again instead of stopping."""
    _, client = world
    link = AgentLink(client, "bad", 1, 0, query_timeout=5.0)
    try:
        assert link.join(5.0).epoch >= 1
        _joined(client, 1)  # a join this link has not seen
        with pytest.raises(Rejoin, match="came after its join"):
            link.sense(0, look=True)
        link.join(5.0)
        assert link.sense(0, look=True).rod is not None
    finally:
        link.close()


def test_a_follower_ahead_of_its_predecessor_is_told_to_wait(world):
    """Not a refusal: code ``wait`` (the predecessor's rod may reach the follower before the
    world), so a real follower asks again; nothing is counted as refused."""
    service, client = world
    before = service.rejected
    replies = list(client.get(keys.sense("bad", 2), payload=_raw(**GOOD_SENSE), timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is None
    error = decode(replies[0].err.payload.to_bytes(), ErrorReply)
    assert error.code == "wait" and "agent 1 is not through tick 0 yet" in error.error
    assert service.rejected == before


def test_a_follower_a_tick_ahead_of_the_world_is_told_to_wait(world):
    """A predecessor's rod of a tick this world has not begun (a world resumed from its
    checkpoint redoes a tick the world before it had begun) makes its follower ask for it: told
    to wait, not refused, so the follower does the tick once this world begins it. Two ticks
    ahead is still refused."""
    service, client = world
    before = service.rejected
    replies = list(client.get(keys.sense("bad", 1), payload=_raw(**{**GOOD_SENSE, "tick": 1}),
                              timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is None
    error = decode(replies[0].err.payload.to_bytes(), ErrorReply)
    assert error.code == "wait" and "the world has not begun tick 1 yet" in error.error
    assert service.rejected == before
    assert "request for tick 2, but the world is at tick 0" in _ask(
        client, keys.sense("bad", 1), _raw(**{**GOOD_SENSE, "tick": 2}))


@pytest.mark.parametrize("key_agent, body, fragment", [
    (1, {**GOOD_MOVE, "offset": [math.nan, 0.0]}, "'offset[0]' must be finite"),
    (1, {**GOOD_MOVE, "offset": [1e9, 0.0]}, "move offset must be two finite numbers of size"),
    (1, {**GOOD_MOVE, "offset": [1.0]}, "'offset' must have length 2"),
    (1, GOOD_MOVE, "tick 0 is an initial tick"),
    (1, {**GOOD_MOVE, "type": "teleport"}, "message type 'teleport' not accepted"),
    (1, {**GOOD_MOVE, "t": 0.0}, "unknown field(s) ['t']"),
    (1, {"v": 1, "type": "move", "tick": 0}, "missing field 'offset'"),
    (1, GOOD_DRIVE, "only the leader (agent 0) may drive"),
    (0, GOOD_DRIVE, "the leader already drove"),
    (0, GOOD_MOVE, "agent 0 is the leader"),
    (7, GOOD_MOVE, "unknown agent id 7"),
])
def test_act_errors_name_the_problem(world, key_agent, body, fragment):
    _, client = world
    assert fragment in _ask(client, keys.act("bad", key_agent), _raw(**body))


def test_garbage_samples_are_dropped(world, caplog):
    """Garbage on agent keys is logged and dropped; the world keeps serving."""
    import time

    service, client = world
    client.put(keys.rod("bad", 1), b"\x00garbage")
    client.put(keys.obs("bad", 2), _raw(v=1, type="obs", tick=0))
    client.put(keys.rod("bad", 1), _raw(v=1, type="rod", tick=0, length=3.57, side=1))
    deadline = time.monotonic() + 10
    while service.rejected < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert service.rejected == 3
    assert "dropped rod sample" in caplog.text and "dropped observation" in caplog.text
    assert "published a rod without settling" in caplog.text
    assert service._through[:2] == [0, -1]  # only the leader, whose rod the fixture published
    replies = list(client.get(keys.sense("bad", 1), payload=encode(SenseRequest(tick=0)),
                              timeout=5.0))
    assert replies and replies[0].ok is not None  # still serving


def test_non_numeric_id_in_key(world):
    _, client = world
    assert "names no agent id" in _ask(client, "swarm/bad/world/sense/abc", _raw(**GOOD_SENSE))


def _attack(endpoint: str, run_id: str, stop: threading.Event, counts: dict,
            password: str) -> None:
    """Fire malformed queries and garbage samples until ``stop``, logged in as follower 1
    (the embedded router admits only the run's users, and lets follower 1 query only its
    own keys: tests/test_acl.py)."""
    bad_queries = [
        (keys.sense(run_id, 1), b"\xff\x00garbage"),
        (keys.act(run_id, 1), _raw(**{**GOOD_MOVE, "offset": [math.inf, 1.0]})),
        (keys.act(run_id, 1), _raw(**{**GOOD_MOVE, "v": 99})),
        (keys.act(run_id, 1), encode(Drive(tick=10**6, t=1.0))),
        (keys.sense(run_id, 1), _raw(**{**GOOD_SENSE, "look": 3})),
    ]
    garbage = [(keys.rod(run_id, 1), b"\x00\x01"), (keys.obs(run_id, 2), _raw(v=1, type="obs")),
               (keys.rod(run_id, 9), _raw(v=1, type="rod", tick=0, length=-1.0, side=1))]
    with zenoh.open(zenoh_config("client", connect=[endpoint], user="follower-1",
                                 password=password)) as session:
        wait_for_world(session, run_id, stop)
        i = 0
        while not stop.is_set() and i < 5000:
            key, payload = bad_queries[i % len(bad_queries)]
            for reply in session.get(key, payload=payload, timeout=2.0):
                counts["errors" if reply.ok is None else "answered"] += 1
            gkey, gpayload = garbage[i % len(garbage)]
            session.put(gkey, gpayload)
            counts["garbage"] += 1
            i += 1


def test_flood_of_malformed_queries_leaves_the_numbers_unchanged(tmp_path):
    cfg = RunConfig(run_id="flood", surface="wavy", followers=8, ticks=60)
    counts = {"errors": 0, "answered": 0, "garbage": 0}
    clean, attacked = run_under_attack(cfg, tmp_path, lambda endpoint, credentials, stop: _attack(
        endpoint, cfg.run_id, stop, counts, credentials.passwords["follower-1"]))
    assert counts["errors"] >= 100 and counts["answered"] == 0, counts  # it overlapped the run
    assert same_results(tmp_path)
    assert attacked["followers"] == clean["followers"]
