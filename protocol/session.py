"""The Zenoh sessions of every process: their configuration (:func:`zenoh_config`, from the
command-line flags of :func:`add_connection_flags` through :func:`connection_config`), opening
one so that Ctrl-C and SIGTERM still act (:func:`open_session`), and the small helpers around
them (free loopback endpoints, a liveliness check, undeclaring)."""
from __future__ import annotations

import argparse
import json
import socket
import threading
from collections.abc import Sequence
from pathlib import Path

import zenoh

MODES = ("peer", "client", "router")

# Largest Zenoh message a link accepts, in bytes (`transport/link/rx/max_message_size`, Zenoh's
# default 1 GiB). Every message of the protocol is far smaller (design §8); a larger one is
# dropped by the receiving link before anything decodes it.
MAX_MESSAGE_SIZE = 1 << 20
MAX_MESSAGE_SIZE_KEY = "transport/link/rx/max_message_size"
TLS_KEY = "transport/link/tls"


def undeclare_all(handles: list) -> None:
    """Undeclare ``handles`` (subscribers, queryables, publishers, tokens), newest first, and
    empty the list; one already gone with a closing session is skipped."""
    for handle in reversed(handles):
        try:
            handle.undeclare()
        except zenoh.ZError:
            pass
    handles.clear()


def scouting_settings(multicast: bool = False) -> dict:
    """The ``scouting`` section. Without multicast a process finds the others only through its
    explicit endpoints, so it has nobody to scout for: ``delay`` 0 stops a router or peer from
    waiting Zenoh's default 500 ms for scouted peers when it opens (0.5 s of every run's
    start-up, most of a short run's wall time)."""
    settings: dict = {"multicast": {"enabled": bool(multicast)}, "gossip": {"enabled": True}}
    if not multicast:
        settings["delay"] = 0
    return settings


def tls_settings(ca: str | Path, cert: str | Path, key: str | Path) -> dict:
    """The ``transport/link/tls`` section for mutual TLS: trust only ``ca``, present ``cert``.

    Used by routers (listen side) and clients (connect side) alike: both verify the other end
    against ``ca``, so a client without a certificate from the deployment's CA is refused.
    """
    cert, key = str(cert), str(key)
    return {"root_ca_certificate": str(ca), "enable_mtls": True,
            "listen_certificate": cert, "listen_private_key": key,
            "connect_certificate": cert, "connect_private_key": key,
            "verify_name_on_connect": True}


def zenoh_config(
    mode: str = "peer",
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    user: str | None = None,
    password: str | None = None,
    connect_timeout: float = 30.0,
    tls_ca: str | Path | None = None,
    tls_cert: str | Path | None = None,
    tls_key: str | Path | None = None,
    max_message_size: int = MAX_MESSAGE_SIZE,
    extra: Sequence[str] = (),
) -> zenoh.Config:
    """Build a session configuration.

    Parameters
    ----------
    mode : {"peer", "client", "router"}
        Zenoh mode; the world acting as embedded router uses ``"router"``.
    listen, connect : sequence of str
        Endpoints such as ``"tcp/127.0.0.1:7447"``. A peer given no listen endpoint listens
        on a free loopback port only (Zenoh's own default is every interface).
    multicast_scouting : bool
        Off by default: every process finds the others through explicit endpoints only.
    user, password : str, optional
        Credentials for a router with user/password authentication.
    connect_timeout : float
        Seconds to keep retrying the connect endpoints at start-up (a process may start
        before the router it connects to); opening fails after that.
    tls_ca, tls_cert, tls_key : path, optional
        Mutual TLS (all three together): the CA certificate that signed the other end's, this
        process's certificate and its private key (PEM). Needed for ``tls/`` endpoints.
    max_message_size : int
        Bytes; larger incoming messages are dropped by the link (:data:`MAX_MESSAGE_SIZE`).
    extra : sequence of str
        ``KEY:VALUE`` pairs inserted with ``insert_json5`` (``--cfg`` of the zenoh examples).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    for name, endpoints in (("listen", listen), ("connect", connect)):
        for endpoint in endpoints:
            if not isinstance(endpoint, str) or "/" not in endpoint:
                raise ValueError(f"{name} endpoint must look like 'tcp/HOST:PORT', "
                                 f"got {endpoint!r}")
    if (user is None) != (password is None):
        raise ValueError("user and password must be given together")
    tls = (tls_ca, tls_cert, tls_key)
    if any(x is not None for x in tls) and any(x is None for x in tls):
        raise ValueError("tls_ca, tls_cert and tls_key must be given together")
    if isinstance(max_message_size, bool) or not isinstance(max_message_size, int) \
            or max_message_size < 1024:
        raise ValueError(f"max_message_size must be an integer >= 1024, got {max_message_size!r}")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting", json.dumps(scouting_settings(multicast_scouting)))
    if mode == "peer" and not listen:
        listen = ["tcp/127.0.0.1:0"]
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        if connect_timeout <= 0:
            raise ValueError(f"connect_timeout must be positive, got {connect_timeout}")
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        conf.insert_json5("connect/timeout_ms", str(int(connect_timeout * 1000)))
        conf.insert_json5("connect/exit_on_failure", "true")
        conf.insert_json5("connect/retry", json.dumps(
            {"period_init_ms": 50, "period_max_ms": 500, "period_increase_factor": 2}))
    if mode == "client" and not connect:
        raise ValueError("client mode needs at least one connect endpoint")
    if user is not None:
        conf.insert_json5(
            "transport/auth/usrpwd", json.dumps({"user": user, "password": password})
        )
    if tls_ca is not None:
        conf.insert_json5(TLS_KEY, json.dumps(tls_settings(tls_ca, tls_cert, tls_key)))
    conf.insert_json5(MAX_MESSAGE_SIZE_KEY, str(max_message_size))
    for item in extra:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise ValueError(f"extra config must be KEY:VALUE, got {item!r}")
        conf.insert_json5(key, value)
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """``zenoh.open(conf)``, waited for in a way Ctrl-C and SIGTERM interrupt: a session whose
    router is not up yet retries inside Zenoh until its connect timeout, where no Python
    signal handler runs, so it is opened in a helper thread. Interrupted, the wait raises
    ``KeyboardInterrupt`` at once (the process is ending; the helper is a daemon)."""
    outcome: list = []

    def open_it() -> None:
        try:
            outcome.append(zenoh.open(conf))
        except zenoh.ZError as exc:
            outcome.append(exc)

    opener = threading.Thread(target=open_it, name="zenoh-open", daemon=True)
    opener.start()
    while opener.is_alive():
        opener.join(0.1)
    if not outcome:
        raise RuntimeError("the Zenoh session could not be opened")
    if isinstance(outcome[0], zenoh.ZError):
        raise outcome[0]
    return outcome[0]


def token_live(session: zenoh.Session, key: str, timeout: float = 0.5) -> bool:
    """Whether a liveliness token on ``key`` is live now (a world or agent id in use)."""
    return any(reply.ok is not None for reply in session.liveliness().get(key, timeout=timeout))


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that is free right now (loopback by default)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/host:port`` endpoint on a port that is free right now (loopback by default)."""
    return f"tcp/{host}:{free_port(host)}"


def add_connection_flags(parser: argparse.ArgumentParser, *,
                         session_modes: tuple[str, ...] = ("client", "peer"),
                         default_mode: str = "client", connect_required: bool = False) -> None:
    """Every command's Zenoh connection flags (:func:`connection_config` reads them):
    ``--connect``, ``--listen``, ``--session-mode`` (one of ``session_modes``), ``--user``
    with ``--password`` or ``--password-file``, ``--tls-ca``/``--tls-cert``/``--tls-key``
    and ``--cfg KEY:VALUE``."""
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        required=connect_required,
                        help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 "
                             "(repeatable)")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to listen on (repeatable)")
    parser.add_argument("--session-mode", choices=session_modes, default=None,
                        help=f"Zenoh session mode [default {default_mode}]")
    parser.add_argument("--user", help="Zenoh user name (router with authentication)")
    secret = parser.add_mutually_exclusive_group()
    secret.add_argument("--password", help="Zenoh password (visible in process listings)")
    secret.add_argument("--password-file", metavar="FILE",
                        help="read the Zenoh password from the first line of FILE")
    parser.add_argument("--tls-ca", metavar="PEM",
                        help="CA certificate for tls/ endpoints (with --tls-cert, --tls-key)")
    parser.add_argument("--tls-cert", metavar="PEM", help="this process's TLS certificate")
    parser.add_argument("--tls-key", metavar="PEM", help="this process's TLS private key")
    parser.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                        help="extra Zenoh configuration, inserted as JSON5")


LOCAL_ROUTER = "tcp/127.0.0.1:7447"
"""Where a hand-started world listens as the run's router unless told otherwise, and where an
agent given no ``--connect`` looks for it."""


def connection_config(args: argparse.Namespace, default_mode: str = "client",
                      connect_timeout: float = 30.0,
                      default_listen: Sequence[str] = (),
                      default_connect: Sequence[str] = ()) -> zenoh.Config:
    """The session configuration the flags of :func:`add_connection_flags` ask for (mode
    ``default_mode`` unless ``--session-mode`` is given, listening on ``default_listen``
    unless ``--listen`` is, connecting to ``default_connect`` unless ``--connect`` or
    ``--listen`` is). ValueError names a bad flag."""
    user, password = credentials(args)
    connect = args.connect or ([] if args.listen else list(default_connect))
    return zenoh_config(args.session_mode or default_mode, connect=connect,
                        listen=args.listen or default_listen, user=user, password=password,
                        connect_timeout=connect_timeout, extra=args.cfg, **tls_options(args))


def credentials(args: argparse.Namespace) -> tuple[str | None, str | None]:
    """(user, password) from the flags of :func:`add_connection_flags` (ValueError if
    unreadable)."""
    password = args.password
    if args.password_file:
        try:
            password = Path(args.password_file).read_text(encoding="utf-8").splitlines()[0].strip()
        except (OSError, IndexError) as exc:
            raise ValueError(f"cannot read a password from {args.password_file}: {exc}") from None
    return args.user, password


def tls_options(args: argparse.Namespace) -> dict[str, str | None]:
    """``tls_ca``, ``tls_cert``, ``tls_key`` for :func:`zenoh_config` from the flags of
    :func:`add_connection_flags` (ValueError unless all three or none are given, or if a file
    is missing)."""
    files = {"tls_ca": args.tls_ca, "tls_cert": args.tls_cert, "tls_key": args.tls_key}
    given = [name for name, path in files.items() if path is not None]
    if given and len(given) != len(files):
        raise ValueError("--tls-ca, --tls-cert and --tls-key must be given together")
    for name, path in files.items():
        if path is not None and not Path(path).is_file():
            raise ValueError(f"--{name.replace('_', '-')}: no such file {path}")
    return files
