"""A run across hosts: the router (the generated TLS + access-control configuration of
``swarm deploy``), the world, the leader and each follower in its own Linux network namespace,
joined to the router's namespace by veth links, every process started with its compose
command. Lockstep numbers equal those of the same deployment on loopback, with plain links
and with ``tc netem`` delay (10 ms) and loss (1%) on every link.

Needs root, ``ip netns`` and veth links; the netem case also needs the kernel's ``sch_netem``.
Each part is skipped, with the reason, where the machine does not allow it. The namespaces,
links and ``/etc/netns/<ns>`` files are made by the test and removed at its end.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from protocol.config import load_config
from tests.deployment import (ROUTER_IN_COMPOSE, Deployment, check_complete_run, free_ports,
                              generate, run_processes)

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


def _loopback_run(deployment: Deployment, volumes: Path) -> Path:
    listen, connect = free_ports()
    commands = {s: deployment.local_command(s, connect, volumes) for s in SERVICES}
    codes, output = run_processes(deployment.router_config(listen), commands, volumes, ROOT,
                                  RUN_TIMEOUT_S)
    assert codes == dict.fromkeys(commands, 0), output
    return Path(deployment.local_path(deployment.option("world", "--out"),
                                      deployment.mounts("world", volumes)))


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
    assert codes == dict.fromkeys(services, 0), output
    return Path(deployment.local_path(deployment.option("world", "--out"),
                                      deployment.mounts("world", volumes)))


@pytest.fixture(scope="module")
def deployment(tmp_path_factory) -> Deployment:
    problem = _netns_problem()
    if problem:
        pytest.skip(f"no run across network namespaces here: {problem}")
    deployment = generate(tmp_path_factory.mktemp("hosts") / "deploy", "hosts", FOLLOWERS)
    with (deployment.folder / "run.toml").open("a") as fh:
        fh.write(NOISE)
    return deployment


@pytest.fixture(scope="module")
def loopback(deployment, tmp_path_factory) -> Path:
    return _loopback_run(deployment, tmp_path_factory.mktemp("loopback"))


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
