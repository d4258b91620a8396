"""Joining a live ``swarm run --ros2`` from what it prints (design §10, docs/ros2.md): a Zenoh
client configured from the printed block alone, as rmw_zenoh_cpp reads
``ZENOH_CONFIG_OVERRIDE``, receives the run's ROS 2 topics with their attachments and can put,
declare and query nothing into the run; in the slow tier the same from the Zenoh version that
rmw_zenoh_cpp 0.2.5 vendors (eclipse-zenoh 1.4.0, in a venv of its own)."""
from __future__ import annotations

import json
import os
import queue
import re
import socket
import subprocess
import sys
import textwrap
import threading
import time
import venv
from pathlib import Path

import pytest
import zenoh

from protocol import ros2
from protocol.config import RunConfig, dump_config
from protocol.session import free_tcp_endpoint
from swarm.cli import main
from swarm.launch import agent_commands, write_briefs
from swarm.ros2_join import check_ros2_listen
from world.ros2_join import config_override, join_block, reachable

RUN_ID, DOMAIN = "rosjoin", 23
INTRUDER = b"intruder"
RMW_ZENOH_ZENOH = {"0.2.5": "1.4.0", "0.2.9": "1.6.2"}
"""The Zenoh release that rmw_zenoh_cpp releases' ``zenoh_cpp_vendor`` builds (zenoh-c at
1.4.0, 1.6.2), where PyPI has a wheel of it: 0.2.10's 1.8.0 is a source distribution only
(docs/ros2.md)."""


def test_join_block_is_the_recipe():
    block = join_block(7, "tcp/127.0.0.1:7447", "observer", "s3cret")
    lines = block.splitlines()
    assert len(lines) <= 8
    assert "tcp/127.0.0.1:7447" in lines[0] and "this machine only" in lines[0]
    assert "  export RMW_IMPLEMENTATION=rmw_zenoh_cpp ROS_DOMAIN_ID=7" in lines
    override = ("  export ZENOH_CONFIG_OVERRIDE='mode=\"client\";connect/endpoints="
                "[\"tcp/127.0.0.1:7447\"];transport/auth/usrpwd/user=\"observer\";"
                "transport/auth/usrpwd/password=\"s3cret\"'")
    assert override in lines
    assert "  ros2 topic echo /swarm/agent_1/pose" in lines
    assert any(line.startswith("  rviz2 -d deploy/rviz/swarm.rviz") for line in lines)
    assert (Path(__file__).resolve().parents[1] / "deploy/rviz/swarm.rviz").is_file()
    # a router listening on every interface is named by an address others reach
    assert reachable("tcp/0.0.0.0:7447") != "tcp/0.0.0.0:7447"
    assert reachable("tcp/0.0.0.0:7447").endswith(":7447")
    assert reachable("tcp/10.1.2.3:7447") == "tcp/10.1.2.3:7447"
    assert "from other machines" in join_block(7, "tcp/10.1.2.3:7447", "observer", "x")
    with pytest.raises(ValueError, match="password"):
        config_override("tcp/h:1", "observer", "a;b")
    # no login (a hand-started world's router): no credentials in the override, and the line
    # says what to add where a router asks for one
    bare = join_block(7, "tcp/127.0.0.1:7447", listen_flag="--listen").splitlines()
    assert bare[0].endswith("no login (a router that asks for one: add your observer's "
                            "transport/auth/usrpwd/user and password to the override)")
    assert "--listen tcp/0.0.0.0:7447 lets others in" in bare[0]
    assert ("  export ZENOH_CONFIG_OVERRIDE='mode=\"client\";connect/endpoints="
            "[\"tcp/127.0.0.1:7447\"]'") in bare
    assert bare[1:4] == lines[1:4] and bare[5:] == lines[5:]
    with pytest.raises(ValueError, match="together"):
        config_override("tcp/h:1", "observer")


def test_ros2_listen_refusals(tmp_path, capsys):
    assert check_ros2_listen(None, False) is None
    free = free_tcp_endpoint()
    assert check_ros2_listen(free, True) == free
    for bad in ("udp/0.0.0.0:7447", "tcp/0.0.0.0", "tcp/host:0", "tcp/host:70000", "7447"):
        with pytest.raises(ValueError, match="--ros2-listen"):
            check_ros2_listen(bad, True)
    with socket.socket() as busy:  # a port in use is refused before anything runs
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = f"tcp/127.0.0.1:{busy.getsockname()[1]}"
        with pytest.raises(ValueError, match="cannot listen there"):
            check_ros2_listen(taken, True)
        assert main(["run", "--ros2", "--ros2-listen", taken, "--out", str(tmp_path / "b")]) == 2
        assert not (tmp_path / "b").exists()
    out = tmp_path / "run"
    assert main(["run", "--ros2-listen", "tcp/0.0.0.0:7447", "--out", str(out)]) == 2
    assert main(["run", "--ros2", "--ros2-listen", "tcp/x", "--out", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert [line for line in err if line.startswith("error:")][-2:] == [
        "error: --ros2-listen needs --ros2 (it is where ROS 2 machines join the run's topics)",
        "error: --ros2-listen must be tcp/HOST:PORT (port 1-65535), e.g. tcp/0.0.0.0:7447, "
        "got 'tcp/x'"]
    assert not out.exists()


# --- a live run joined from its printed block ----------------------------------------------------


class LiveRun:
    """``python -m swarm run --ros2 --ros2-listen ENDPOINT`` in realtime (about 5 s of wall
    time), or the command ``cmd`` listening on ``endpoint``, its standard output read line by
    line."""

    def __init__(self, out: Path, cmd: list[str] | None = None,
                 endpoint: str | None = None) -> None:
        self.endpoint = endpoint or free_tcp_endpoint()
        cmd = cmd or [sys.executable, "-m", "swarm", "run", "--ros2", "--ros-domain",
                      str(DOMAIN), "--ros2-listen", self.endpoint, "--in-process", "--run-id",
                      RUN_ID, "--followers", "2", "--ticks", "40", "--mode", "realtime",
                      "--time-scale", "0.1", "--out", str(out)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                     stdin=subprocess.DEVNULL, text=True, cwd=out.parent)
        self.lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def printed_block(self, timeout: float = 60.0) -> str:
        """The join block as printed: from its ``ROS 2:`` line through its ``rviz2`` line."""
        deadline, block = time.monotonic() + timeout, []
        while time.monotonic() < deadline:
            line = self.lines.get(timeout=max(0.1, deadline - time.monotonic()))
            assert line is not None, "the run ended without printing the join block"
            if line.startswith("ROS 2: ") or block:
                block.append(line)
            if block and line.startswith("  rviz2 "):
                return "\n".join(block)
        raise AssertionError("no join block within the timeout")

    def block(self, timeout: float = 60.0) -> tuple[int, str]:
        """``(ROS_DOMAIN_ID, ZENOH_CONFIG_OVERRIDE)`` as the printed block gives them."""
        deadline, domain = time.monotonic() + timeout, None
        while time.monotonic() < deadline:
            line = self.lines.get(timeout=max(0.1, deadline - time.monotonic()))
            assert line is not None, "the run ended without printing the join block"
            if match := re.search(r"ROS_DOMAIN_ID=(\d+)", line):
                domain = int(match[1])
            if match := re.fullmatch(r"  export ZENOH_CONFIG_OVERRIDE='(.*)'", line):
                assert domain is not None
                return domain, match[1]
        raise AssertionError("no join block within the timeout")

    def finish(self, timeout: float = 90.0) -> int:
        """The run's exit status, once it ends (killed after ``timeout`` s)."""
        try:
            return self.proc.wait(timeout)
        finally:
            self.close()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


def rmw_zenoh_config(override: str) -> zenoh.Config:
    """A session configuration from ``ZENOH_CONFIG_OVERRIDE`` as rmw_zenoh_cpp applies it
    (``;``-separated pairs, each split at its first ``=``, inserted as JSON5); multicast
    scouting off, as in every test (a client with an endpoint does not scout anyway)."""
    conf = zenoh.Config()
    for pair in override.split(";"):
        key, _, value = pair.partition("=")
        conf.insert_json5(key, value)
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class Samples:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.items: list[tuple[str, bytes, bytes | None, float]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        attachment = None if sample.attachment is None else sample.attachment.to_bytes()
        with self.lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes(), attachment,
                               time.monotonic()))

    def snapshot(self) -> list[tuple[str, bytes, bytes | None, float]]:
        with self.lock:
            return list(self.items)

    def wait(self, predicate, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not predicate(self.snapshot()):
            assert time.monotonic() < deadline, "timed out waiting for samples"
            time.sleep(0.05)


def pose_key(domain: int, agent: int) -> str:
    return ros2.topic_key(domain, ros2.agent_topic(agent, "pose"), "geometry_msgs/msg/PoseStamped",
                          ros2.type_hash("geometry_msgs/msg/PoseStamped"))


def test_a_client_given_only_the_printed_block_reads_and_cannot_write(tmp_path):
    run = LiveRun(tmp_path / "run")
    try:
        domain, override = run.block()
        assert domain == DOMAIN
        assert run.endpoint in override
        reader_got, witness_got, witness_tokens = Samples(), Samples(), Samples()
        with zenoh.open(rmw_zenoh_config(override)) as reader, \
                zenoh.open(rmw_zenoh_config(override)) as witness:
            keep = [reader.declare_subscriber(f"{domain}/**", reader_got),
                    witness.declare_subscriber(f"swarm/{RUN_ID}/**", witness_got),
                    witness.declare_subscriber(f"{domain}/**", witness_got),
                    witness.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**",
                                                            witness_tokens)]
            key = pose_key(domain, 1)
            reader_got.wait(lambda s: sum(k == key for k, *_ in s) >= 3)
            # every sample on the topic carries the attachment rmw_zenoh 0.2.4+ writes
            poses = [(payload, attachment) for k, payload, attachment, _ in
                     reader_got.snapshot() if k == key]
            sequences = [ros2.parse_attachment(attachment)[0] for _, attachment in poses]
            assert sequences == list(range(sequences[0], sequences[0] + len(sequences)))
            message = ros2.typestore().deserialize_cdr(poses[-1][0],
                                                       "geometry_msgs/msg/PoseStamped")
            assert message.header.frame_id == ros2.FRAME
            # the graph: the world's node is visible to a liveliness query
            graph = [str(r.ok.key_expr) for r in
                     reader.liveliness().get(f"@ros2_lv/{domain}/**", timeout=10.0)
                     if r.ok is not None]
            publisher = [t for t in graph if ros2.parse_token(t).topic == "/swarm/agent_1/pose"]
            assert len(publisher) == 1
            assert {ros2.parse_attachment(a)[2] for _, a in poses} == {ros2.gid(publisher[0])}

            # the reader writes into the run: a world tick, a rod, a ROS 2 pose, a token
            start = time.monotonic()
            intruding = [f"swarm/{RUN_ID}/world/tick", f"swarm/{RUN_ID}/agent/1/rod", key]
            keep.append(reader.liveliness().declare_token(
                f"@ros2_lv/{domain}/0123456789abcdef/0/0/NN/%/%/intruder"))
            for _ in range(5):
                for k in intruding:
                    reader.put(k, INTRUDER)
                time.sleep(0.1)
            # ... while the world's samples on those keys still reach the witness
            witness_got.wait(lambda s: {f"swarm/{RUN_ID}/world/tick", key} <= {
                k for k, _, _, t in s if t > start + 0.5})
            assert not [k for k, payload, *_ in witness_got.snapshot() if payload == INTRUDER]
            assert not [k for k, *_ in witness_tokens.snapshot() if "intruder" in k]
            for item in keep:
                item.undeclare()
        code = run.finish()
    finally:
        run.close()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["complete"] is True
    # a tick missed under the machine's load may leave a follower out of formation (design §7)
    assert code == (1 if summary["formation_broken"] else 0)


def test_a_hand_started_world_prints_the_same_block(tmp_path):
    """``python -m world --ros2`` prints the block ``swarm run --ros2`` prints (the one
    :func:`world.ros2_join.join_block`; no login: a router started by hand asks for none,
    and ``--listen`` is its flag to let others in), and a Zenoh client made from the printed
    override alone, as rmw_zenoh_cpp makes it, reads the run's poses."""
    config = RunConfig(run_id=RUN_ID, followers=2, ticks=20, ros2=True, ros_domain=DOMAIN,
                       start_timeout=30.0)
    dump_config(config, tmp_path / "config.toml")
    endpoint, out = free_tcp_endpoint(), tmp_path / "out"
    world = LiveRun(out, [sys.executable, "-m", "world", "--config",
                          str(tmp_path / "config.toml"), "--listen", endpoint, "--out",
                          str(out)], endpoint)
    agents: list[subprocess.Popen] = []
    try:
        block = world.printed_block()
        assert block == join_block(DOMAIN, endpoint, listen_flag="--listen")
        assert "this machine only; --listen tcp/0.0.0.0:7447 lets others in" in block
        [override] = re.findall(r"ZENOH_CONFIG_OVERRIDE='(.*)'", block)
        got = Samples()
        with zenoh.open(rmw_zenoh_config(override)) as reader:
            subscriber = reader.declare_subscriber(pose_key(DOMAIN, 1), got)
            agents = [subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                      for cmd in agent_commands(write_briefs(config, tmp_path), endpoint, 2)]
            got.wait(lambda s: len(s) >= 3)
            subscriber.undeclare()
        assert world.finish() == 0
    finally:
        world.close()
        for agent in agents:
            if agent.poll() is None:
                agent.kill()
            agent.wait(10)
    assert json.loads((out / "summary.json").read_text())["complete"] is True


# --- the versions crossed: rmw_zenoh 0.2.5's Zenoh ---------------------------------------------

SUBSCRIBER = textwrap.dedent("""
    import json, sys, time
    import zenoh
    override, domain, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    conf = zenoh.Config()
    for pair in override.split(";"):
        key, _, value = pair.partition("=")
        conf.insert_json5(key, value)
    conf.insert_json5("scouting/multicast/enabled", "false")
    def on_sample(sample):
        attachment = sample.attachment
        print(json.dumps({"key": str(sample.key_expr),
                          "payload": sample.payload.to_bytes().hex(),
                          "attachment": None if attachment is None
                          else attachment.to_bytes().hex()}), flush=True)
    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(domain + "/**", on_sample)
        time.sleep(seconds)
        subscriber.undeclare()
""")


def zenoh_venv(version: str, cache: Path) -> Path:
    """The python of a venv holding eclipse-zenoh ``version`` alone (its wheel: nothing is
    compiled), made once in ``cache`` (outside the checkout); skips the test when PyPI cannot
    be reached."""
    home = cache / f"eclipse-zenoh-{version}"
    python = home / "bin" / "python"
    ready = home / ".installed"
    if ready.is_file():
        return python
    venv.EnvBuilder(with_pip=True, clear=True).create(home)
    try:
        done = subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-input",
                               "--disable-pip-version-check", "--only-binary", ":all:",
                               f"eclipse-zenoh=={version}"],
                              capture_output=True, text=True, timeout=300)
    except subprocess.TimeoutExpired:
        pytest.skip(f"installing eclipse-zenoh=={version} from PyPI took over 300 s")
    if done.returncode != 0:
        pytest.skip(f"eclipse-zenoh=={version} could not be installed from PyPI (unreachable?):"
                    f" {done.stderr.strip().splitlines()[-1:]}")
    ready.write_text(version)
    return python


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("rmw_zenoh", sorted(RMW_ZENOH_ZENOH))
def test_rmw_zenohs_zenoh_receives_the_topics_with_their_attachments(tmp_path, rmw_zenoh):
    """A subscriber on the Zenoh release ``rmw_zenoh`` vendors, in a venv of its own under
    the user's cache folder (made once), joins a ``--ros2`` run from its printed block."""
    zenoh_version = RMW_ZENOH_ZENOH[rmw_zenoh]
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "koopman-swarm"
    python = zenoh_venv(zenoh_version, cache)
    version = subprocess.run([str(python), "-c", "import importlib.metadata as m; "
                              "print(m.version('eclipse-zenoh'))"], capture_output=True,
                             text=True, timeout=60, check=True).stdout.strip()
    assert version == zenoh_version
    run = LiveRun(tmp_path / "run")
    try:
        domain, override = run.block()
        sub = subprocess.run([str(python), "-c", SUBSCRIBER, override, str(domain), "4"],
                             capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert sub.returncode == 0, sub.stderr[-2000:]
        assert run.finish() == 0
    finally:
        run.close()
    records = [json.loads(line) for line in sub.stdout.splitlines()]
    by_topic: dict[str, list[dict]] = {}
    for record in records:
        by_topic.setdefault(record["key"], []).append(record)
    key = pose_key(domain, 1)
    assert len(by_topic.get(key, [])) >= 3, sorted(by_topic)
    print(f"zenoh {version}: {len(records)} samples on {len(by_topic)} topics")
    expected = {ros2.topic_key(domain, topic, msgtype, ros2.type_hash(msgtype))
                for topic, msgtype in ros2.run_topics(2)}
    assert set(by_topic) <= expected
    assert {ros2.topic_key(domain, "/clock", "rosgraph_msgs/msg/Clock",
                           ros2.type_hash("rosgraph_msgs/msg/Clock")), key} <= set(by_topic)
    store = ros2.typestore()
    for k, items in by_topic.items():
        parsed = [ros2.parse_attachment(bytes.fromhex(r["attachment"])) for r in items]
        sequences = [sequence for sequence, _, _ in parsed]
        assert sequences == list(range(sequences[0], sequences[0] + len(sequences))), k
        assert len({gid for _, _, gid in parsed}) == 1, k
        assert all(abs(stamp / 1e9 - time.time()) < 600 for _, stamp, _ in parsed), k
    poses = [store.deserialize_cdr(bytes.fromhex(r["payload"]), "geometry_msgs/msg/PoseStamped")
             for r in by_topic[key]]
    assert all(p.header.frame_id == ros2.FRAME for p in poses)
