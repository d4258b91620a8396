"""The docker-compose deployment that ``python -m swarm deploy`` writes, without Docker.

The committed ``deploy/`` is that command's output (secrets aside: they are never committed);
the compose services' commands run here against the generated router configuration, over
mutual TLS. What the access-control rules allow and deny is in tests/test_acl.py. Last, what
the world's sensing replies reveal (never absolute positions unless the run enables GPS).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import stat
import struct
import subprocess
from importlib.metadata import version
from pathlib import Path

import pytest
import yaml
from cryptography import x509
from cryptography.x509.oid import NameOID

from protocol.config import RunConfig, load_config
from protocol.messages import Sensing, encode
from protocol.session import MAX_MESSAGE_SIZE
from swarm.deploy import (
    SECRETS,
    SERVICE_USER,
    SWARM_IMAGE,
    ZENOH_IMAGE,
    access_control,
    build_context,
    generated_files,
    users,
)
from swarm.local import run_local
from tests.deployment import (
    ROUTER_IN_COMPOSE,
    Deployment,
    check_complete_run,
    free_ports,
    generate,
    run_processes,
)
from world.sim import WorldSim

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "deploy"
CONFIG = load_config(COMMITTED / "run.toml")
AGENTS = ("leader", *(f"follower-{k}" for k in range(1, CONFIG.followers + 1)))
RUN_TIMEOUT_S = 60.0  # the whole compose run (about 4 s here)


@pytest.fixture(scope="module")
def deployment(tmp_path_factory) -> Deployment:
    """The committed deployment's run id and size, regenerated with fresh secrets."""
    return generate(tmp_path_factory.mktemp("deploy") / "deploy", CONFIG.run_id, CONFIG.followers)


# --- the committed deployment is the generator's output ---------------------------------------


def test_committed_deploy_is_the_generated_one(deployment):
    """Every generated file but the secrets and ``.env`` is committed byte for byte (in the
    checkout, compose builds the image from its root); nothing else is there but the
    hand-written README, and neither a secret nor ``.env`` is tracked by git."""
    assert build_context(COMMITTED) == ".." and build_context(deployment.folder) is None
    generated = generated_files(CONFIG, "..")
    for rel, text in generated.items():
        assert (COMMITTED / rel).read_text() == text, f"deploy/{rel} is stale: regenerate it"
    for rel, text in generated_files(CONFIG).items():  # elsewhere: no build context
        assert (deployment.folder / rel).read_text() == text
    tracked = subprocess.run(["git", "ls-files", "deploy"], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.split()
    assert sorted(tracked) == sorted(["deploy/README.md", "deploy/rviz/swarm.rviz",
                                      *(f"deploy/{rel}" for rel in generated)])
    assert {f"{SECRETS}/", ".env"} <= set(generated[".gitignore"].splitlines())


# --- the repository's docker-compose.yml ----------------------------------------------------------


PYTHON_SERVICES = {"world": ["python", "-m", "world"], "leader": ["python", "-m", "agents.leader"],
                   **{f"follower-{k}": ["python", "-m", "agents.follower", "--id", str(k)]
                      for k in range(1, CONFIG.followers + 1)}}


def test_root_compose_runs_the_default_deployment(deployment):
    """``docker compose up`` at the repository root: the root file includes deploy/'s, whose
    services are the router, the world, the leader and every follower; the Python services
    are built from the root's Dockerfile and run as the owner of the secrets (``.env``, written
    by the one command, ``python -m swarm deploy``); every file a service mounts exists once
    that command ran (``deployment`` ran it into a fresh folder, which holds the same files);
    nothing is published on the host and every service is on the default network."""
    root = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    assert root == {"include": ["deploy/docker-compose.yml"]}
    compose = yaml.safe_load((ROOT / root["include"][0]).read_text())
    services = compose["services"]
    assert set(services) == {"zenoh", *PYTHON_SERVICES}
    assert services["zenoh"]["image"] == ZENOH_IMAGE
    assert services["zenoh"]["command"] == ["-c", "/etc/zenoh/router.json5"]
    for name, command in PYTHON_SERVICES.items():
        service = services[name]
        assert service["command"][:len(command)] == command
        assert service["image"] == SWARM_IMAGE and service["user"] == SERVICE_USER
        assert (COMMITTED / service["build"]).resolve() == ROOT
        assert service["depends_on"] == ["zenoh"]
    assert (ROOT / "Dockerfile").is_file()
    assert "networks" not in compose
    for name, service in services.items():
        assert not {"ports", "network_mode", "networks", "expose"} & set(service), name
        for spec in service["volumes"]:
            source = spec.split(":")[0]
            if source.startswith("."):
                assert (deployment.folder / source).exists(), (name, spec)
            else:
                assert source in compose["volumes"], (name, spec)
    env = dict(line.split("=", 1) for line in (deployment.folder / ".env").read_text().split())
    assert env == {"SWARM_UID": str(os.getuid()), "SWARM_GID": str(os.getgid())}
    assert (deployment.secret("world", "password").stat().st_uid == os.getuid())


def test_root_compose_passes_docker_compose_config():
    """``docker compose config`` (no engine needed) accepts the root file and resolves the
    deployment's services, build context and user; skipped where the Docker client or its
    compose plugin is missing."""
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker client on this machine")
    probe = subprocess.run([docker, "compose", "version"], capture_output=True, text=True,
                           timeout=60)
    if probe.returncode != 0:
        pytest.skip("the docker client here has no compose plugin (`docker compose version`: "
                    f"{(probe.stderr or probe.stdout).strip().splitlines()[0][:80]})")
    result = subprocess.run([docker, "compose", "config", "--format", "json"], cwd=ROOT,
                            capture_output=True, text=True, timeout=60,
                            env={**os.environ, "SWARM_UID": "1234", "SWARM_GID": "1235"})
    assert result.returncode == 0, result.stderr
    config = json.loads(result.stdout)
    assert set(config["services"]) == {"zenoh", *PYTHON_SERVICES}
    for name in PYTHON_SERVICES:
        service = config["services"][name]
        assert Path(service["build"]["context"]).resolve() == ROOT
        assert service["user"] == "1234:1235"


def test_generated_output_is_deterministic_but_secrets_are_not(deployment, tmp_path):
    other = generate(tmp_path / "again", CONFIG.run_id, CONFIG.followers)
    for rel in generated_files(CONFIG):
        assert (other.folder / rel).read_bytes() == (deployment.folder / rel).read_bytes()
    for user in users(CONFIG.followers):
        assert other.password(user) != deployment.password(user)
        assert (other.secret(user, "key.pem").read_bytes()
                != deployment.secret(user, "key.pem").read_bytes())


def test_deploy_refuses_to_replace_secrets(deployment, capsys):
    from swarm.cli import main

    before = deployment.password("leader")
    assert main(["deploy", "--followers", "3", "--out", str(deployment.folder)]) == 2
    assert "refusing to replace" in capsys.readouterr().err
    assert deployment.password("leader") == before


def test_secrets_are_private_and_certificates_name_their_users(deployment):
    secrets = deployment.folder / SECRETS
    for path in [secrets, *secrets.rglob("*")]:
        mode = stat.S_IMODE(path.stat().st_mode)
        if path.is_dir():
            assert mode == 0o700, path
        elif path.name in ("password", "key.pem", "credentials.txt"):
            assert mode == 0o600, path
        else:  # certificates are public
            assert path.name in ("ca.pem", "cert.pem"), path
    assert not any("ca" in p.name and "key" in p.name for p in secrets.rglob("*"))
    ca = x509.load_pem_x509_certificate(deployment.secret("zenoh", "ca.pem").read_bytes())
    names = {}
    for user in ("zenoh", *users(CONFIG.followers)):
        cert = x509.load_pem_x509_certificate(deployment.secret(user, "cert.pem").read_bytes())
        cert.verify_directly_issued_by(ca)
        assert deployment.secret(user, "ca.pem").read_bytes() == deployment.secret(
            "zenoh", "ca.pem").read_bytes()
        names[user] = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value
    assert names == {"zenoh": "router", **{u: u for u in users(CONFIG.followers)}}
    router_cert = x509.load_pem_x509_certificate(
        deployment.secret("zenoh", "cert.pem").read_bytes())
    alt = router_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "zenoh" in alt.get_values_for_type(x509.DNSName)  # the compose host name


def test_compose_matches_router_and_credentials(deployment):
    router = deployment.router_config("tls/127.0.0.1:7447")
    dictionary = Path(json.loads(router.get_json("transport/auth/usrpwd/dictionary_file")))
    credentials = dict(line.split(":", 1) for line in dictionary.read_text().splitlines())
    assert set(credentials) == set(users(CONFIG.followers))
    assert json.loads(router.get_json("listen/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(router.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(router.get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_SIZE
    assert json.loads(router.get_json("access_control/default_permission")) == "deny"
    services = deployment.services
    assert set(services) == {"zenoh", "world", *AGENTS}
    for service in ("world", *AGENTS):
        mounts = deployment.mounts(service, Path("/volumes"))
        local = {flag: deployment.local_path(deployment.option(service, flag), mounts)
                 for flag in ("--config", "--password-file", "--tls-ca", "--tls-cert",
                              "--tls-key")}
        assert deployment.option(service, "--connect") == ROUTER_IN_COMPOSE
        assert deployment.option(service, "--user") == service
        assert local == {"--config": str(deployment.folder / "run.toml"),
                         **{flag: str(deployment.secret(service, name)) for flag, name in (
                             ("--password-file", "password"), ("--tls-ca", "ca.pem"),
                             ("--tls-cert", "cert.pem"), ("--tls-key", "key.pem"))}}
        assert credentials[service] == deployment.password(service)
        # Each service sees its own secrets only; the world alone sees the results.
        secret_mounts = [p for p in mounts.values() if SECRETS in p.parts]
        assert secret_mounts == [deployment.folder / SECRETS / service]
        assert (Path("/volumes/results") in mounts.values()) == (service == "world")
    for k in range(1, CONFIG.followers + 1):
        mounts = deployment.mounts(f"follower-{k}", Path("/volumes"))
        state = deployment.option(f"follower-{k}", "--state-dir")
        assert deployment.local_path(state, mounts) == f"/volumes/state-{k}"
        assert deployment.option(f"follower-{k}", "--id") == str(k)
    assert "--state-dir" not in services["leader"]["command"]
    for agent in AGENTS:
        assert deployment.option(agent, "--session-mode") == "client"
    image_version = services["zenoh"]["image"].rpartition(":")[2]
    assert image_version.split(".")[:2] == version("eclipse-zenoh").split(".")[:2]


def test_compose_services_complete_a_run(deployment, tmp_path):
    """Every compose service's command, run here against the generated router, over TLS."""
    listen, connect = free_ports()
    commands = {service: deployment.local_command(service, connect, tmp_path)
                for service in ("world", *AGENTS)}
    codes, output = run_processes(deployment.router_config(listen), commands, tmp_path, ROOT,
                                  RUN_TIMEOUT_S)
    assert codes == dict.fromkeys(commands, 0), output
    check_complete_run(Path(deployment.local_path(deployment.option("world", "--out"),
                                                  deployment.mounts("world", tmp_path))), CONFIG)


# --- what sensing reveals ------------------------------------------------------------------------


def _sensing_log(monkeypatch, config: RunConfig) -> list[tuple[int, Sensing, list[tuple]]]:
    """Run ``config`` locally; every sensing reply, with its agent and every agent's (x, y, z)."""
    log = []
    original = WorldSim._read  # every sensing but a control step's: pre, moved, settled

    def read(self: WorldSim, agent: int, tick: int, role: str, look: bool) -> Sensing:
        reply = original(self, agent, tick, role, look)
        poses = [(*map(float, s.pos), float(self.surface.height(s.pos))) for s in self.agents]
        log.append((agent, reply, poses))
        return reply

    monkeypatch.setattr(WorldSim, "_read", read)
    # one agent at a time, so every agent's current pose is the one its successor senses
    run_local(config.replace(pipelined=False))
    return log


def _numbers(msg: Sensing) -> list[float]:
    """Every number a sensing reply carries."""
    values = []
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        values += [float(x) for x in (value if isinstance(value, tuple) else [value])
                   if isinstance(x, float)]
    return values


def _reveals(reply: Sensing, pose: tuple[float, float, float]) -> bool:
    """Whether any coordinate of ``pose`` is in ``reply``, as a number or as wire bytes."""
    wire = encode(reply)
    return any(struct.pack(">d", c) in wire
               or any(math.isclose(x, c, rel_tol=0, abs_tol=1e-9) for x in _numbers(reply))
               for c in pose)


def test_sensing_never_reveals_absolute_positions_without_gps(monkeypatch):
    log = _sensing_log(monkeypatch, RunConfig(run_id="privacy", followers=2, ticks=8,
                                              dictionary="c", velocity="oracle"))
    assert len(log) >= 2 * 8 * 2  # every follower senses at least twice a tick
    for _, reply, poses in log:
        assert reply.gps is None and reply.leader_gps is None
        assert not any(_reveals(reply, pose) for pose in poses)


def test_sensing_reveals_positions_when_the_run_enables_gps(monkeypatch):
    """Positive control of the test above: with GPS on, the same checks see the positions."""
    log = _sensing_log(monkeypatch, RunConfig(run_id="privacy", followers=2, ticks=8, gps=True))
    for agent, reply, poses in log:
        assert reply.gps == pytest.approx(poses[agent], abs=1e-12)
        assert reply.leader_gps == pytest.approx(poses[agent - 1], abs=1e-12)
        assert _reveals(reply, poses[agent]) and _reveals(reply, poses[agent - 1])


# --- session configuration ------------------------------------------------------------------------


def test_every_session_config_bounds_message_size_and_takes_tls_flags(deployment):
    import argparse

    from protocol.session import add_connection_flags, connection_config, tls_options, zenoh_config

    for mode, kwargs in (("peer", {}), ("client", {"connect": ["tcp/127.0.0.1:7447"]}),
                         ("router", {"listen": ["tcp/127.0.0.1:0"]})):
        conf = zenoh_config(mode, **kwargs)
        assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_SIZE
    parser = argparse.ArgumentParser()
    add_connection_flags(parser)
    files = [str(deployment.secret("leader", name)) for name in ("ca.pem", "cert.pem", "key.pem")]
    args = parser.parse_args(["--connect", "tls/localhost:7447", "--tls-ca", files[0],
                              "--tls-cert", files[1], "--tls-key", files[2]])
    conf = connection_config(args)  # the one helper of every command (world, agents, watch)
    assert json.loads(conf.get_json("transport/link/tls/connect_certificate")) == files[1]
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    assert tls_options(parser.parse_args([])) == dict.fromkeys(("tls_ca", "tls_cert", "tls_key"))
    with pytest.raises(ValueError, match="must be given together"):
        tls_options(parser.parse_args(["--tls-ca", files[0]]))
    with pytest.raises(ValueError, match="no such file"):
        tls_options(parser.parse_args(["--tls-ca", "/nonexistent", "--tls-cert", files[1],
                                       "--tls-key", files[2]]))
    with pytest.raises(ValueError, match="max_message_size"):
        zenoh_config("peer", max_message_size=10)


def test_a_drive_runs_world_may_publish_its_cmd_vel_and_nothing_more():
    """design §10: a drive run's router lets the world put on, and hold the tokens of, each
    follower's ``cmd_vel`` (and the teleport run's keys); a teleport run's router does not."""
    def world_ros_rules(config: RunConfig) -> dict[str, list[str]]:
        rules = access_control(config.run_id, config.followers, ros_domain=config.ros_domain,
                               drive=config.motion == "drive")["rules"]
        return {r["id"]: r["key_exprs"] for r in rules
                if r["id"] in ("world-ros2-publish", "world-ros2-tokens")}

    drive = dataclasses.replace(CONFIG, motion="drive")
    generated = generated_files(drive)["zenoh/router.json5"]
    teleport, driving = world_ros_rules(CONFIG), world_ros_rules(drive)
    twist = "geometry_msgs::msg::dds_::Twist_"
    for rule in ("world-ros2-publish", "world-ros2-tokens"):
        added = [key for key in driving[rule] if key not in teleport[rule]]
        assert set(teleport[rule]) < set(driving[rule])
        assert len(added) == CONFIG.followers
        assert all(f"agent_{k}/cmd_vel/{twist}/*" in key or f"agent_{k}%cmd_vel/{twist}/*" in key
                   for k, key in enumerate(added, start=1)), added
        assert all(key in generated for key in added)
    assert not any("cmd_vel" in key for keys in teleport.values() for key in keys)
