"""Entry point of the world process: ``python -m world --config run.toml [--listen EP] [--out DIR]``."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import zenoh

from protocol.cli import (
    EXPECTED_FAILURES, add_log_level_flag, bounded_interrupt, check_out_dir, describe,
    setup_logging,
)
from protocol.config import RunConfig, dump_config, load_config
from protocol.session import add_credential_flags, credentials, tls_options, zenoh_config
from world import checkpoint
from world.service import WorldService
from world.sim import default_max_speed, resolve_leader_start
from world.surfaces import Surface, make_surface


def resolve_with_surface(config: RunConfig) -> tuple[RunConfig, Surface]:
    """Build the run's surface and fill in what the config leaves to it (the leader start,
    and with ``motion = "drive"`` the default top speed)."""
    surface = make_surface(config.surface, config.surface_params)
    config = config.replace(leader_start=resolve_leader_start(config, surface))
    if config.motion == "drive" and config.max_speed is None:
        config = config.replace(max_speed=default_max_speed(config, surface))
    return config, surface


def resolve(config: RunConfig) -> RunConfig:
    """The config with the leader start filled in (validates the surface)."""
    return resolve_with_surface(config)[0]


def default_out(config: RunConfig) -> Path:
    return Path("runs") / config.run_id


def run_world(config: RunConfig, conf: zenoh.Config, out_dir: str | Path,
              on_tick: Callable[[int], None] | None = None,
              on_ready: Callable[[WorldService], None] | None = None,
              resume: bool = False, force: bool = False) -> dict:
    """Run one world on a new session built from ``conf``; return the summary.

    Writes ``config.toml`` (resolved) before the first tick. ``on_ready`` gets the service once
    its queryables and token are declared (launchers start agents then, and may ``abort`` it).
    ``resume`` continues the run in ``out_dir`` from its last complete tick. A fresh run
    refuses a folder that holds results already, unless ``force`` (which replaces them).
    """
    config, surface = resolve_with_surface(config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not resume:
        checkpoint.claim(out_dir, force)
        dump_config(config, out_dir / "config.toml")
    with zenoh.open(conf) as session:
        service = WorldService(session, config, surface, out_dir, on_tick=on_tick, resume=resume)
        try:
            if on_ready is not None:
                on_ready(service)
            return service.run()
        finally:
            service.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="The world process: hidden surface, sensing, motion, results.")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--config", help="run configuration TOML")
    source.add_argument("--resume", metavar="RUN_DIR",
                        help="continue the run in RUN_DIR from its last complete tick")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help="act as embedded Zenoh router listening here (default tcp/127.0.0.1:7447)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="connect as a client to a Zenoh router (e.g. docker-compose's zenohd)")
    p.add_argument("--out", help="results folder (default runs/<run_id>)")
    add_credential_flags(p)
    add_log_level_flag(p)
    p.add_argument("--force", action="store_true",
                   help="replace the results already in --out (default: refuse)")
    args = p.parse_args(argv)
    setup_logging(args.log_level)
    with bounded_interrupt():
        return _serve(args)


def _serve(args: argparse.Namespace) -> int:
    """The world process's run, from parsed arguments; its exit status."""
    out = None
    try:
        config = load_config(Path(args.resume) / "config.toml" if args.resume else args.config)
        user, password = credentials(args)
        if args.connect:
            conf = zenoh_config("client", connect=args.connect, user=user, password=password,
                                extra=args.cfg, **tls_options(args))
        else:
            conf = zenoh_config("router", listen=args.listen or ["tcp/127.0.0.1:7447"],
                                user=user, password=password, extra=args.cfg,
                                **tls_options(args))
        out = check_out_dir(args.resume or args.out or default_out(config),
                            "--resume" if args.resume else "--out")
        summary = run_world(config, conf, out, resume=bool(args.resume), force=args.force)
    except checkpoint.AlreadyComplete as exc:
        print(str(exc), file=sys.stderr)
        return 0
    except OSError as exc:  # the results disk failed during the run (read-only, full)
        where = "" if out is None else f" in {out}"
        print(f"error: cannot write the results{where}: {describe(exc)}", file=sys.stderr)
        return 1
    except EXPECTED_FAILURES as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    if not summary["complete"]:
        print(f"error: run incomplete: {summary['reason']}", file=sys.stderr)
        return 1
    return 0
