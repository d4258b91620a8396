"""Generated, locked-down deployments (``python -m swarm deploy``, deploy/README.md).

One run id and a number of followers determine everything but the secrets:

- :func:`access_control`: the router's rules, one subject and one policy per user, every key
  under ``swarm/<run>/`` (no wildcard over run ids). Users: ``world``, ``leader`` (agent 0),
  ``follower-K`` and ``observer`` (subscribe only).
- :func:`router_config`: the router's whole configuration (listen endpoints, user/password
  authentication, mutual TLS, ``max_message_size``, access control). ``swarm run``'s embedded
  router uses it too.
- :func:`write_deployment`: a folder with ``run.toml`` (the world's alone), ``agents/<user>.toml``
  (each agent's brief, :class:`protocol.config.AgentBrief`: what that robot is told and
  nothing of the world), ``zenoh/router.json5``, ``docker-compose.yml`` and ``.gitignore``
  (deterministic), ``.env`` (the uid and gid the
  Python services run as: those of whoever ran the command, who owns the secrets), and
  ``secrets/`` (random: a
  password per user, a CA, the router's and each user's certificate and key; the CA's private
  key is never written, so no further certificate can be signed with it;
  :mod:`swarm.certificates`, the ``[deploy]`` extra). Secrets come from the operating
  system's CSPRNG (``secrets``, ``cryptography``), deliberately unseeded: they must not be
  reproducible from anything in the repository or the run configuration.
"""
from __future__ import annotations

import json
import os
import secrets as random_secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from protocol import keys, ros2
from protocol.config import BRIEF_COMMAND, AgentBrief, RunConfig
from protocol.session import MAX_MESSAGE_SIZE, scouting_settings, tls_settings

if TYPE_CHECKING:  # swarm.certificates needs the [deploy] extra; swarm run imports this module
    from swarm.certificates import Identity

ZENOH_IMAGE = "eclipse/zenoh:1.10.2"  # kept at the eclipse-zenoh version of pyproject.toml
SWARM_IMAGE = "koopman-swarm:local"
SOURCE_ROOT = Path(__file__).resolve().parents[1]  # a checkout's root, with the Dockerfile
IMAGE_USER = "10001"  # the image's own user (Dockerfile), when no .env names another
SERVICE_USER = f"${{SWARM_UID:-{IMAGE_USER}}}:${{SWARM_GID:-{IMAGE_USER}}}"
"""The Python services' ``user``, from the deployment's ``.env``: mode-0600 secrets mounted
from the host are readable by their owner only."""
ROUTER_HOST = "zenoh"  # the router's name on the compose network (and in its certificate)
ROUTER_PORT = 7447
OBSERVER = "observer"
SECRETS = "secrets"
PRIVATE_DIR_MODE = 0o700
SECRET_FILE_MODE = 0o600

# Paths inside the containers.
RUN_TOML_IN_CONTAINER = "/etc/swarm/run.toml"  # the world's only
BRIEF_IN_CONTAINER = "/etc/swarm/agent.toml"  # an agent's own brief
BRIEFS = "agents"  # the deployment's folder of briefs
SECRETS_IN_CONTAINER = "/run/secrets/swarm"
ROUTER_DIR_IN_CONTAINER = "/etc/zenoh"
RESULTS_IN_CONTAINER = "/results"
STATE_IN_CONTAINER = "/state"


def agent_user(agent: int) -> str:
    """The user name of agent ``agent``: ``leader`` for 0, ``follower-K`` otherwise."""
    keys.check_agent_id(agent)
    return "leader" if agent == 0 else f"follower-{agent}"


def agent_briefs(config: RunConfig) -> dict[str, AgentBrief]:
    """Every agent's brief (:class:`protocol.config.AgentBrief`) in the run ``config``, by its
    user (:func:`agent_user`), the leader first."""
    return {agent_user(k): AgentBrief.of(config, k) for k in range(config.followers + 1)}


def users(followers: int) -> list[str]:
    """Every user of a run with ``followers`` followers, in a fixed order."""
    _check_followers(followers)
    return ["world", *(agent_user(k) for k in range(followers + 1)), OBSERVER]


def _check_followers(followers: int) -> None:
    if isinstance(followers, bool) or not isinstance(followers, int) or followers < 1:
        raise ValueError(f"followers must be a positive integer, got {followers!r}")


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
            "key_exprs": key_exprs}


def _agent_needs(run_id: str, agent: int) -> list[str]:
    """What agent ``agent`` subscribes to (agents/link.py): world ticks and ``world/done``; a
    follower also its predecessor's rod (a rod more than one tick ahead of the world's is
    held until the world announces its tick) and the world's missed-tick notices."""
    if agent == 0:
        return [keys.tick(run_id), keys.done(run_id)]
    return [keys.rod(run_id, agent - 1), keys.tick(run_id), keys.missed(run_id),
            keys.done(run_id)]


def access_control(run_id: str, followers: int, *, cert_names: bool = False,
                   ros_domain: int = 0, drive: bool = False) -> dict:
    """The ``access_control`` section: deny by default, allow each user what its role needs.

    ``cert_names``: a user must also present a TLS certificate whose common name is its user
    name (mutual TLS deployments); without it the password alone identifies the user.
    ``ros_domain``: the ROS 2 domain the world publishes the run's topics on (``--ros2``):
    the world may put on exactly its topics' keys and hold exactly its node's and publishers'
    liveliness tokens (:func:`protocol.ros2.world_keys`, :func:`protocol.ros2.world_tokens`;
    any session id and type hash, so that no rule needs rosbags; ``drive``: a drive run's,
    with the followers' ``cmd_vel``); the observer (or a ROS 2 router joining as it) may watch
    the domain's data and graph.

    At the router, ``ingress`` is what a client sends and ``egress`` what the router forwards
    to it; a message passes only if the sender's ingress rule and the receiver's egress rule
    both allow it, and a rule's key expression must include the message's.
    """
    keys.check_run_id(run_id)
    root = f"swarm/{run_id}"
    world_ops = [keys.sense(run_id), keys.act(run_id)]
    agent_samples = [keys.rod(run_id), keys.obs(run_id)]
    rules = [
        # Everyone who publishes is told of every subscription in the run (a declared
        # publisher sends only to subscribers it knows of; observers subscribe to all of
        # `swarm/<run>/**`). It reveals only which key expressions are subscribed.
        _rule("see-subscribers", "egress", ["declare_subscriber"], [f"{root}/**"]),
        # --- world ---
        _rule("world-serve", "ingress", ["declare_queryable", "reply"], world_ops),
        _rule("world-get-queries", "egress", ["query"], world_ops),
        _rule("world-publish", "ingress", ["put"], [f"{root}/world/**"]),
        _rule("world-subscribe", "ingress", ["declare_subscriber"], agent_samples),
        _rule("world-receive", "egress", ["put"], agent_samples),
        _rule("world-token", "ingress", ["liveliness_token", "liveliness_query"],
              [keys.alive(run_id, "world")]),
        _rule("world-watch", "ingress", ["declare_liveliness_subscriber"],
              [keys.alive(run_id, "*")]),
        _rule("world-see", "egress", ["liveliness_token"], [keys.alive(run_id, "*")]),
        # --- every agent: watches the world's liveliness token ---
        _rule("agents-watch-world", "ingress", ["declare_liveliness_subscriber"],
              [keys.alive(run_id, "world")]),
        _rule("agents-see-world", "egress", ["liveliness_token"], [keys.alive(run_id, "world")]),
        # --- observer: subscribes, nothing else ---
        _rule("observer-subscribe", "ingress", ["declare_subscriber"], [f"{root}/**"]),
        _rule("observer-receive", "egress", ["put"], [f"{root}/**"]),
        _rule("observer-watch", "ingress", ["declare_liveliness_subscriber"],
              [keys.alive(run_id, "*")]),
        _rule("observer-see", "egress", ["liveliness_token"], [keys.alive(run_id, "*")]),
    ]
    ros_data, ros_graph = ros2.graph_keys(ros_domain)
    rules += [
        # --- ROS 2 (design §10): the world's topics and graph entities, as rmw_zenoh names them
        _rule("world-ros2-publish", "ingress", ["put"],
              ros2.world_keys(ros_domain, followers, ros2.any_hash, drive=drive)),
        _rule("world-ros2-tokens", "ingress", ["liveliness_token"],
              ros2.world_tokens(ros_domain, followers, digest=ros2.any_hash, drive=drive)),
        _rule("world-ros2-subscribers", "egress", ["declare_subscriber"], [ros_data]),
        _rule("observer-ros2-subscribe", "ingress", ["declare_subscriber"], [ros_data]),
        _rule("observer-ros2-receive", "egress", ["put"], [ros_data]),
        _rule("observer-ros2-graph", "ingress",
              ["declare_liveliness_subscriber", "liveliness_query"], [ros_graph]),
        _rule("observer-ros2-see", "egress", ["liveliness_token"], [ros_graph]),
    ]
    policies = [
        {"id": "world", "subjects": ["world"],
         "rules": ["see-subscribers", "world-serve", "world-get-queries", "world-publish",
                   "world-subscribe", "world-receive", "world-token", "world-watch", "world-see",
                   "world-ros2-publish", "world-ros2-tokens", "world-ros2-subscribers"]},
        {"id": OBSERVER, "subjects": [OBSERVER],
         "rules": ["observer-subscribe", "observer-receive", "observer-watch", "observer-see",
                   "observer-ros2-subscribe", "observer-ros2-receive", "observer-ros2-graph",
                   "observer-ros2-see"]},
    ]
    for k in range(followers + 1):
        own_ops = [keys.sense(run_id, k), keys.act(run_id, k)]
        needs = _agent_needs(run_id, k)
        rules += [
            _rule(f"agent-{k}-subscribe", "ingress", ["declare_subscriber"], needs),
            _rule(f"agent-{k}-receive", "egress", ["put"], needs),
            _rule(f"agent-{k}-publish", "ingress", ["put"], [f"{root}/agent/{k}/**"]),
            _rule(f"agent-{k}-query", "ingress", ["query"], own_ops),
            # Replies (error replies included) go back to the asking agent only.
            _rule(f"agent-{k}-replies", "egress", ["reply"], own_ops),
            # Its token, and the liveliness query by which it refuses to start twice; the
            # answers to a liveliness query are tokens, hence the egress rule.
            _rule(f"agent-{k}-token", "ingress", ["liveliness_token", "liveliness_query"],
                  [keys.alive(run_id, k)]),
            _rule(f"agent-{k}-token-seen", "egress", ["liveliness_token"],
                  [keys.alive(run_id, k)]),
        ]
        policies.append({
            "id": agent_user(k), "subjects": [agent_user(k)],
            "rules": ["see-subscribers", "agents-watch-world", "agents-see-world",
                      *(f"agent-{k}-{what}" for what in
                        ("subscribe", "receive", "publish", "query", "replies", "token",
                         "token-seen"))]})
    subjects = []
    for user in users(followers):
        subject = {"id": user, "usernames": [user]}
        if cert_names:
            subject["cert_common_names"] = [user]
        subjects.append(subject)
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


@dataclass(frozen=True)
class TlsFiles:
    """Paths of a TLS identity as the process using them sees them."""

    ca: str
    cert: str
    key: str


def router_config(run_id: str, followers: int, *, listen: list[str], dictionary_file: str,
                  tls: TlsFiles | None = None, ros_domain: int = 0,
                  drive: bool = False) -> dict:
    """The router's configuration as a dict (``zenoh.Config.from_json5(json.dumps(...))``);
    ``ros_domain`` and ``drive`` as for :func:`access_control`.

    With ``tls``, the router accepts ``tls/`` links only, each from a client holding a
    certificate of the deployment's CA whose common name is the user's name.
    """
    link: dict = {"rx": {"max_message_size": MAX_MESSAGE_SIZE}}
    if tls is not None:
        link["protocols"] = ["tls"]
        link["tls"] = tls_settings(tls.ca, tls.cert, tls.key)
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": scouting_settings(),
        "transport": {"auth": {"usrpwd": {"dictionary_file": dictionary_file}}, "link": link},
        "access_control": access_control(run_id, followers, cert_names=tls is not None,
                                         ros_domain=ros_domain, drive=drive),
    }


# --- secrets -------------------------------------------------------------------------------------


def write_secret(path: Path, data: str | bytes) -> None:
    """Create ``path`` with mode 0600 from the start (never readable by others, even briefly)."""
    raw = data.encode() if isinstance(data, str) else data
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, SECRET_FILE_MODE)
    with os.fdopen(fd, "wb") as fh:
        fh.write(raw)


def private_dir(path: Path) -> Path:
    """Create ``path`` (mode 0700; it must not exist yet) and return it."""
    path.mkdir(mode=PRIVATE_DIR_MODE, parents=False)
    return path


def new_password() -> str:
    """A random password (32 URL-safe characters: 192 bits; never contains ``:``)."""
    return random_secrets.token_urlsafe(24)


def write_credentials(folder: Path, names: list[str]) -> dict[str, str]:
    """``folder/credentials.txt`` (the router's ``user:password`` lines) and a random password
    per user; returns {user: password}. Files mode 0600."""
    passwords = {user: new_password() for user in names}
    write_secret(folder / "credentials.txt",
                 "".join(f"{user}:{password}\n" for user, password in passwords.items()))
    return passwords


# --- the deployment folder ------------------------------------------------------------------------


def _json_lines(value, indent: int = 0) -> list[str]:
    """JSON (valid JSON5), one line per list element of objects, scalar lists inline."""
    pad, inner = " " * indent, " " * (indent + 2)
    compact = {"separators": (", ", ": ")}
    if isinstance(value, dict) and value:
        lines = ["{"]
        for key, item in value.items():
            sub = _json_lines(item, indent + 2)
            lines.append(f"{inner}{json.dumps(key)}: {sub[0]}")
            lines += sub[1:]
            lines[-1] += ","
        lines[-1] = lines[-1][:-1]
        return lines + [f"{pad}}}"]
    if isinstance(value, list) and value and any(isinstance(x, (dict, list)) for x in value):
        return ["[", *(f"{inner}{json.dumps(x, **compact)}," for x in value[:-1]),
                f"{inner}{json.dumps(value[-1], **compact)}", f"{pad}]"]
    return [json.dumps(value, **compact)]


def _json5(header: str, data: dict) -> str:
    body = "\n".join(_json_lines(data))
    return "".join(f"// {line}".rstrip() + "\n" for line in header.splitlines()) + body + "\n"


def _yaml(value, indent: int = 0) -> list[str]:
    """Block YAML for dicts and lists of scalars/dicts; scalars as JSON (valid YAML)."""
    pad = " " * indent
    lines = []
    if isinstance(value, dict):
        for key, item in value.items():
            if isinstance(item, (dict, list)) and item:
                if isinstance(item, list) and all(not isinstance(x, (dict, list)) for x in item):
                    lines.append(f"{pad}{key}: {json.dumps(item)}")
                else:
                    lines.append(f"{pad}{key}:")
                    lines += _yaml(item, indent + 2)
            else:
                lines.append(f"{pad}{key}: {json.dumps(item) if item != {} else '{}'}")
    elif isinstance(value, list):
        for item in value:
            lines.append(f"{pad}- {json.dumps(item)}")
    else:
        raise ValueError(f"cannot write {value!r} as YAML here")
    return lines


def _run_toml(config: RunConfig) -> str:
    return (
        "# Run configuration of the deployment (written by `python -m swarm deploy`; mounted\n"
        f"# read-only at {RUN_TOML_IN_CONTAINER} in the world's container only: agents get their\n"
        f"# brief, {BRIEFS}/<user>.toml). Any option of `python -m swarm run` (design §9) may be\n"
        "# added; then write the briefs anew, as what agents are told may have changed:\n"
        f"#   {BRIEF_COMMAND} run.toml --all --out {BRIEFS}\n"
        "# run_id and followers must stay as generated: the router's rules are\n"
        "# written for exactly this run id and these agents.\n"
        f"run_id = {json.dumps(config.run_id)}\n"
        f"followers = {config.followers}\n"
        "# Containers start in any order and the world compiles its numba kernels on first use.\n"
        f"start_timeout = {config.start_timeout!r}\n"
        f"agent_timeout = {config.agent_timeout!r}\n"
        + (f"# The world publishes the run's ROS 2 topics on domain {config.ros_domain} "
           "(docs/ros2.md);\n# the router's ROS 2 rules are written for it.\nros2 = true\n"
           f"ros_domain = {config.ros_domain}\n" if config.ros2 else
           "# The router's ROS 2 rules are written for domain 0: add `ros2 = true` to have the\n"
           "# world publish the run's ROS 2 topics there (docs/ros2.md).\n")
    )


def _client_flags(user: str) -> list[str]:
    secret = f"{SECRETS_IN_CONTAINER}"
    return ["--connect", f"tls/{ROUTER_HOST}:{ROUTER_PORT}", "--user", user,
            "--password-file", f"{secret}/password", "--tls-ca", f"{secret}/ca.pem",
            "--tls-cert", f"{secret}/cert.pem", "--tls-key", f"{secret}/key.pem"]


def compose(config: RunConfig, build: str | None = None) -> dict:
    """The docker-compose services: the router, the world, the leader and each follower.

    Each Python service mounts only its own secrets; the world alone mounts the run's
    configuration and the results volume; each agent mounts its own brief; each follower has
    its own state volume. The Python services run as
    :data:`SERVICE_USER`; with ``build`` (the Dockerfile's folder, relative to the compose
    file) compose builds their image.
    """
    def service(user: str, command: list[str], volumes: list[str]) -> dict:
        told = (f"./run.toml:{RUN_TOML_IN_CONTAINER}:ro" if user == "world"
                else f"./{BRIEFS}/{user}.toml:{BRIEF_IN_CONTAINER}:ro")
        return {"image": SWARM_IMAGE, **({"build": build} if build else {}),
                "user": SERVICE_USER, "depends_on": ["zenoh"], "restart": "no",
                "command": command,
                "volumes": [told, f"./{SECRETS}/{user}:{SECRETS_IN_CONTAINER}:ro", *volumes]}

    base = ["--config", RUN_TOML_IN_CONTAINER]
    brief = ["--config", BRIEF_IN_CONTAINER]
    services = {
        "zenoh": {"image": ZENOH_IMAGE, "restart": "no",
                  "command": ["-c", f"{ROUTER_DIR_IN_CONTAINER}/router.json5"],
                  "volumes": [f"./zenoh/router.json5:{ROUTER_DIR_IN_CONTAINER}/router.json5:ro",
                              f"./{SECRETS}/zenoh:{ROUTER_DIR_IN_CONTAINER}/{SECRETS}:ro"]},
        "world": service("world", ["python", "-m", "world", *base, "--out",
                                   f"{RESULTS_IN_CONTAINER}/{config.run_id}",
                                   *_client_flags("world")],
                         [f"results:{RESULTS_IN_CONTAINER}"]),
        "leader": service("leader", ["python", "-m", "agents.leader", *brief,
                                     "--session-mode", "client", *_client_flags("leader")], []),
    }
    volumes = {"results": {}}
    for k in range(1, config.followers + 1):
        user = agent_user(k)
        services[user] = service(user, [
            "python", "-m", "agents.follower", "--id", str(k), *brief, "--session-mode", "client",
            "--state-dir", STATE_IN_CONTAINER, *_client_flags(user)],
            [f"state-{k}:{STATE_IN_CONTAINER}"])
        volumes[f"state-{k}"] = {}
    return {"services": services, "volumes": volumes}


COMPOSE_HEADER = """\
# One run over a zenohd router: user/password authentication, mutual TLS, access control.
# Written by `python -m swarm deploy` (deploy/README.md); regenerate rather than edit.
# The repository's docker-compose.yml includes the one in deploy/: `docker compose up` there.
#
# Every service mounts only its own secrets (secrets/<user>/); the world alone mounts the
# run's configuration (run.toml: seed, surface) and the results volume; each agent mounts only
# its own brief (agents/<user>.toml); each follower keeps its checkpoint in its own volume
# state-K. The Python services run as the owner of the secrets (SWARM_UID, SWARM_GID in .env).
"""


def build_context(out: Path) -> str | None:
    """The Dockerfile's folder relative to the deployment folder ``out``, when ``out`` lies in
    a checkout (compose then builds the image); None otherwise (build it by hand)."""
    if not (SOURCE_ROOT / "Dockerfile").is_file():
        return None
    rel = Path(os.path.relpath(SOURCE_ROOT, Path(out).resolve()))
    return rel.as_posix() if all(part == ".." for part in rel.parts) else None


def generated_files(config: RunConfig, build: str | None = None) -> dict[str, str]:
    """Relative path -> text of every deterministic file of the deployment of ``config``
    (``build``: :func:`build_context`)."""
    secrets_dir = f"{ROUTER_DIR_IN_CONTAINER}/{SECRETS}"
    router = router_config(
        config.run_id, config.followers, listen=[f"tls/[::]:{ROUTER_PORT}"],
        dictionary_file=f"{secrets_dir}/credentials.txt", ros_domain=config.ros_domain,
        drive=config.drives,
        tls=TlsFiles(f"{secrets_dir}/ca.pem", f"{secrets_dir}/cert.pem",
                     f"{secrets_dir}/key.pem"))
    header = (f"zenohd configuration of run {config.run_id!r} with {config.followers} followers,\n"
              "written by `python -m swarm deploy` (deploy/README.md explains every rule).\n"
              "Paths are those inside the router's container (docker-compose.yml mounts them).")
    return {
        ".gitignore": (f"# Random passwords and private keys: never commit them; .env names the\n"
                       f"# user who owns them.\n{SECRETS}/\n.env\n"),
        "run.toml": _run_toml(config),
        **{f"{BRIEFS}/{user}.toml": brief.text() for user, brief in agent_briefs(config).items()},
        "zenoh/router.json5": _json5(header, router),
        "docker-compose.yml": COMPOSE_HEADER + "\n".join(_yaml(compose(config, build))) + "\n",
    }


def write_secrets(out: Path, followers: int, router: Identity,
                  tls: dict[str, Identity]) -> None:
    """``out/secrets/``: for the router ``zenoh/`` (credentials.txt, and its TLS identity
    ``router``: CA, certificate and key); for each user ``<user>/`` (password, and its
    identity from ``tls``). Mode 0700 / 0600."""
    root = private_dir(out / SECRETS)
    names = users(followers)
    router_dir = private_dir(root / "zenoh")
    passwords = write_credentials(router_dir, names)
    _write_identity(router_dir, router)
    for user in names:
        folder = private_dir(root / user)
        write_secret(folder / "password", passwords[user] + "\n")
        _write_identity(folder, tls[user])


def _write_identity(folder: Path, identity: Identity) -> None:
    """``ca.pem``, ``cert.pem`` and ``key.pem`` (mode 0600) in ``folder``."""
    (folder / "ca.pem").write_bytes(identity.ca)
    (folder / "cert.pem").write_bytes(identity.cert)
    write_secret(folder / "key.pem", identity.key)


def write_deployment(out: str | Path, config: RunConfig, *, force: bool = False,
                     router_hosts: tuple[str, ...] = (ROUTER_HOST, "localhost", "127.0.0.1",
                                                      "::1")) -> list[Path]:
    """Write the deployment of ``config`` into ``out``; return the files written.

    Refuses (ValueError) if ``out`` already holds secrets, unless ``force``: then the old
    secrets are replaced (a running router must be restarted with the new ones).
    """
    from swarm.certificates import identities  # before anything is written: [deploy] extra

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    if (out / SECRETS).exists():
        if not force:
            raise ValueError(f"{out / SECRETS} already exists: refusing to replace its passwords "
                             "and keys (use --force to generate new ones)")
        shutil.rmtree(out / SECRETS)
    router, tls = identities(users(config.followers), router_hosts)
    written = []
    files = {**generated_files(config, build_context(out)),
             ".env": f"SWARM_UID={os.getuid()}\nSWARM_GID={os.getgid()}\n"}
    for rel, text in files.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        written.append(path)
    write_secrets(out, config.followers, router, tls)
    written += sorted(p for p in (out / SECRETS).rglob("*") if p.is_file())
    return written
