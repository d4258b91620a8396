"""Test support: a deployment written by ``python -m swarm deploy``, run here without Docker.

The router is a Zenoh session opened in router mode from the deployment's ``zenoh/router.json5``
(the file the compose ``zenoh`` service runs), its listen endpoint moved to a free loopback port
and every path mapped through the compose volumes that mount it. Clients connect to
``tls/localhost:PORT`` with the files each compose service mounts.
"""
from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import yaml
import zenoh

from protocol.config import RunConfig, dump_config
from protocol.session import free_port, free_tcp_endpoint, zenoh_config
from swarm.cli import main as swarm_main
from swarm.launch import agent_commands, write_briefs
from tests import waiting

ROUTER_IN_COMPOSE = "tls/zenoh:7447"
WAIT_S = 15.0  # upper bound of every wait for something that must happen (a loaded machine)
ABSENT_S = 0.5  # how long a message that must not arrive is given to arrive anyway
ROUTER_PATH_KEYS = ("transport/auth/usrpwd/dictionary_file",
                    *(f"transport/link/tls/{name}" for name in (
                        "root_ca_certificate", "listen_certificate", "listen_private_key",
                        "connect_certificate", "connect_private_key")))


def generate(out: Path, run_id: str, followers: int) -> Deployment:
    """Write a deployment with the command an operator runs; fail if it does not succeed."""
    code = swarm_main(["deploy", "--followers", str(followers), "--run-id", run_id,
                       "--out", str(out)])
    if code != 0:
        raise RuntimeError(f"python -m swarm deploy exited with {code}")
    return Deployment(out)


def free_ports() -> tuple[str, str]:
    """(listen, connect) endpoints of a free loopback port for a TLS router."""
    port = free_port()
    return f"tls/127.0.0.1:{port}", f"tls/localhost:{port}"


class Deployment:
    """The files of one generated deployment, seen from this machine."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.compose = yaml.safe_load((folder / "docker-compose.yml").read_text())
        self.services = self.compose["services"]

    def configure(self, text: str) -> None:
        """Make ``text`` the deployment's ``run.toml`` and write the agents' briefs anew from
        it, as deploy/README.md tells an operator who adds options."""
        (self.folder / "run.toml").write_text(text)
        code = swarm_main(["agent-config", str(self.folder / "run.toml"), "--all", "--out",
                           str(self.folder / "agents")])
        if code != 0:
            raise RuntimeError(f"python -m swarm agent-config exited with {code}")

    def mounts(self, service: str, volumes_dir: Path) -> dict[str, Path]:
        """Container path -> local path of ``service``'s volumes; named ones in ``volumes_dir``."""
        mounts = {}
        for spec in self.services[service].get("volumes", []):
            source, target = spec.split(":")[:2]
            mounts[target] = (self.folder / source if source.startswith(".")
                              else volumes_dir / source)
        return mounts

    @staticmethod
    def local_path(arg: str, mounts: dict[str, Path]) -> str:
        """``arg`` with a container path replaced by the local path mounted there."""
        for target, local in mounts.items():
            if arg == target or arg.startswith(target + "/"):
                return str(local / Path(arg).relative_to(target))
        return arg

    def option(self, service: str, flag: str) -> str:
        command = self.services[service]["command"]
        return command[command.index(flag) + 1]

    def local_command(self, service: str, endpoint: str, volumes_dir: Path) -> list[str]:
        """The compose ``command`` of ``service``, runnable here against ``endpoint``."""
        mounts = self.mounts(service, volumes_dir)
        program, *args = self.services[service]["command"]
        if program != "python":
            raise ValueError(f"service {service!r} does not run python: {program!r}")
        return [sys.executable] + [endpoint if a == ROUTER_IN_COMPOSE
                                   else self.local_path(a, mounts) for a in args]

    def router_config(self, listen: str) -> zenoh.Config:
        """The compose router's configuration, listening on ``listen``, with local paths."""
        mounts = self.mounts("zenoh", Path("/nonexistent"))  # the router has no named volume
        path = self.local_path(self.option("zenoh", "-c"), mounts)
        conf = zenoh.Config.from_json5(Path(path).read_text())
        for key in ROUTER_PATH_KEYS:
            conf.insert_json5(key, json.dumps(self.local_path(json.loads(conf.get_json(key)),
                                                              mounts)))
        conf.insert_json5("listen/endpoints", json.dumps([listen]))
        return conf

    def secret(self, user: str, name: str) -> Path:
        return self.folder / "secrets" / user / name

    def password(self, user: str) -> str:
        return self.secret(user, "password").read_text().strip()

    def client(self, endpoint: str, user: str, *, password: str | None = None,
               identity: str | None = None, connect_timeout: float = WAIT_S) -> zenoh.Session:
        """A client session as ``user`` (its password unless another is given), presenting the
        TLS certificate of ``identity`` (default: the user's own)."""
        identity = identity or user
        return zenoh.open(zenoh_config(
            "client", connect=[endpoint], user=user,
            password=self.password(user) if password is None else password,
            connect_timeout=connect_timeout, tls_ca=self.secret(identity, "ca.pem"),
            tls_cert=self.secret(identity, "cert.pem"), tls_key=self.secret(identity, "key.pem")))


def run_processes(router: zenoh.Config, commands: dict[str, list[str]], logs: Path, cwd: Path,
                  timeout: float) -> tuple[dict[str, int], dict[str, str]]:
    """Start ``router``, run every command to its end (killed after ``timeout`` seconds in
    all); return the exit codes and the tail of each output, by name."""
    procs, files = {}, {}
    with zenoh.open(router):
        try:
            for name, command in commands.items():
                files[name] = logs / f"{name}.log"
                with files[name].open("w") as log:
                    procs[name] = subprocess.Popen(command, cwd=cwd, stdout=log,
                                                   stderr=subprocess.STDOUT)
            deadline = time.monotonic() + timeout
            codes = {name: proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                     for name, proc in procs.items()}
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
    return codes, {name: path.read_text()[-2000:] for name, path in files.items()}


def check_complete_run(out: Path, config) -> None:
    """``out`` holds a complete run of ``config``: every tick, every follower estimating from
    the end of its initial ticks, none missed (ValueError naming what is wrong otherwise)."""
    summary = json.loads((out / "summary.json").read_text())
    followers = {str(k) for k in range(1, config.followers + 1)}
    problems = []
    if not summary["complete"] or summary["ticks_completed"] != config.ticks:
        problems.append(f"complete={summary['complete']}, ticks={summary['ticks_completed']}")
    if set(summary["followers"]) != followers:
        problems.append(f"followers {sorted(summary['followers'])}")
    expected = (config.ticks - config.init_ticks, 0)
    for k, stats in summary["followers"].items():
        if (stats["estimated_ticks"], stats["missed_ticks"]) != expected:
            problems.append(f"follower {k}: {stats['estimated_ticks']} estimated, "
                            f"{stats['missed_ticks']} missed")
    if problems:
        raise ValueError(f"run in {out} is not complete: {'; '.join(problems)}")


class Inbox:
    """What a subscriber or liveliness subscriber received: (key, payload) pairs, with waits."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cond.notify_all()

    def wait_for(self, item: tuple[str, bytes], timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: item in self.items, timeout)

    def keys(self) -> set[str]:
        with self._cond:
            return {key for key, _ in self.items}


def until(condition: Callable[[], bool], timeout: float = WAIT_S) -> bool:
    """:func:`tests.waiting.until` with this module's default bound."""
    return waiting.until(condition, timeout)


def delivered(send: Callable[[], None], inbox: Inbox, item: tuple[str, bytes]) -> bool:
    """Send until ``item`` arrives (routes are declared asynchronously); False on timeout."""
    def attempt() -> bool:
        send()
        return inbox.wait_for(item, 0.1)
    return until(attempt)


def replies(session: zenoh.Session, key: str, timeout: float = 1.0) -> list[tuple[bool, bytes]]:
    """Every reply to a query on ``key`` from every queryable (no consolidation): (ok, payload)."""
    answers = session.get(key, target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
    return [(True, r.ok.payload.to_bytes()) if r.ok is not None
            else (False, r.err.payload.to_bytes()) for r in answers]


def hand_started(folder: Path, config: RunConfig) -> list[subprocess.Popen]:
    """A world started by hand (``python -m world`` on a free loopback port) and its agents
    (leader first), as a deployment starts them: its results go to ``folder / "out"``; the
    world's stderr is piped (text), the rest discarded. The caller ends them."""
    dump_config(config, folder / "config.toml")
    endpoint = free_tcp_endpoint()
    world = subprocess.Popen([sys.executable, "-m", "world", "--config",
                              str(folder / "config.toml"), "--listen", endpoint, "--out",
                              str(folder / "out")], cwd=waiting.ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return [world] + [subprocess.Popen(cmd, cwd=waiting.ROOT, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.DEVNULL)
                      for cmd in agent_commands(write_briefs(config, folder), endpoint,
                                                config.followers)]
