"""Command-line plumbing shared by ``python -m agents.leader`` and ``python -m agents.follower``.

An agent process reads only its brief (:class:`protocol.config.AgentBrief`): what that robot
knows, never the world's secrets. A run's configuration given in its place is refused in one
line that says how to make the brief (design §9).
"""
from __future__ import annotations

import argparse
from collections.abc import Callable

import zenoh

from agents.link import RunFinished
from protocol.cli import (
    FAILED,
    REFUSED,
    Parser,
    add_log_level_flag,
    describe,
    ends_with,
    fail,
    refuse,
    run_command,
    setup_logging,
)
from protocol.config import BRIEF_COMMAND, AgentBrief
from protocol.session import LOCAL_ROUTER, add_connection_flags, connection_config, open_session


def parser(program: str, description: str) -> argparse.ArgumentParser:
    """The flags every agent takes; ``program`` is how usage and errors name it
    (``python -m agents.follower``), whichever way it was started."""
    p = Parser(prog=program, description=description)
    p.add_argument("--config", required=True, metavar="BRIEF",
                   help="this agent's brief: what the robot is told, never the run's "
                        f"config.toml (make it with `{BRIEF_COMMAND} RUN.toml --id K`)")
    add_connection_flags(p)
    add_log_level_flag(p)
    return p


def run_cli(args: argparse.Namespace, agent: int | None,
            body: Callable[[zenoh.Session, AgentBrief], None]) -> int:
    """Read the brief of ``args.config`` (it must be agent ``agent``'s; None: any follower's),
    open the session from ``args``, run ``body``; map the outcome to an exit status."""
    setup_logging(args.log_level)
    return run_command(lambda: _run(args, agent, body))


def _run(args: argparse.Namespace, agent: int | None,
         body: Callable[[zenoh.Session, AgentBrief], None]) -> None:
    with ends_with(REFUSED, ValueError):
        brief = AgentBrief.load(args.config)
        if brief.agent != agent and (agent is not None or brief.agent == 0):
            refuse(f"{args.config} is {_whose(brief.agent)} brief, not {_whose(agent)}")
        settings = brief.settings
        # a client given no endpoint looks where a hand-started world listens by default
        local = (LOCAL_ROUTER,) if (args.session_mode or "client") == "client" else ()
        conf = connection_config(args, connect_timeout=settings.start_timeout,
                                 default_connect=local)
    try:
        session = open_session(conf)
    except zenoh.ZError as exc:
        where = ", ".join(args.connect or (() if args.listen else local)) or "the network"
        fail(f"no world reachable at {where} within {settings.start_timeout:g} s (is the world "
             f"or the Zenoh router running there?): {describe(exc)}")
    with ends_with(REFUSED, ValueError), \
            ends_with(FAILED, zenoh.ZError, RuntimeError, OSError):  # AgentAbort: a RuntimeError
        try:
            with session:
                body(session, brief)
        except RunFinished:
            return


def _whose(agent: int | None) -> str:
    """``"the leader's"``, ``"follower K's"``, or for None ``"a follower's"``."""
    return "a follower's" if agent is None else (
        "the leader's" if agent == 0 else f"follower {agent}'s")
