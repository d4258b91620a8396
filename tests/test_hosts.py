"""A run across hosts: the router (the generated TLS + access-control configuration of
``swarm deploy``), the world, the leader and each follower in its own Linux network namespace,
joined to the router's namespace by veth links, every process started with its compose
command. Lockstep numbers equal those of the same deployment on loopback, with plain links
and with ``tc netem`` delay (10 ms) and loss (1%) on every link.

Needs root, ``ip netns`` and veth links; the netem case also needs the kernel's ``sch_netem``.
Each part is skipped, with the reason, where the machine does not allow it. The namespaces,
links and ``/etc/netns/<ns>`` files are made by the test and removed at its end.

Realtime mode over delayed links: see :func:`test_realtime_misses_match_the_injected_delay`.
"""
from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from protocol.config import load_config
from tests.delay_relay import main as relay_main
from tests.delay_relay import relay_process
from tests.deployment import (
    ROUTER_IN_COMPOSE,
    Deployment,
    check_complete_run,
    free_ports,
    generate,
    run_processes,
)

ROOT = Path(__file__).resolve().parents[1]
RUN_TIMEOUT_S = 240.0
FOLLOWERS = 2
NOISE = "\nsurface = \"wavy\"\nticks = 24\nseed = 3\nnoise_range = 0.01\nnoise_bearing = 0.005\n"
RESULTS = ("ticks.csv", "observations.csv")
SERVICES = ["world", "leader", *(f"follower-{k}" for k in range(1, FOLLOWERS + 1))]
ROUTER_SCRIPT = """
import sys, zenoh
from pathlib import Path
from tests.deployment import Deployment
with zenoh.open(Deployment(Path(sys.argv[1])).router_config(sys.argv[2])):
    print("router up", flush=True)
    sys.stdin.read()  # until the test closes stdin
"""


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)


def _netns_problem() -> str | None:
    """Why this machine cannot make network namespaces, or None."""
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"swarm-probe-{os.getpid()}"
    made = _ip("netns", "add", probe)
    if made.returncode != 0:
        return f"the kernel refuses network namespaces: {made.stderr.strip()}"
    _ip("netns", "del", probe)
    return None


class Hosts:
    """Namespaces ``<prefix>-<name>``, each joined to ``<prefix>-router`` by a veth link
    10.78.<i>.2 <-> 10.78.<i>.1, where the name ``zenoh`` (the router's, as in the compose
    network and its certificate) resolves to the router's end of the link."""

    def __init__(self, names: list[str]) -> None:
        self.prefix = f"sw{os.getpid() % 100000}"
        self.router = f"{self.prefix}-router"
        self.names = names
        self.made: list[str] = []
        self.etc_made = not Path("/etc/netns").exists()

    def ns(self, name: str) -> str:
        return f"{self.prefix}-{name}"

    def _run(self, *args: str) -> None:
        done = _ip(*args)
        if done.returncode != 0:
            raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")

    def up(self) -> None:
        self._run("netns", "add", self.router)
        self.made.append(self.router)
        self._run("-n", self.router, "link", "set", "lo", "up")
        for i, name in enumerate(self.names, start=1):
            ns, outer, inner = self.ns(name), f"{self.prefix}r{i}", f"{self.prefix}h{i}"
            self._run("netns", "add", ns)
            self.made.append(ns)
            self._run("link", "add", outer, "netns", self.router, "type", "veth", "peer",
                      "name", inner, "netns", ns)
            self._run("-n", self.router, "addr", "add", f"10.78.{i}.1/24", "dev", outer)
            self._run("-n", ns, "addr", "add", f"10.78.{i}.2/24", "dev", inner)
            for where, dev in ((self.router, outer), (ns, inner)):
                self._run("-n", where, "link", "set", dev, "up")
            self._run("-n", ns, "link", "set", "lo", "up")
            etc = Path("/etc/netns") / ns  # `ip netns exec` mounts these over /etc
            etc.mkdir(parents=True, exist_ok=True)
            (etc / "hosts").write_text(f"127.0.0.1 localhost\n10.78.{i}.1 zenoh\n")

    def impair(self, delay_ms: int, loss_pct: float) -> str | None:
        """netem on both ends of every link; the kernel's refusal if it has no netem."""
        for i, name in enumerate(self.names, start=1):
            for where, dev in ((self.router, f"{self.prefix}r{i}"), (self.ns(name),
                                                                    f"{self.prefix}h{i}")):
                done = _ip("netns", "exec", where, "tc", "qdisc", "add", "dev", dev, "root",
                           "netem", "delay", f"{delay_ms}ms", "loss", f"{loss_pct}%")
                if done.returncode != 0:
                    return done.stderr.strip() or "tc failed"
        return None

    def exec(self, name: str, command: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.ns(name) if name != "router" else self.router,
                *command]

    def down(self) -> None:
        for ns in reversed(self.made):
            _ip("netns", "del", ns)  # its veth ends go with it
            shutil.rmtree(Path("/etc/netns") / ns, ignore_errors=True)
        self.made.clear()
        if self.etc_made and Path("/etc/netns").exists() and not any(Path("/etc/netns").iterdir()):
            Path("/etc/netns").rmdir()


def _loopback_run(deployment: Deployment, volumes: Path, hop_ms: float | None = None) -> Path:
    """Run every service on loopback; with ``hop_ms``, each one connects through a relay
    (:mod:`tests.delay_relay`) that delays its link to the router by ``hop_ms`` each way."""
    listen, connect = free_ports()
    relay = (contextlib.nullcontext(None) if hop_ms is None
             else relay_process(f"127.0.0.1:{listen.rpartition(':')[2]}", hop_ms))
    with relay as port:
        if port is not None:
            connect = f"tls/localhost:{port}"
        commands = {s: deployment.local_command(s, connect, volumes) for s in SERVICES}
        codes, output = run_processes(deployment.router_config(listen), commands, volumes, ROOT,
                                      RUN_TIMEOUT_S)
    return _checked_out(deployment, volumes, codes, output)


def _namespaced_run(deployment: Deployment, hosts: Hosts, volumes: Path) -> Path:
    services = SERVICES
    logs = {name: (volumes / f"{name}.log").open("w") for name in ["router", *services]}
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["router"] = subprocess.Popen(
            hosts.exec("router", [sys.executable, "-c", ROUTER_SCRIPT, str(deployment.folder),
                                  "tls/0.0.0.0:7447"]),
            cwd=ROOT, stdin=subprocess.PIPE, stdout=logs["router"], stderr=subprocess.STDOUT)
        for name in services:  # the compose command, connecting to tls/zenoh:7447
            procs[name] = subprocess.Popen(
                hosts.exec(name, deployment.local_command(name, ROUTER_IN_COMPOSE, volumes)),
                cwd=ROOT, stdout=logs[name], stderr=subprocess.STDOUT)
        codes = {name: procs[name].wait(timeout=RUN_TIMEOUT_S) for name in services}
    finally:
        for name, proc in procs.items():
            if name == "router" and proc.poll() is None:
                proc.stdin.close()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    pass
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in logs.values():
            log.close()
    output = {name: (volumes / f"{name}.log").read_text()[-2000:] for name in logs}
    return _checked_out(deployment, volumes, codes, output)


def _checked_out(deployment: Deployment, volumes: Path, codes: dict[str, int],
                 output) -> Path:
    """The world's results folder of a finished run, after checking every service's status:
    0 for each agent, and for the world 0, or 1 exactly when its summary says the formation
    broke (a realtime tick missed leaves its follower out of formation, design §7)."""
    out = Path(deployment.local_path(deployment.option("world", "--out"),
                                     deployment.mounts("world", volumes)))
    summary = out / "summary.json"
    broken = summary.exists() and json.loads(summary.read_text()).get("formation_broken")
    expected = {name: 1 if name == "world" and broken else 0 for name in codes}
    assert codes == expected, output
    return out


@pytest.fixture(scope="module")
def deployment(tmp_path_factory) -> Deployment:
    problem = _netns_problem()
    if problem:
        pytest.skip(f"no run across network namespaces here: {problem}")
    deployment = generate(tmp_path_factory.mktemp("hosts") / "deploy", "hosts", FOLLOWERS)
    deployment.configure((deployment.folder / "run.toml").read_text() + NOISE)
    return deployment


@pytest.fixture(scope="module")
def loopback(deployment, tmp_path_factory) -> Path:
    return _loopback_run(deployment, tmp_path_factory.mktemp("loopback"))


@pytest.mark.slow  # network namespaces; fast tier: the same deployment on loopback (test_deploy)
@pytest.mark.parametrize("links", ["veth", "veth+netem"])
def test_a_run_across_namespaces_matches_loopback(deployment, loopback, tmp_path, links):
    hosts = Hosts(SERVICES)
    try:
        hosts.up()
        if links == "veth+netem":
            refused = hosts.impair(delay_ms=10, loss_pct=1.0)
            if refused:
                pytest.skip(f"tc netem unavailable here (kernel without sch_netem?): {refused}")
        out = _namespaced_run(deployment, hosts, tmp_path)
    finally:
        hosts.down()
    check_complete_run(out, load_config(deployment.folder / "run.toml"))
    for name in RESULTS:
        assert (out / name).read_bytes() == (loopback / name).read_bytes(), name


# --- realtime mode over delayed links --------------------------------------------------------

def test_the_delay_relay_delays_each_direction_and_keeps_order():
    """Through the relay each direction takes at least the delay, bytes arrive in order and
    intact, and a close reaches the other side."""
    delay_s, arrivals, echoed = 0.05, [], []
    with socket.create_server(("127.0.0.1", 0)) as server:
        server.settimeout(10)

        def echo() -> None:
            with server.accept()[0] as conn:
                conn.settimeout(10)
                while data := conn.recv(65536):
                    arrivals.append(time.monotonic())
                    conn.sendall(data)
                echoed.append(True)

        echoer = threading.Thread(target=echo)
        echoer.start()
        try:
            with relay_process(f"127.0.0.1:{server.getsockname()[1]}", delay_s * 1000) as port:
                with socket.create_connection(("127.0.0.1", port), timeout=10) as client:
                    sent = time.monotonic()
                    client.sendall(b"ping")
                    assert client.recv(16) == b"ping"
                    back = time.monotonic()
                    assert arrivals[0] - sent >= delay_s and back - arrivals[0] >= delay_s
                    message = bytes(range(256)) * 4096  # 1 MiB, many chunks
                    client.sendall(message)
                    received = b""
                    while len(received) < len(message):
                        received += client.recv(65536)
                    assert received == message
                    client.shutdown(socket.SHUT_WR)
                    assert client.recv(16) == b""  # the echo server saw the end and closed
        finally:
            echoer.join(timeout=10)
    assert echoed == [True]
    with pytest.raises(ValueError, match="--listen"):
        relay_main(["--listen", "nowhere", "--to", "127.0.0.1:1", "--delay-ms", "1"])
    with pytest.raises(ValueError, match="--delay-ms"):
        relay_main(["--listen", "127.0.0.1:0", "--to", "127.0.0.1:1", "--delay-ms", "-1"])


HOP_MS = 20.0  # one-way delay injected on each process's link to the router, milliseconds
# (20 ms: the margin a period leaves for computing is then 180 ms at least, which a loaded
# 2-core machine once exceeded at 10 ms, missing a tick the delay did not predict)
RT_TICKS, RT_INIT_TICKS = 6, 2
REALTIME = ("\nmode = \"realtime\"\nsurface = \"wavy\"\nseed = 3\nticks = {ticks}\n"
            "init_ticks = {init}\ntime_scale = {scale!r}\n")
LEADER_ROUND_TRIPS = 1  # drive (agents/leader.py)


def follower_round_trips(tick: int, init_ticks: int) -> int:
    """Sequential queries of a follower tick (agents/follower.py): sense, move (from
    ``init_ticks`` on; the reply carries the sensing after it), snap."""
    return 2 if tick < init_ticks else 3


def settle_time(agent: int, tick: int, hop_s: float, init_ticks: int) -> float:
    """Least wall time (s) from the start of a realtime tick until the world has ``agent``
    through it, when every process's link to the router delays each message by ``hop_s`` one
    way (so world <-> agent takes two hops); computing time is not counted.

    The leader learns of the tick (2 hops), drives (a round trip, 4 hops) and publishes its rod
    (2 hops to the world and to follower 1). Follower ``k`` starts when its predecessor's rod
    arrives, makes its round trips one after the other and publishes its observation and rod
    (2 hops to the world and to follower ``k + 1``)."""
    one_way = 2 * hop_s  # world <-> agent, through the router
    elapsed = one_way + LEADER_ROUND_TRIPS * 2 * one_way + one_way
    for _ in range(agent):
        elapsed += follower_round_trips(tick, init_ticks) * 2 * one_way + one_way
    return elapsed


def _missed_cells(out: Path) -> dict[tuple[int, int], bool]:
    """(agent, tick) -> whether the world recorded the agent as having missed the tick."""
    with (out / "ticks.csv").open() as fh:
        return {(int(r["agent"]), int(r["tick"])): r["missed"] == "1" for r in csv.DictReader(fh)}


def _check_realtime_record(out: Path) -> dict[tuple[int, int], bool]:
    """The run is complete and its three records of misses agree (ticks.csv, the summary's
    ``missed_ticks``, and observations.csv, which holds a row exactly for each follower-tick
    not missed); return the misses."""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and summary["ticks_completed"] == RT_TICKS, summary
    missed = _missed_cells(out)
    assert set(missed) == {(a, t) for a in range(FOLLOWERS + 1) for t in range(RT_TICKS)}
    for k in range(1, FOLLOWERS + 1):
        assert summary["followers"][str(k)]["missed_ticks"] == sum(
            missed[(k, t)] for t in range(RT_TICKS)), k
    with (out / "observations.csv").open() as fh:
        observed = {(int(r["agent"]), int(r["tick"])) for r in csv.DictReader(fh)}
    assert observed == {c for c, m in missed.items() if c[0] > 0 and not m}
    return missed


def _made(folder: Path) -> Path:
    folder.mkdir()
    return folder


@pytest.fixture(scope="module")
def realtime_deployment(tmp_path_factory) -> tuple[Deployment, str]:
    """A generated deployment and its generated run.toml (each run appends its options)."""
    deployment = generate(tmp_path_factory.mktemp("realtime") / "deploy", "realtime", FOLLOWERS)
    return deployment, (deployment.folder / "run.toml").read_text()


@pytest.mark.slow  # a paced deployment behind delayed links (the misses of a realtime run:
# test_faults.py, fast)
@pytest.mark.parametrize("links", ["relay", "netem"])
def test_realtime_misses_match_the_injected_delay(realtime_deployment, tmp_path, links):
    """Realtime runs over links delayed by HOP_MS each way miss exactly where the delay
    predicts, and the same tight period without the delay misses nothing.

    The delay is injected from outside, below Zenoh: by ``tests/delay_relay.py`` (every process
    connects through a relay process on loopback that holds each byte HOP_MS in each
    direction), or by ``tc netem`` on both ends of every veth link of the network namespaces.
    Both give every process's link to the router the same one-way delay, so one prediction
    (:func:`settle_time`) serves both. The relay case needs no privileges and no kernel module,
    so it runs everywhere; netem, the real thing, runs where the kernel has ``sch_netem`` and
    namespaces are allowed, and is skipped otherwise. Neither case adds loss: over TCP a lost
    segment waits for a retransmission timeout (200 ms or more), which no period derived from
    a HOP_MS delay can absorb, and the relay cannot lose bytes at all (loss is covered in
    lockstep by ``test_a_run_across_namespaces_matches_loopback``).

    The prediction is a lower bound (computing time only adds to it), so a cell whose
    predicted time is at least twice the period must miss, whatever the machine. A cell
    predicted at most half the period must not: that margin absorbs the computing time of a
    shared, noisy machine. Cells in between are not asserted. Periods: ``max/2`` (the last
    follower must miss each estimating tick, the leader never) and ``2*max`` (nothing may
    miss). The tight period without delay shows that the misses come from the delay.
    """
    deployment, base_toml = realtime_deployment
    comm_period = load_config(deployment.folder / "run.toml").comm_period
    cells = [(a, t) for a in range(FOLLOWERS + 1) for t in range(RT_TICKS)]
    need = {(a, t): settle_time(a, t, HOP_MS / 1000, RT_INIT_TICKS) for a, t in cells}
    tight, loose = max(need.values()) / 2, 2 * max(need.values())
    must_miss = {c for c in cells if need[c] >= 2 * tight}
    must_settle = {c for c in cells if need[c] <= tight / 2}
    assert must_miss and must_settle, "the prediction leaves nothing to check"
    print(f"predicted settle times (ms): { {c: round(v * 1000) for c, v in need.items()} }; "
          f"periods {tight * 1000:.0f} and {loose * 1000:.0f} ms")

    def configure(period_s: float) -> None:
        deployment.configure(base_toml + REALTIME.format(
            ticks=RT_TICKS, init=RT_INIT_TICKS, scale=period_s / comm_period))

    runs: dict[str, Path] = {}
    if links == "relay":
        for name, period, hop in (("tight", tight, HOP_MS), ("loose", loose, HOP_MS)):
            configure(period)
            runs[name] = _loopback_run(deployment, _made(tmp_path / name), hop)
    else:
        problem = _netns_problem()
        if problem:
            pytest.skip(f"no run across network namespaces here: {problem}")
        hosts = Hosts(SERVICES)
        try:
            hosts.up()
            refused = hosts.impair(delay_ms=int(HOP_MS), loss_pct=0.0)
            if refused:
                pytest.skip(f"tc netem unavailable here (kernel without sch_netem?): {refused}")
            for name, period in (("tight", tight), ("loose", loose)):
                configure(period)
                runs[name] = _namespaced_run(deployment, hosts, _made(tmp_path / name))
        finally:
            hosts.down()
    configure(tight)  # the control: the relay adds no delay
    runs["undelayed"] = _loopback_run(deployment, _made(tmp_path / "undelayed"), 0.0)
    missed = {name: _check_realtime_record(out) for name, out in runs.items()}
    print({name: sorted(c for c, m in cells_missed.items() if m)
           for name, cells_missed in missed.items()})
    assert all(missed["tight"][c] for c in must_miss), "predicted misses did not happen"
    assert not any(missed["tight"][c] for c in must_settle), "predicted settles missed"
    assert not any(missed["loose"].values()), "missed with twice the predicted time"
    assert not any(missed["undelayed"].values()), "missed without the delay"
