"""Command-line plumbing shared by ``python -m agents.leader`` and ``python -m agents.follower``."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

import zenoh

from agents.link import AgentAbort, RunFinished
from protocol.cli import add_log_level_flag, bounded_interrupt, describe, setup_logging
from protocol.config import AgentSettings, load_agent_settings
from protocol.session import add_credential_flags, credentials, tls_options, zenoh_config


def parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--config", required=True, help="run configuration (the config.toml of a run)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--mode", choices=("peer", "client"), default="client")
    add_credential_flags(p)
    add_log_level_flag(p)
    return p


def run_cli(args: argparse.Namespace, body: Callable[[zenoh.Session, AgentSettings], None]) -> int:
    """Open the session from ``args``, run ``body``; map the outcome to an exit status."""
    setup_logging(args.log_level)
    try:
        settings = load_agent_settings(args.config)
        user, password = credentials(args)
        conf = zenoh_config(args.mode, connect=args.connect, listen=args.listen, user=user,
                            password=password, connect_timeout=settings.start_timeout,
                            extra=args.cfg, **tls_options(args))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        where = ", ".join(args.connect) or "the network"
        print(f"error: no world reachable at {where} within {settings.start_timeout:g} s "
              f"(is the world or the Zenoh router running there?): {describe(exc)}",
              file=sys.stderr)
        return 1
    try:
        with bounded_interrupt(), session:  # Ctrl-C: the session closes, or 130 within 8 s
            body(session, settings)
    except zenoh.ZError as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 1
    except ValueError as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 2
    except RunFinished:
        return 0
    except (AgentAbort, RuntimeError, OSError) as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0
