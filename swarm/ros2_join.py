"""``swarm run --ros2``'s side of joining a live run from a ROS 2 machine (design §10,
docs/ros2.md): the ``--ros2-listen`` flag, and printing the join block
(:func:`world.ros2_join.join_block`, which a hand-started world prints too) above the progress
bar once the run's router is up.
"""
from __future__ import annotations

import argparse
import socket
import sys

from world.ros2_join import TCP_ENDPOINT, join_block


def add_ros2_listen_flag(parser: argparse.ArgumentParser) -> None:
    """``--ros2-listen ENDPOINT`` of ``swarm run``."""
    parser.add_argument("--ros2-listen", metavar="ENDPOINT", default=None,
                        help="with --ros2: the run's router also listens on this fixed "
                             "endpoint for ROS 2 machines, e.g. tcp/0.0.0.0:7447; the join recipe "
                             "is printed at start [default only its loopback port]")


def check_ros2_listen(endpoint: str | None, ros2_on: bool) -> str | None:
    """``endpoint`` if it is a ``tcp/HOST:PORT`` endpoint (port 1-65535) given with
    ``--ros2`` where this machine can listen now; None if it is None; else ValueError naming
    ``--ros2-listen``."""
    if endpoint is None:
        return None
    match = TCP_ENDPOINT.fullmatch(endpoint) if isinstance(endpoint, str) else None
    if match is None or not 1 <= int(match["port"]) <= 65535:
        raise ValueError(f"--ros2-listen must be tcp/HOST:PORT (port 1-65535), e.g. "
                         f"tcp/0.0.0.0:7447, got {endpoint!r}")
    if not ros2_on:
        raise ValueError("--ros2-listen needs --ros2 (it is where ROS 2 machines join the "
                         "run's topics)")
    _check_bindable(match["host"].strip("[]"), int(match["port"]), endpoint)
    return endpoint


def _check_bindable(host: str, port: int, endpoint: str) -> None:
    """ValueError unless a TCP socket can listen on ``host:port`` right now (the router
    binds it a moment later: a busy port is refused before anything runs)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port,
                                                             type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as exc:
        raise ValueError(f"--ros2-listen {endpoint}: cannot listen there "
                         f"({exc.strerror or exc})") from None


def announce(domain: int, endpoint: str, user: str, password: str) -> None:
    """Print :func:`join_block` on standard output (above any progress bar), flushed."""
    from tqdm import tqdm

    tqdm.write(join_block(domain, endpoint, user, password), file=sys.stdout)
    sys.stdout.flush()
