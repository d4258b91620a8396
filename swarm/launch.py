"""Launch one run: the world as embedded router, the agents as processes or in-process sessions.

``launch(config, out_dir)`` is what ``python -m swarm run`` calls; tests and experiments call it
too. The world runs in the calling process (main thread); agents are either separate
``python -m agents.*`` processes (default) or threads, each with its own Zenoh session.
"""
from __future__ import annotations

import logging
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from agents.follower import run_follower
from agents.leader import run_leader
from agents.link import AgentAbort, RunFinished
from protocol.config import AgentSettings, RunConfig
from protocol.session import free_tcp_endpoint, zenoh_config
from world.main import run_world
from world.service import WorldService

log = logging.getLogger(__name__)

POLL_S = 0.2


def agent_commands(config_path: Path, endpoint: str, n_followers: int) -> list[list[str]]:
    """The command lines of the leader and every follower for a hand-assembled run."""
    base = ["--config", str(config_path), "--connect", endpoint]
    cmds = [[sys.executable, "-m", "agents.leader", *base]]
    cmds += [[sys.executable, "-m", "agents.follower", "--id", str(k), *base]
             for k in range(1, n_followers + 1)]
    return cmds


class _ProcessAgents:
    """Agents as child processes, logs under ``out/logs``; a watcher aborts the world on a crash."""

    def __init__(self, config: RunConfig, out_dir: Path, endpoint: str) -> None:
        self.config, self.out_dir, self.endpoint = config, out_dir, endpoint
        self.procs: list[subprocess.Popen] = []
        self._stop = threading.Event()

    def start(self, service: WorldService) -> None:
        logs = self.out_dir / "logs"
        logs.mkdir(exist_ok=True)
        cmds = agent_commands(self.out_dir / "config.toml", self.endpoint, self.config.followers)
        for k, cmd in enumerate(cmds):
            with open(logs / f"agent-{k}.log", "wb") as log_file:
                self.procs.append(subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT,
                                                   stdin=subprocess.DEVNULL))
        threading.Thread(target=self._watch, args=(service,), daemon=True).start()

    def _watch(self, service: WorldService) -> None:
        while not self._stop.wait(POLL_S):
            for k, proc in enumerate(self.procs):
                code = proc.poll()
                if code not in (None, 0):
                    service.abort(f"agent {k} exited with status {code} "
                                  f"(see {self.out_dir / 'logs' / f'agent-{k}.log'})")
                    return

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        deadline = time.monotonic() + timeout
        for proc in self.procs:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(2.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


class _ThreadAgents:
    """Agents as threads in this process, each with its own Zenoh session."""

    def __init__(self, config: RunConfig, endpoint: str) -> None:
        self.settings = AgentSettings.from_config(config)
        self.endpoint = endpoint
        self.threads: list[threading.Thread] = []
        self.errors: list[str] = []

    def start(self, service: WorldService) -> None:
        bodies: list[Callable[[zenoh.Session], None]] = [
            lambda s: run_leader(s, self.settings)]
        bodies += [lambda s, k=k: run_follower(s, self.settings, k)
                   for k in range(1, self.settings.followers + 1)]
        for k, body in enumerate(bodies):
            thread = threading.Thread(target=self._agent, args=(k, body, service),
                                      name=f"agent-{k}", daemon=True)
            thread.start()
            self.threads.append(thread)

    def _agent(self, k: int, body: Callable[[zenoh.Session], None], service: WorldService) -> None:
        try:
            with zenoh.open(zenoh_config("peer", connect=[self.endpoint])) as session:
                body(session)
        except RunFinished:
            return
        except (AgentAbort, ValueError, RuntimeError) as exc:
            self.errors.append(f"agent {k}: {exc}")
            service.abort(f"agent {k} stopped: {exc}")

    def stop(self, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        for thread in self.threads:
            thread.join(max(0.1, deadline - time.monotonic()))


def new_run_id() -> str:
    """A run id from the wall clock and a few random characters (the id never affects numbers)."""
    import secrets

    return time.strftime("%Y%m%d-%H%M%S") + "-" + secrets.token_hex(3)


def launch(config: RunConfig, out_dir: str | Path, *, in_process: bool = False,
           on_tick: Callable[[int], None] | None = None, endpoint: str | None = None,
           before_agents: Callable[[], None] | None = None) -> dict:
    """Run ``config`` end to end; return the summary (also in ``out_dir/summary.json``).

    The world listens on ``endpoint`` (default: a free loopback port). ``before_agents`` is
    called once the world is up, before the agents start (the live view connects there).

    Raises RuntimeError if the agents do not come up. Ctrl-C stops every agent and leaves a
    partial result marked incomplete.
    """
    out_dir = Path(out_dir)  # run_world resolves the config and writes config.toml first
    endpoint = endpoint or free_tcp_endpoint()
    agents = _ThreadAgents(config, endpoint) if in_process else _ProcessAgents(config, out_dir, endpoint)

    def ready(service: WorldService) -> None:
        if before_agents is not None:
            before_agents()
        agents.start(service)

    try:
        summary = run_world(config, zenoh_config("router", listen=[endpoint]), out_dir,
                            on_tick=on_tick, on_ready=ready)
    except BaseException:  # Ctrl-C or a failure: end every agent now
        agents.stop(timeout=1.0)
        raise
    agents.stop()
    return summary
