"""How a ROS 2 machine joins a live ``swarm run --ros2`` (design §10, docs/ros2.md): the
``--ros2-listen`` flag and the block the launcher prints once the run's router is up.

The block names the endpoint and gives a recipe to paste into a shell of a ROS 2 Jazzy machine:
``RMW_IMPLEMENTATION=rmw_zenoh_cpp``, the run's domain, and ``ZENOH_CONFIG_OVERRIDE`` (read by
``rmw_zenoh_cpp`` 0.2.3 and later: ``;``-separated ``key=json5 value`` pairs applied to its
session configuration) making every ROS 2 process a Zenoh client of the run's router, logged
in as the run's ``observer``: the one user whose access-control rules let it subscribe and
watch the ROS 2 graph, and publish, query or declare nothing (:func:`swarm.deploy.
access_control`). Its password is random, made for this run only.
"""
from __future__ import annotations

import argparse
import json
import re
import socket
import sys

from protocol import ros2

RVIZ_CONFIG = "deploy/rviz/swarm.rviz"  # in a checkout of this repository
OVERRIDE_ENV = "ZENOH_CONFIG_OVERRIDE"
_TCP = re.compile(r"tcp/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*):(?P<port>\d{1,5})")
_ANY_HOST = ("0.0.0.0", "[::]")


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
    match = _TCP.fullmatch(endpoint) if isinstance(endpoint, str) else None
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


def reachable(endpoint: str) -> str:
    """The endpoint another machine connects to for a router listening on ``endpoint``: a
    wildcard host (``0.0.0.0``, ``[::]``) becomes this machine's address on its default
    route (its host name if it has none)."""
    match = _TCP.fullmatch(endpoint)
    if match is None or match["host"] not in _ANY_HOST:
        return endpoint
    return f"tcp/{_host_address()}:{match['port']}"


def _host_address() -> str:
    """This machine's address on its default route: connecting a UDP socket picks the route
    and sends nothing."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1: never reached, only routed
            return probe.getsockname()[0]
    except OSError:
        return socket.gethostname()


def config_override(endpoint: str, user: str, password: str) -> str:
    """The ``ZENOH_CONFIG_OVERRIDE`` value making a ROS 2 process a client of the router at
    ``endpoint``, logged in as ``user``.

    >>> config_override("tcp/10.0.0.5:7447", "observer", "pw")
    'mode="client";connect/endpoints=["tcp/10.0.0.5:7447"];transport/auth/usrpwd/user="observer";transport/auth/usrpwd/password="pw"'
    """
    for name, value in (("user", user), ("password", password)):
        if ";" in value or "'" in value:  # the separator, and the shell's quote
            raise ValueError(f"{name} must not contain ';' or a single quote")
    pairs = {"mode": "client", "connect/endpoints": [endpoint],
             "transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}
    return ";".join(f"{key}={json.dumps(value)}" for key, value in pairs.items())


def join_block(domain: int, endpoint: str, user: str, password: str) -> str:
    """The lines ``swarm run --ros2`` prints: the endpoint, and the recipe for a ROS 2 Jazzy
    machine (rmw_zenoh_cpp 0.2.4-0.2.10) to see the run's topics as ``user`` (read-only)."""
    address = reachable(endpoint)
    local = address.startswith(("tcp/127.", "tcp/localhost:", "tcp/[::1]:"))
    where = ("this machine only; --ros2-listen tcp/0.0.0.0:7447 lets others in" if local
             else "from other machines")
    echo = ros2.agent_topic(1, "pose")
    return "\n".join([
        f"ROS 2: topics on domain {ros2.check_domain(domain)} at {address} ({where}), user "
        f"{user} (read-only, password for this run only)",
        "On a ROS 2 Jazzy machine (rmw_zenoh_cpp 0.2.4-0.2.10), paste:",
        "  source /opt/ros/jazzy/setup.bash",
        f"  export RMW_IMPLEMENTATION=rmw_zenoh_cpp ROS_DOMAIN_ID={domain}",
        f"  export {OVERRIDE_ENV}='{config_override(address, user, password)}'",
        f"  ros2 topic echo {echo}",
        f"  rviz2 -d {RVIZ_CONFIG} --ros-args -p use_sim_time:=true   # from a checkout of "
        "this repository",
    ])


def announce(domain: int, endpoint: str, user: str, password: str) -> None:
    """Print :func:`join_block` on standard output (above any progress bar), flushed."""
    from tqdm import tqdm

    tqdm.write(join_block(domain, endpoint, user, password), file=sys.stdout)
    sys.stdout.flush()
