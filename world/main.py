"""Entry point of the world process: ``python -m world (--config run.toml | --resume RUN_DIR)
[--out DIR] [--force] [--listen EP] [--connect EP] [--ros2 [--ros-domain N]]``."""
from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import zenoh

from protocol.cli import (
    DONE,
    REFUSED,
    NewFolder,
    Parser,
    add_log_level_flag,
    add_results_flags,
    default_out,
    ends_with,
    exit_process,
    fail,
    program,
    quantity,
    run_command,
    run_failures,
    setup_logging,
)
from protocol.config import RunConfig, config_from_file, dump_config, file_options, with_env_domain
from protocol.distribution import require
from protocol.folder import FolderLock, check_out_dir
from protocol.session import LOCAL_ROUTER, add_connection_flags, connection_config, open_session
from world import checkpoint, geometry
from world.results import run_failure
from world.ros2_join import join_block
from world.service import WorldService
from world.sim import default_max_speed, resolve_leader_start
from world.surfaces import Surface, make_surface, require_surface_extra

DEFAULT_LISTEN = (LOCAL_ROUTER,)
"""Where the world listens as embedded router when given no ``--listen``."""


def resolve_with_surface(config: RunConfig,
                         surface: Surface | None = None) -> tuple[RunConfig, Surface]:
    """Build the run's surface (unless given, already built from ``config``) and fill in what
    the config leaves to it (the leader start, and with ``motion = "drive"`` the default top
    speed); the column at the start must lie on the surface. Everything a run can be refused
    for in its surface, raster or start is refused here (ValueError), before a run writes
    anything."""
    if surface is None:
        surface = make_surface(config.surface, config.surface_params)
    config = config.replace(leader_start=resolve_leader_start(config, surface))
    if config.drives and config.max_speed is None:
        config = config.replace(max_speed=default_max_speed(config, surface))
    start = config.leader_start
    geometry.column(surface, start[:2], start[2:], config.followers, config.spacing,
                    config.side_sign)  # ValueError where it leaves the surface's domain
    return config, surface


def resolve(config: RunConfig) -> RunConfig:
    """The config with the leader start filled in (validates the surface)."""
    return resolve_with_surface(config)[0]


def run_world(config: RunConfig, conf: zenoh.Config, out_dir: str | Path,
              on_tick: Callable[[int], None] | None = None,
              on_ready: Callable[[WorldService], None] | None = None,
              resume: bool = False, force: bool = False,
              lock: FolderLock | None = None, surface: Surface | None = None) -> dict:
    """Run one world on a new session built from ``conf``; return the summary.

    Holds ``out_dir``'s one-writer lock (:class:`protocol.folder.FolderLock`) from before it
    looks at the folder until the results are closed; a caller that took it already (``swarm
    run`` checks the folder under it) passes it as ``lock``. Writes ``config.toml`` (resolved)
    before the first tick. ``on_ready`` gets the service once its queryables and token are
    declared (launchers start agents then, and may ``abort`` it). ``resume`` continues the run
    in ``out_dir`` from its last complete tick. A fresh run refuses a folder that holds results
    already, unless ``force`` (which replaces them).

    ``surface``: the run's surface when the caller built it already (:func:`resolve_with_surface`).

    Raises FolderBusy if another process writes into ``out_dir``, FolderRefused if it holds a
    symbolic link.
    """
    out_dir = Path(out_dir)
    with contextlib.nullcontext() if lock is not None else FolderLock(out_dir, config.run_id):
        config, surface = resolve_with_surface(config, surface)
        if not resume:
            checkpoint.claim(out_dir, force)
            dump_config(config, out_dir / "config.toml")
        with open_session(conf) as session:
            service = WorldService(session, config, surface, out_dir, on_tick=on_tick,
                                   resume=resume)
            try:
                if on_ready is not None:
                    on_ready(service)
                return service.run()
            finally:
                service.close()


def main(argv: list[str] | None = None) -> int:
    p = Parser(
        prog=program("world", "swarm-world"),
        description="The world process: hidden surface, sensing, motion, results.")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--config", help="run configuration TOML")
    source.add_argument("--resume", metavar="RUN_DIR",
                        help="continue the run in RUN_DIR from its last complete tick")
    add_results_flags(p)
    add_connection_flags(p, session_modes=("router", "peer", "client"),
                         default_mode="router, or client with --connect only")
    add_log_level_flag(p)
    p.add_argument("--ros2", action="store_true", default=None,
                   help="also publish the run's ROS 2 topics (rmw_zenoh layout; [ros] extra)")
    p.add_argument("--ros-domain", type=int, help="ROS 2 domain id, 0-232 [default the "
                                                  "config's, else ROS_DOMAIN_ID, else 0]")
    args = p.parse_args(argv)
    setup_logging(args.log_level)
    return run_command(lambda: _serve(args))


def require_extras(config: RunConfig) -> None:
    """Refuse (:class:`protocol.distribution.MissingExtra`) a run whose surface or ROS 2
    publishing needs an extra that is not installed, before anything is written."""
    require_surface_extra(config.surface)
    if config.ros2:
        require("ros")


def config_path(args: argparse.Namespace) -> Path:
    """The run configuration the arguments name: ``--config``, or ``--resume``'s
    ``config.toml``."""
    return Path(args.resume) / "config.toml" if args.resume else Path(args.config)


def ros_options(config: RunConfig, args: argparse.Namespace,
                file: Mapping[str, Any] | None = None) -> RunConfig:
    """``config`` with ``--ros2`` and ``--ros-domain`` applied; where neither the flags nor
    the config file (whose options are ``file``, else read from :func:`config_path`) give the
    domain, ROS 2 publishing takes ``ROS_DOMAIN_ID`` (:func:`protocol.config.with_env_domain`).
    ValueError for ``--ros-domain`` without ROS 2 publishing."""
    flags: dict[str, Any] = {}
    if args.ros2:
        flags["ros2"] = True
    if args.ros_domain is not None:
        flags["ros_domain"] = args.ros_domain
    given = with_env_domain({**(file_options(config_path(args)) if file is None else file),
                             **flags})
    return config.replace(**{k: given[k] for k in ("ros2", "ros_domain") if k in given})


def joins_router(args: argparse.Namespace) -> bool:
    """Whether a hand-started world joins a router as its client (``--connect`` alone) instead
    of being the run's router."""
    return bool(args.connect) and not args.listen


def ros2_endpoint(args: argparse.Namespace) -> str:
    """Where ROS 2 machines reach a hand-started world's topics: the router it joined, else
    the first TCP endpoint it listens on (else its first)."""
    if joins_router(args):
        return args.connect[0]
    listen = args.listen or list(DEFAULT_LISTEN)
    return next((e for e in listen if e.startswith("tcp/")), listen[0])


def waiting_line(config: RunConfig, args: argparse.Namespace, out: str | Path) -> str:
    """What a hand-started world says once it serves the run: where agents reach it, whom it
    waits for and where the results go."""
    if joins_router(args):
        where = "joined the router at " + ", ".join(args.connect)
    else:
        where = "listening on " + ", ".join(args.listen or DEFAULT_LISTEN)
    return (f"world: run {config.run_id} {where}; waiting up to {config.start_timeout:g} s for "
            f"the leader and {quantity(config.followers, 'followers')}; results into {out}")


def _serve(args: argparse.Namespace) -> int:
    """The world process's run, from parsed arguments; its exit status. As embedded router
    (the default) it listens on ``DEFAULT_LISTEN`` unless given ``--listen``; given only
    ``--connect`` it joins that router as a client (e.g. docker-compose's zenohd)."""
    with ends_with(REFUSED, ValueError):
        path = config_path(args)
        file = file_options(path)
        config = ros_options(config_from_file(file, path), args, file)
        require_extras(config)
        surface = resolve_with_surface(config)[1]  # a surface, raster or start refused here
        client = joins_router(args)
        conf = connection_config(args, "client" if client else "router",
                                 default_listen=() if client else DEFAULT_LISTEN)
        out = args.resume or args.out or default_out(config.run_id)
    def ready(service: WorldService) -> None:
        print(waiting_line(config, args, out), flush=True)
        if config.ros2:  # the block swarm run --ros2 prints (design §10)
            print(join_block(config.ros_domain, ros2_endpoint(args), listen_flag="--listen"),
                  flush=True)

    folder = NewFolder(out, config.run_id)
    with folder.undone_if_refused(), run_failures(out):  # a folder in use or holding results,
        # nothing to resume: refused
        with ends_with(REFUSED, ValueError):
            check_out_dir(out, "--resume" if args.resume else "--out")
        try:
            summary = run_world(config, conf, out, resume=bool(args.resume), force=args.force,
                                surface=surface, on_ready=ready)
        except checkpoint.AlreadyComplete as exc:
            print(str(exc), file=sys.stderr)
            return DONE
    if (failure := run_failure(summary)) is not None:
        fail(failure)
    return DONE


def console() -> None:
    """The installed script's entry: :func:`main`, then :func:`protocol.cli.exit_process`."""
    exit_process(main())
