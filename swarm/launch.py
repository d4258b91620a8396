"""Launch one run: the world as embedded router, the agents as processes or in-process sessions.

``launch(config, out_dir)`` is what ``python -m swarm run`` calls; tests and experiments call it
too. The world runs in the calling process (main thread); agents are either separate
``python -m agents.*`` processes (default) or threads, each with its own Zenoh session.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from agents.follower import run_follower
from agents.leader import run_leader
from agents.link import AgentAbort, RunFinished
from protocol.cli import describe, stops_deferred
from protocol.config import AgentSettings, RunConfig
from protocol.folder import FolderLock, open_file
from protocol.messages import safe_text
from protocol.session import free_tcp_endpoint, zenoh_config
from swarm.deploy import (
    OBSERVER,
    agent_briefs,
    agent_user,
    private_dir,
    router_config,
    users,
    write_credentials,
    write_secret,
)
from swarm.ros2_join import announce, check_ros2_listen
from world.main import run_world
from world.service import WorldService
from world.surfaces import Surface

log = logging.getLogger(__name__)

POLL_S = 0.2
STOP_S = 30.0
"""The least time :meth:`_ThreadAgents.stop` waits for the agent threads once their sessions
are closed (at least the run's ``start_timeout``, which bounds a session still opening) before
it gives up on them with :class:`AgentThreadsStuck`; they end in milliseconds."""


class AgentThreadsStuck(RuntimeError):
    """In-process agent threads did not end once their sessions were closed: the interpreter
    must not finalise with one inside Zenoh, which would abort the process."""


def write_briefs(config: RunConfig, folder: Path) -> Path:
    """Write every agent's brief (:class:`protocol.config.AgentBrief`) of the run ``config``
    into ``folder`` (made if need be) as ``<user>.toml`` (``leader.toml``,
    ``follower-K.toml``); return ``folder``. What :func:`agent_commands` gives the agents."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for user, brief in agent_briefs(config).items():
        brief.write(folder / f"{user}.toml")
    return folder


def agent_commands(briefs: Path, endpoint: str, n_followers: int,
                   credentials: RunCredentials | None = None) -> list[list[str]]:
    """The command lines of the leader and every follower for a hand-assembled run, each
    given its own brief in the folder ``briefs`` (:func:`write_briefs`) and, when
    ``credentials`` are given, its own user and password file. No argument holds anything
    but the brief's path and how to connect: never the run's configuration."""
    def base(agent: int) -> list[str]:
        flags = ["--config", str(Path(briefs) / f"{agent_user(agent)}.toml"),
                 "--connect", endpoint]
        if credentials is not None:
            flags += ["--user", agent_user(agent),
                      "--password-file", str(credentials.password_file(agent_user(agent)))]
        return flags

    cmds = [[sys.executable, "-m", "agents.leader", *base(0)]]
    cmds += [[sys.executable, "-m", "agents.follower", "--id", str(k), *base(k)]
             for k in range(1, n_followers + 1)]
    return cmds


@dataclass(frozen=True)
class RunCredentials:
    """Random per-run credentials of ``swarm run``'s embedded router, in a private folder.

    ``folder`` (mode 0700) holds ``credentials.txt`` (the router's dictionary) and one
    ``<user>.password`` file per user (mode 0600): every agent, and ``observer`` for a viewer
    that attaches to the run. No one gets the world's: the world is the router itself.
    """

    folder: Path
    passwords: dict[str, str]

    @classmethod
    def create(cls, folder: Path, followers: int) -> RunCredentials:
        private_dir(folder)
        names = [user for user in users(followers) if user != "world"]
        passwords = write_credentials(folder, names)
        for user, password in passwords.items():
            write_secret(folder / f"{user}.password", password + "\n")
        return cls(folder, passwords)

    @property
    def dictionary(self) -> Path:
        return self.folder / "credentials.txt"

    def password_file(self, user: str) -> Path:
        if user not in self.passwords:
            raise ValueError(f"user must be one of {sorted(self.passwords)}, got {user!r}")
        return self.folder / f"{user}.password"


def embedded_router_config(config: RunConfig, endpoint: str, credentials: RunCredentials,
                           ros2_listen: str | None = None) -> zenoh.Config:
    """The world's router configuration for ``swarm run``: listens on ``endpoint`` (and on
    ``ros2_listen``, where ROS 2 machines join), admits only the run's users, with the
    access-control rules of a deployment (swarm/deploy.py)."""
    return zenoh.Config.from_json5(json.dumps(router_config(
        config.run_id, config.followers, listen=[endpoint, *filter(None, [ros2_listen])],
        dictionary_file=str(credentials.dictionary), ros_domain=config.ros_domain,
        drive=config.drives)))


def last_error_line(log: Path, limit: int = 240) -> str | None:
    """The last ``error: ...`` line an agent process wrote to ``log`` (its one-line report of
    why it stopped), without the prefix and at most ``limit`` characters; None if there is
    none or the log cannot be read."""
    try:
        with open(log, "rb") as f:
            f.seek(max(0, f.seek(0, 2) - 8192))
            lines = f.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return None
    said = next((line[len("error:"):].strip() for line in reversed(lines)
                 if line.startswith("error:")), None)
    if not said:
        return None
    said = safe_text(said)
    return said if len(said) <= limit else said[:limit - 3] + "..."


class _ProcessAgents:
    """Agents as child processes, logs under ``out/logs``; a watcher aborts the world on a crash."""

    def __init__(self, config: RunConfig, out_dir: Path, endpoint: str,
                 credentials: RunCredentials) -> None:
        self.config, self.out_dir, self.endpoint = config, out_dir, endpoint
        self.credentials = credentials
        self.procs: list[subprocess.Popen] = []
        self._stop = threading.Event()

    def start(self, service: WorldService) -> None:
        # each agent reads its brief from the run's private folder, never the config.toml of
        # the results folder (the world's secrets); a follower keeps its state there too
        briefs = write_briefs(service.config, self.credentials.folder)
        cmds = agent_commands(briefs, self.endpoint, self.config.followers, self.credentials)
        with stops_deferred():  # every agent started is in self.procs, for stop() to end
            self._spawn(cmds)
        threading.Thread(target=self._watch, args=(service,), daemon=True).start()

    def _spawn(self, cmds: list[list[str]]) -> None:
        for k, cmd in enumerate(cmds):
            log_fd = open_file(self.out_dir / "logs" / f"agent-{k}.log",
                               os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            with os.fdopen(log_fd, "wb") as log_file:
                # a session of its own: a terminal's Ctrl-C reaches the launcher only, which
                # ends the run and then its agents in order (no agent vanishes mid-tick)
                self.procs.append(subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT,
                                                   stdin=subprocess.DEVNULL,
                                                   start_new_session=True))

    def _watch(self, service: WorldService) -> None:
        """End the run when an agent fails; in realtime an agent killed by a signal is only
        reported: the world records its ticks as missed and the run goes on (design §4)."""
        dead: set[int] = set()
        while not self._stop.wait(POLL_S):
            for k, proc in enumerate(self.procs):
                code = proc.poll()
                if code in (None, 0) or k in dead:
                    continue
                path = self.out_dir / "logs" / f"agent-{k}.log"
                said = last_error_line(path)
                why = (f"agent {k} exited with status {code}" + (f": {said}" if said else "")
                       + f" (see {path})")
                if self.config.mode == "realtime" and code < 0:
                    dead.add(k)
                    log.warning("%s; the run goes on without it, its ticks recorded as missed",
                                why)
                    continue
                service.abort(why)
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


SESSIONS_PER_PROCESS = 300
"""Zenoh sessions one process opened reliably here: client sessions to the same router
stopped opening at the 351st, whatever the file descriptors in use (``zenoh`` 1.x)."""


class _ThreadAgents:
    """Agents as threads in this process, each with its own Zenoh session."""

    def __init__(self, endpoint: str, credentials: RunCredentials) -> None:
        self.endpoint = endpoint
        self.credentials = credentials
        self.threads: list[threading.Thread] = []
        self.sessions: dict[int, zenoh.Session] = {}
        self._lock = threading.Lock()  # guards sessions and _stopping
        self._stopping = False
        self.settings: AgentSettings | None = None  # set by start

    def start(self, service: WorldService) -> None:
        # what the world resolved (e.g. a drive run's default top speed), as the processes
        # read it from the briefs written from it (one interpreter: plug-ins are trusted code)
        self.settings = AgentSettings.from_config(service.config)
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
            user = agent_user(k)
            # the router is up before the agents start: a session that does not open within
            # half the start timeout will not, and saying so first names the real cause
            with zenoh.open(zenoh_config("client", connect=[self.endpoint], user=user,
                                         password=self.credentials.passwords[user],
                                         connect_timeout=self.settings.start_timeout / 2)
                            ) as session:
                with self._lock:
                    self.sessions[k] = session
                    if self._stopping:  # stopped while the session opened: nothing to do
                        return
                body(session)
        except RunFinished:
            return
        except (AgentAbort, ValueError, RuntimeError) as exc:
            service.abort(f"agent {k} stopped: {exc}")
        except zenoh.ZError as exc:  # its session did not open (or broke)
            service.abort(f"agent {k}'s Zenoh session failed: {describe(exc)}"
                          + (f" ({self.settings.followers + 1} agents share this process: "
                             "use the process layout for runs this large)"
                             if self.settings.followers + 1 > SESSIONS_PER_PROCESS else ""))

    def stop(self, timeout: float = 10.0) -> None:
        """Wait up to ``timeout`` s for the agents to end by themselves; then close the session
        of every one still running, which ends it (every wait of its link ends when its session
        goes, and a session still opening is closed as soon as it opens); then wait for every
        agent thread to end, up to :data:`STOP_S` (at least the run's ``start_timeout``).

        No agent thread outlives this: one still in Zenoh's native code when the interpreter
        finalises would abort the process as it takes the GIL back. Each ends only once Zenoh
        has let go of its link's callbacks (:meth:`agents.link.AgentLink.close`), so no Zenoh
        thread calls into the interpreter after it either.

        Raises
        ------
        AgentThreadsStuck
            If a thread is still running after that wait (never expected: a Zenoh bug).
        """
        deadline = time.monotonic() + timeout
        for thread in self.threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        with self._lock:
            self._stopping = True
            running = [self.sessions[k] for k, thread in enumerate(self.threads)
                       if thread.is_alive() and k in self.sessions]
        for session in running:
            with contextlib.suppress(zenoh.ZError):
                session.close()
        limit = max(STOP_S, self.settings.start_timeout if self.settings is not None else 0.0)
        deadline = time.monotonic() + limit
        for thread in self.threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        stuck = [thread.name for thread in self.threads if thread.is_alive()]
        if stuck:
            raise AgentThreadsStuck(f"in-process agent thread(s) {', '.join(stuck)} still "
                                    f"running {limit:g} s after their sessions were closed")


def new_run_id() -> str:
    """A run id from the wall clock and a few random characters (the id never affects numbers)."""
    import secrets

    return time.strftime("%Y%m%d-%H%M%S") + "-" + secrets.token_hex(3)


def launch(config: RunConfig, out_dir: str | Path, *, in_process: bool = False,
           on_tick: Callable[[int], None] | None = None, endpoint: str | None = None,
           credentials_dir: str | Path | None = None,
           credentials: RunCredentials | None = None,
           before_agents: Callable[[RunCredentials], None] | None = None,
           force: bool = False, lock: FolderLock | None = None,
           surface: Surface | None = None, ros2_listen: str | None = None) -> dict:
    """Run ``config`` end to end; return the summary (also in ``out_dir/summary.json``).

    The world listens on ``endpoint`` (default: a free loopback port) as a router that admits
    only this run's users, each with a random password (:class:`RunCredentials`), under the
    access-control rules of a deployment. The credentials are written to ``credentials_dir``
    (created, mode 0700; it must not exist), by default to a temporary folder removed at the
    end; or ``credentials`` made beforehand with :meth:`RunCredentials.create` are used.
    ``before_agents`` is called with them once the world is up, before the agents start
    (the live view connects there, as the ``observer`` user). A folder that holds results
    is refused unless ``force`` (which replaces them). ``lock``: the folder's one-writer lock,
    when the caller holds it already, and ``surface``, when the caller built it (see
    :func:`world.main.run_world`).

    Raises RuntimeError if the agents do not come up. Ctrl-C stops every agent and leaves a
    partial result marked incomplete.

    With ``config.ros2`` the router also listens on ``ros2_listen`` (a ``tcp/HOST:PORT``
    endpoint, :func:`swarm.ros2_join.check_ros2_listen`) if given, and once it is up the
    recipe for a ROS 2 machine to join as the observer is printed
    (:func:`swarm.ros2_join.announce`).
    """
    out_dir = Path(out_dir)  # run_world resolves the config and writes config.toml first
    check_ros2_listen(ros2_listen, config.ros2)
    endpoint = endpoint or free_tcp_endpoint()
    with contextlib.ExitStack() as scratch:  # a temporary folder is removed at the end
        if credentials is None:
            folder = Path(credentials_dir) if credentials_dir is not None else Path(
                scratch.enter_context(tempfile.TemporaryDirectory(prefix="swarm-credentials-"))
            ) / "run"
            credentials = RunCredentials.create(folder, config.followers)
        return _launch(config, out_dir, in_process, on_tick, endpoint, credentials,
                       before_agents, force, lock, surface, ros2_listen)


def _launch(config: RunConfig, out_dir: Path, in_process: bool,
            on_tick: Callable[[int], None] | None, endpoint: str,
            credentials: RunCredentials,
            before_agents: Callable[[RunCredentials], None] | None = None,
            force: bool = False, lock: FolderLock | None = None,
            surface: Surface | None = None, ros2_listen: str | None = None) -> dict:
    agents = (_ThreadAgents(endpoint, credentials) if in_process
              else _ProcessAgents(config, out_dir, endpoint, credentials))
    log.info("run %s: credentials in %s (observer: %s)", config.run_id, credentials.folder,
             credentials.password_file(OBSERVER))

    def ready(service: WorldService) -> None:
        if config.ros2:
            announce(config.ros_domain, ros2_listen or endpoint, OBSERVER,
                     credentials.passwords[OBSERVER])
        if before_agents is not None:
            before_agents(credentials)
        agents.start(service)

    try:
        summary = run_world(config, embedded_router_config(config, endpoint, credentials,
                                                           ros2_listen),
                            out_dir, on_tick=on_tick, on_ready=ready, force=force,
                            lock=lock, surface=surface)
    except BaseException:  # Ctrl-C or a failure: end every agent now
        try:
            agents.stop(timeout=1.0)
        except AgentThreadsStuck as stuck:  # the failure's own reason is the one to tell
            log.error("%s", stuck)
        raise
    # a run that ended incomplete has no world left for its agents to wait for
    agents.stop(timeout=10.0 if summary["complete"] else 1.0)
    return summary
