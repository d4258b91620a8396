"""Command-line plumbing shared by ``python -m agents.leader`` and ``python -m agents.follower``."""
from __future__ import annotations

import argparse
from collections.abc import Callable

import zenoh

from agents.link import RunFinished
from protocol.cli import (
    FAILED,
    REFUSED,
    add_log_level_flag,
    describe,
    ends_with,
    fail,
    run_command,
    setup_logging,
)
from protocol.config import AgentSettings, load_agent_settings
from protocol.session import add_connection_flags, connection_config, open_session


def parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--config", required=True, help="run configuration (the config.toml of a run)")
    add_connection_flags(p)
    add_log_level_flag(p)
    return p


def run_cli(args: argparse.Namespace, body: Callable[[zenoh.Session, AgentSettings], None]) -> int:
    """Open the session from ``args``, run ``body``; map the outcome to an exit status."""
    setup_logging(args.log_level)
    return run_command(lambda: _run(args, body))


def _run(args: argparse.Namespace, body: Callable[[zenoh.Session, AgentSettings], None]) -> None:
    with ends_with(REFUSED, ValueError):
        settings = load_agent_settings(args.config)
        conf = connection_config(args, connect_timeout=settings.start_timeout)
    try:
        session = open_session(conf)
    except zenoh.ZError as exc:
        where = ", ".join(args.connect) or "the network"
        fail(f"no world reachable at {where} within {settings.start_timeout:g} s (is the world "
             f"or the Zenoh router running there?): {describe(exc)}")
    with ends_with(REFUSED, ValueError), \
            ends_with(FAILED, zenoh.ZError, RuntimeError, OSError):  # AgentAbort: a RuntimeError
        try:
            with session:
                body(session, settings)
        except RunFinished:
            return
