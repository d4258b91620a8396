"""How a ROS 2 machine joins a run's live topics (design §10, docs/ros2.md): the block that
``swarm run --ros2`` and a hand-started ``python -m world --ros2`` print once the run's router
(or the router the world joined) is up.

The block names the endpoint and gives a recipe to paste into a shell of a ROS 2 Jazzy machine:
``RMW_IMPLEMENTATION=rmw_zenoh_cpp``, the run's domain, and ``ZENOH_CONFIG_OVERRIDE`` (read by
``rmw_zenoh_cpp`` 0.2.3 and later: ``;``-separated ``key=json5 value`` pairs applied to its
session configuration) making every ROS 2 process a Zenoh client of that router; with a user
(``swarm run``: the run's ``observer``, the one user whose access-control rules let it
subscribe and watch the ROS 2 graph, and publish, query or declare nothing,
:func:`swarm.deploy.access_control`; its password random, made for this run only), logged in
as it.
"""
from __future__ import annotations

import json
import re
import socket

from protocol import ros2

RVIZ_CONFIG = "deploy/rviz/swarm.rviz"  # in a checkout of this repository
OVERRIDE_ENV = "ZENOH_CONFIG_OVERRIDE"
TCP_ENDPOINT = re.compile(
    r"tcp/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*):(?P<port>\d{1,5})")
_ANY_HOST = ("0.0.0.0", "[::]")


def reachable(endpoint: str) -> str:
    """The endpoint another machine connects to for a router listening on ``endpoint``: a
    wildcard host (``0.0.0.0``, ``[::]``) becomes this machine's address on its default
    route (its host name if it has none)."""
    match = TCP_ENDPOINT.fullmatch(endpoint)
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


def config_override(endpoint: str, user: str | None = None, password: str | None = None) -> str:
    """The ``ZENOH_CONFIG_OVERRIDE`` value making a ROS 2 process a client of the router at
    ``endpoint``, logged in as ``user`` if given (with ``password``).

    >>> config_override("tcp/10.0.0.5:7447", "observer", "pw")
    'mode="client";connect/endpoints=["tcp/10.0.0.5:7447"];transport/auth/usrpwd/user="observer";transport/auth/usrpwd/password="pw"'
    >>> config_override("tcp/10.0.0.5:7447")
    'mode="client";connect/endpoints=["tcp/10.0.0.5:7447"]'
    >>> config_override("tcp/10.0.0.5:7447';rm -rf ~;'")
    Traceback (most recent call last):
    ...
    ValueError: endpoint must not contain ';' or a single quote
    """
    if (user is None) != (password is None):
        raise ValueError("user and password must be given together")
    pairs: dict[str, object] = {"mode": "client", "connect/endpoints": [endpoint]}
    quoted = (("endpoint", endpoint),) + ((("user", user), ("password", password))
                                          if user is not None else ())
    for name, value in quoted:  # pasted between single quotes, split at ';'
        if ";" in value or "'" in value:
            raise ValueError(f"{name} must not contain ';' or a single quote")
    if user is not None:
        pairs.update({"transport/auth/usrpwd/user": user,
                      "transport/auth/usrpwd/password": password})
    return ";".join(f"{key}={json.dumps(value)}" for key, value in pairs.items())


def join_block(domain: int, endpoint: str, user: str | None = None,
               password: str | None = None, listen_flag: str = "--ros2-listen") -> str:
    """The lines a ``--ros2`` run prints (``swarm run``, and a world started by hand): the
    endpoint, and the recipe for a ROS 2 Jazzy machine (rmw_zenoh_cpp 0.2.4-0.2.10) to see the
    run's topics, as ``user`` (read-only) if given, else with no login. ``listen_flag`` is
    the flag that lets other machines in when ``endpoint`` is a loopback one."""
    address = reachable(endpoint)
    local = address.startswith(("tcp/127.", "tcp/localhost:", "tcp/[::1]:"))
    where = (f"this machine only; {listen_flag} tcp/0.0.0.0:7447 lets others in" if local
             else "from other machines")
    login = (f"user {user} (read-only, password for this run only)" if user is not None
             else "no login (a router that asks for one: add your observer's "
                  "transport/auth/usrpwd/user and password to the override)")
    echo = ros2.agent_topic(1, "pose")
    return "\n".join([
        f"ROS 2: topics on domain {ros2.check_domain(domain)} at {address} ({where}), {login}",
        "On a ROS 2 Jazzy machine (rmw_zenoh_cpp 0.2.4-0.2.10), paste:",
        "  source /opt/ros/jazzy/setup.bash",
        f"  export RMW_IMPLEMENTATION=rmw_zenoh_cpp ROS_DOMAIN_ID={domain}",
        f"  export {OVERRIDE_ENV}='{config_override(address, user, password)}'",
        f"  ros2 topic echo {echo}",
        f"  rviz2 -d {RVIZ_CONFIG} --ros-args -p use_sim_time:=true   # from a checkout of "
        "this repository",
    ])
