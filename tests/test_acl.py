"""Attacks on a generated deployment (``python -m swarm deploy``, N = 5 followers), with real
router sessions: the router runs the generated ``router.json5`` over mutual TLS, each client
logs in with the generated files of the user it claims to be.

Each refusal has a positive control (the same action by the user allowed to do it succeeds), and
a forbidden message is sent before a legitimate one on the same link, so it would have arrived
first.
"""
from __future__ import annotations

import json
import stat
import sys
from pathlib import Path

import pytest
import zenoh

from protocol import keys, ros2
from protocol.config import RunConfig, load_config
from protocol.session import free_tcp_endpoint, undeclare_all, zenoh_config
from swarm.deploy import agent_user
from swarm.launch import RunCredentials, embedded_router_config
from tests.deployment import (
    ABSENT_S,
    WAIT_S,
    Deployment,
    Inbox,
    check_complete_run,
    delivered,
    free_ports,
    generate,
    replies,
    run_processes,
    until,
)

ROOT = Path(__file__).resolve().parents[1]
RUN, OTHER_RUN = "run-a", "run-b"
N = 5
RUN_TIMEOUT_S = 90.0  # a whole run, 7 processes (about 6 s here)


@pytest.fixture(scope="module")
def deployment(tmp_path_factory) -> Deployment:
    return generate(tmp_path_factory.mktemp("acl") / "deploy", RUN, N)


@pytest.fixture
def router(deployment):
    """A router from the generated configuration; yields the endpoint clients connect to."""
    listen, connect = free_ports()
    with zenoh.open(deployment.router_config(listen)):
        yield connect


def _answer(asked: list[str]):
    def answer(query: zenoh.Query) -> None:
        asked.append(str(query.key_expr))
        query.reply(query.key_expr, b"world")
    return answer


def test_follower_queries_only_its_own_sensing_and_motion(deployment, router):
    asked: list[str] = []
    with (deployment.client(router, "world") as world,
          deployment.client(router, "follower-3") as follower):
        handles = [world.declare_queryable(keys.sense(RUN), _answer(asked)),
                   world.declare_queryable(keys.act(RUN), _answer(asked))]
        assert until(lambda: replies(follower, keys.sense(RUN, 3)) == [(True, b"world")])
        assert replies(follower, keys.act(RUN, 3)) == [(True, b"world")]
        for other in (0, 1, 2, 4, 5):
            assert replies(follower, keys.sense(RUN, other), ABSENT_S) == []
            assert replies(follower, keys.act(RUN, other), ABSENT_S) == []
        assert replies(follower, keys.sense(RUN), ABSENT_S) == []  # the wildcard
        assert sorted(set(asked)) == [keys.act(RUN, 3), keys.sense(RUN, 3)]
        undeclare_all(handles)


def test_follower_cannot_publish_another_agents_samples_or_world_keys(deployment, router):
    """The observer, subscribed to the whole run, is the witness: nothing forged reaches it,
    nor the world, nor the follower behind the victim."""
    own = keys.rod(RUN, 3)
    forged = [keys.rod(RUN, 2), keys.obs(RUN, 2), keys.rod(RUN, 4), keys.obs(RUN, 4),
              keys.tick(RUN), keys.done(RUN), keys.missed(RUN), keys.view(RUN, "tick"),
              f"swarm/{RUN}/agent/3x/rod"]
    rod_4 = keys.rod(RUN, 4)
    with (deployment.client(router, "world") as world,
          deployment.client(router, "observer") as observer,
          deployment.client(router, "follower-3") as attacker,
          deployment.client(router, "follower-4") as victim,
          deployment.client(router, "follower-5") as behind):
        seen, world_inbox, behind_inbox = Inbox(), Inbox(), Inbox()
        handles = [observer.declare_subscriber(f"swarm/{RUN}/**", seen),
                   world.declare_subscriber(keys.rod(RUN), world_inbox),
                   world.declare_subscriber(keys.obs(RUN), world_inbox),
                   behind.declare_subscriber(rod_4, behind_inbox)]
        # Positive controls: every route is in place.
        assert delivered(lambda: attacker.put(own, b"own"), seen, (own, b"own"))
        assert delivered(lambda: attacker.put(own, b"own"), world_inbox, (own, b"own"))
        assert delivered(lambda: victim.put(rod_4, b"real"), behind_inbox, (rod_4, b"real"))
        for key in forged:
            attacker.put(key, b"forged")
        attacker.put(own, b"after")
        assert seen.wait_for((own, b"after"), WAIT_S)
        assert world_inbox.wait_for((own, b"after"), WAIT_S)
        assert not seen.wait_for((forged[0], b"forged"), ABSENT_S)
        assert seen.keys() == {own, rod_4}
        assert all(payload != b"forged" for _, payload in seen.items + world_inbox.items)
        assert world_inbox.keys() == {own, rod_4}
        assert {payload for _, payload in behind_inbox.items} == {b"real"}
        undeclare_all(handles)


def test_agents_never_receive_world_view(deployment, router):
    """``world/view/**`` carries absolute coordinates: observers get it, no agent does, even
    when subscribing to it directly or through a wildcard."""
    view = keys.view(RUN, "tick")
    with (deployment.client(router, "world") as world,
          deployment.client(router, "observer") as observer):
        seen = Inbox()
        handles = [observer.declare_subscriber(keys.view(RUN), seen)]
        agents = [deployment.client(router, agent_user(k)) for k in (0, 1, 5)]
        try:
            inboxes = [Inbox() for _ in agents]
            for agent, inbox in zip(agents, inboxes):
                for key in (keys.view(RUN), f"swarm/{RUN}/world/**", f"swarm/{RUN}/**"):
                    handles.append(agent.declare_subscriber(key, inbox))
            # Positive control: the leader's own subscription to ticks, declared last.
            handles.append(agents[0].declare_subscriber(keys.tick(RUN), inboxes[0]))
            assert delivered(lambda: world.put(keys.tick(RUN), b"tick"), inboxes[0],
                             (keys.tick(RUN), b"tick"))
            assert delivered(lambda: world.put(view, b"truth"), seen, (view, b"truth"))
            assert not any(inbox.wait_for((view, b"truth"), ABSENT_S) for inbox in inboxes)
            assert all(view not in inbox.keys() for inbox in inboxes)
        finally:
            undeclare_all(handles)
            for agent in agents:
                agent.close()


def test_follower_receives_only_its_predecessors_rod(deployment, router):
    rod_2 = keys.rod(RUN, 2)
    with (deployment.client(router, "world") as world,
          deployment.client(router, "follower-2") as leader_of_3,
          deployment.client(router, "follower-3") as follower,
          deployment.client(router, "follower-5") as other):
        tokens, own, foreign = Inbox(), Inbox(), Inbox()
        handles = [world.liveliness().declare_subscriber(keys.alive(RUN, "*"), tokens,
                                                          history=True),
                   other.declare_subscriber(rod_2, foreign),
                   other.declare_subscriber(keys.obs(RUN, 2), foreign),
                   # Declared after the subscriptions: once the world sees the token, the
                   # router has handled them.
                   other.liveliness().declare_token(keys.alive(RUN, 5))]
        assert tokens.wait_for((keys.alive(RUN, 5), b""), WAIT_S)
        handles.append(follower.declare_subscriber(rod_2, own))
        assert delivered(lambda: leader_of_3.put(rod_2, b"rod"), own, (rod_2, b"rod"))
        leader_of_3.put(keys.obs(RUN, 2), b"obs")
        assert not foreign.wait_for((rod_2, b"rod"), ABSENT_S)
        assert foreign.items == []
        undeclare_all(handles)


def test_agent_cannot_serve_world_queries_or_hold_another_token(deployment, router):
    sense_4 = keys.sense(RUN, 4)
    with (deployment.client(router, "world") as world,
          deployment.client(router, "follower-3") as follower,
          deployment.client(router, "follower-4") as victim):
        tokens = Inbox()
        handles = [
            world.declare_queryable(keys.sense(RUN), lambda q: q.reply(q.key_expr, b"world")),
            world.liveliness().declare_subscriber(keys.alive(RUN, "*"), tokens, history=True),
            follower.declare_queryable(sense_4, lambda q: q.reply(q.key_expr, b"forged")),
            follower.liveliness().declare_token(keys.alive(RUN, 4)),
            follower.liveliness().declare_token(keys.alive(RUN, "world")),
            # Declared last on the same link: once the world sees it, the router has handled
            # the forged declarations above.
            follower.liveliness().declare_token(keys.alive(RUN, 3)),
        ]
        assert tokens.wait_for((keys.alive(RUN, 3), b""), WAIT_S)
        assert tokens.keys() == {keys.alive(RUN, 3)}
        assert until(lambda: (True, b"world") in replies(victim, sense_4))
        assert replies(victim, sense_4) == [(True, b"world")]
        undeclare_all(handles)


@pytest.mark.parametrize("agent", [0, 1, 5])
def test_agent_sees_the_world_and_its_own_token(deployment, router, agent):
    """What liveliness an agent needs: the world's token, and its own (a second process with
    the same id finds it and refuses to start)."""
    own, user = keys.alive(RUN, agent), agent_user(agent)
    with deployment.client(router, "world") as world, deployment.client(router, user) as client:
        world_seen = Inbox()
        handles = [world.liveliness().declare_token(keys.alive(RUN, "world")),
                   client.liveliness().declare_subscriber(keys.alive(RUN, "world"), world_seen,
                                                          history=True),
                   client.liveliness().declare_token(own)]
        assert world_seen.wait_for((keys.alive(RUN, "world"), b""), WAIT_S)
        with deployment.client(router, user) as twin:
            assert until(lambda: [str(r.ok.key_expr) for r in twin.liveliness().get(
                own, timeout=1.0) if r.ok is not None] == [own])
        undeclare_all(handles)


def test_a_second_world_finds_the_live_one(deployment, router):
    """The liveliness query of ``world-token``: a world can tell that its run id is live
    (issue 8: a second world must not join a live run)."""
    alive = keys.alive(RUN, "world")
    with deployment.client(router, "world") as world:
        token = world.liveliness().declare_token(alive)
        with deployment.client(router, "world") as second:
            assert until(lambda: [str(r.ok.key_expr) for r in second.liveliness().get(
                alive, timeout=1.0) if r.ok is not None] == [alive])
        token.undeclare()


def test_observer_subscribes_but_cannot_query_publish_or_declare(deployment, router):
    asked: list[str] = []
    with (deployment.client(router, "world") as world,
          deployment.client(router, "observer") as observer,
          deployment.client(router, "leader") as leader):
        seen, ticks, tokens = Inbox(), Inbox(), Inbox()
        handles = [world.declare_queryable(keys.sense(RUN), _answer(asked)),
                   world.declare_queryable(keys.act(RUN), _answer(asked)),
                   world.liveliness().declare_token(keys.alive(RUN, "world")),
                   observer.declare_subscriber(f"swarm/{RUN}/**", seen),
                   observer.liveliness().declare_subscriber(keys.alive(RUN, "*"), tokens,
                                                            history=True),
                   leader.declare_subscriber(keys.tick(RUN), ticks)]
        # It subscribes: the world's samples, an agent's rod, the liveliness tokens.
        assert delivered(lambda: world.put(keys.view(RUN, "tick"), b"v"), seen,
                         (keys.view(RUN, "tick"), b"v"))
        assert delivered(lambda: leader.put(keys.rod(RUN, 0), b"r"), seen, (keys.rod(RUN, 0), b"r"))
        assert tokens.wait_for((keys.alive(RUN, "world"), b""), WAIT_S)
        # It cannot query the sensing or motion of any agent.
        for key in (keys.sense(RUN, 0), keys.act(RUN, 0), keys.sense(RUN)):
            assert replies(observer, key, ABSENT_S) == []
        assert asked == []
        # It cannot publish: the leader never sees its tick.
        observer.put(keys.tick(RUN), b"forged")
        assert delivered(lambda: world.put(keys.tick(RUN), b"world"), ticks,
                         (keys.tick(RUN), b"world"))
        assert not ticks.wait_for((keys.tick(RUN), b"forged"), ABSENT_S)
        # Its queryable and token are not declared: the world never sees the token, the
        # leader's query reaches the world only.
        world_tokens = Inbox()
        handles += [world.liveliness().declare_subscriber(keys.alive(RUN, "*"), world_tokens),
                    observer.declare_queryable(keys.sense(RUN, 0),
                                               lambda q: q.reply(q.key_expr, b"forged")),
                    observer.liveliness().declare_token(keys.alive(RUN, 0))]
        assert not world_tokens.wait_for((keys.alive(RUN, 0), b""), ABSENT_S)
        assert until(lambda: replies(leader, keys.sense(RUN, 0)) == [(True, b"world")])
        assert replies(leader, keys.sense(RUN, 0)) == [(True, b"world")]
        undeclare_all(handles)


def _ros_pose_key(domain: int, agent: int) -> str:
    msgtype = "geometry_msgs/msg/PoseStamped"
    return ros2.topic_key(domain, ros2.agent_topic(agent, "pose"), msgtype,
                          ros2.type_hash(msgtype))


def test_world_publishes_its_ros2_keys_an_agent_cannot_and_the_observer_subscribes(
        deployment, router):
    """design §10: the world may put on exactly its topics' keys; an agent may not (not even on
    the world's keys); the observer, subscribed as a ROS 2 subscriber would (the domain's
    wildcard), receives the world's samples."""
    domain = load_config(deployment.folder / "run.toml").ros_domain
    own = _ros_pose_key(domain, 1)
    not_its_topic = f"{domain}/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_00"
    beyond = _ros_pose_key(domain, N + 1)  # an agent this run does not have
    with (deployment.client(router, "world") as world,
          deployment.client(router, "observer") as observer,
          deployment.client(router, "follower-3") as agent):
        seen = Inbox()
        handles = [observer.declare_subscriber(ros2.graph_keys(domain)[0], seen)]
        assert delivered(lambda: world.put(own, b"world"), seen, (own, b"world"))
        agent.put(own, b"forged")
        agent.put(_ros_pose_key(domain, 3), b"forged")
        world.put(not_its_topic, b"not its topic")
        world.put(beyond, b"not its topic")
        world.put(own, b"after")
        assert seen.wait_for((own, b"after"), WAIT_S)
        assert not seen.wait_for((own, b"forged"), ABSENT_S)
        assert seen.keys() == {own}
        assert {payload for _, payload in seen.items} == {b"world", b"after"}
        undeclare_all(handles)


def test_only_the_world_holds_its_ros2_graph_tokens(deployment, router):
    """The world's node and publisher tokens reach the observer's view of the ROS 2 graph (a
    liveliness query, as rmw_zenoh makes); the same tokens declared by an agent, and a token
    the world has no business holding, do not."""
    domain = load_config(deployment.folder / "run.toml").ros_domain
    with (deployment.client(router, "world") as world,
          deployment.client(router, "observer") as observer,
          deployment.client(router, "follower-2") as agent):
        digest = ros2.type_hash
        node, first, *_ = ros2.world_tokens(domain, N, str(world.zid()), digest=digest)
        forged = ros2.world_tokens(domain, N, str(agent.zid()), digest=digest)[:2]
        subscription = first.replace("/MP/", "/MS/")
        handles = [world.liveliness().declare_token(node),
                   world.liveliness().declare_token(first),
                   world.liveliness().declare_token(subscription),
                   *(agent.liveliness().declare_token(token) for token in forged)]

        def graph() -> set[str]:
            return {str(r.ok.key_expr) for r in observer.liveliness().get(
                ros2.graph_keys(domain)[1], timeout=1.0) if r.ok is not None}

        assert until(lambda: graph() == {node, first})
        assert not until(lambda: graph() != {node, first}, ABSENT_S)
        undeclare_all(handles)


def test_config_of_one_run_grants_nothing_in_another(deployment, router):
    """Cross-run: the router generated for run A, every user acting on run B's keys."""
    asked: list[str] = []
    with (deployment.client(router, "world") as world,
          deployment.client(router, "leader") as leader,
          deployment.client(router, "follower-1") as follower,
          deployment.client(router, "observer") as observer):
        seen, ticks, rods = Inbox(), Inbox(), Inbox()
        handles = [world.declare_queryable(keys.sense(RUN), _answer(asked)),
                   world.declare_queryable(keys.sense(OTHER_RUN), _answer(asked)),
                   observer.declare_subscriber(f"swarm/{OTHER_RUN}/**", seen),
                   leader.declare_subscriber(keys.tick(OTHER_RUN), ticks),
                   world.declare_subscriber(keys.rod(OTHER_RUN), rods),
                   observer.declare_subscriber(f"swarm/{RUN}/**", seen)]
        # Positive control in run A.
        assert until(lambda: replies(follower, keys.sense(RUN, 1)) == [(True, b"world")])
        assert delivered(lambda: world.put(keys.tick(RUN), b"a"), seen, (keys.tick(RUN), b"a"))
        assert replies(follower, keys.sense(OTHER_RUN, 1), ABSENT_S) == []
        world.put(keys.tick(OTHER_RUN), b"b")
        follower.put(keys.rod(OTHER_RUN, 1), b"b")
        world.put(keys.tick(RUN), b"after")
        assert seen.wait_for((keys.tick(RUN), b"after"), WAIT_S)
        assert not ticks.wait_for((keys.tick(OTHER_RUN), b"b"), ABSENT_S)
        assert rods.items == []
        assert not any(key.startswith(f"swarm/{OTHER_RUN}/") for key in seen.keys())
        assert set(asked) == {keys.sense(RUN, 1)}
        undeclare_all(handles)


def test_wrong_password_is_refused(deployment, router):
    with deployment.client(router, "follower-1"):  # positive control: the right one opens
        pass
    for user, password in (("follower-1", "wrong"), ("world", deployment.password("leader"))):
        with pytest.raises(zenoh.ZError):
            deployment.client(router, user, password=password, connect_timeout=1.0).close()


def test_password_with_another_users_certificate_grants_nothing(deployment, router):
    """The leader's password with follower 1's certificate: both must name the same user, so
    this session matches no subject and may do nothing."""
    asked: list[str] = []
    with (deployment.client(router, "world") as world,
          deployment.client(router, "leader", identity="follower-1") as mixed,
          deployment.client(router, "leader") as leader):
        handles = [world.declare_queryable(keys.sense(RUN), _answer(asked))]
        assert until(lambda: replies(leader, keys.sense(RUN, 0)) == [(True, b"world")])
        for key in (keys.sense(RUN, 0), keys.sense(RUN, 1)):
            assert replies(mixed, key, ABSENT_S) == []
        assert set(asked) == {keys.sense(RUN, 0)}
        undeclare_all(handles)


def test_clients_without_tls_or_without_the_deployments_certificate_are_refused(
        deployment, router, tmp_path):
    port = router.rpartition(":")[2]
    user, password = "follower-1", deployment.password("follower-1")
    with deployment.client(router, user):  # positive control
        pass
    attempts = {
        "plain tcp": zenoh_config("client", connect=[f"tcp/localhost:{port}"], user=user,
                                  password=password, connect_timeout=1.0),
        "tls, no client certificate": zenoh_config(
            "client", connect=[router], user=user, password=password, connect_timeout=1.0,
            extra=[f'transport/link/tls/root_ca_certificate:'
                   f'{json.dumps(str(deployment.secret(user, "ca.pem")))}']),
    }
    stranger = generate(tmp_path / "stranger", RUN, N)  # the same users, another CA
    attempts["certificate of another CA"] = zenoh_config(
        "client", connect=[router], user=user, password=password, connect_timeout=1.0,
        tls_ca=deployment.secret(user, "ca.pem"), tls_cert=stranger.secret(user, "cert.pem"),
        tls_key=stranger.secret(user, "key.pem"))
    refused = []
    for name, conf in attempts.items():
        try:
            zenoh.open(conf).close()
        except zenoh.ZError:
            refused.append(name)
    assert refused == list(attempts)


@pytest.mark.slow  # five followers; fast tier: test_deploy.py's compose services complete a run
def test_a_whole_run_over_the_generated_configuration(deployment, tmp_path):
    """World, leader and five followers as processes, each with its own generated files."""
    listen, connect = free_ports()
    config = load_config(deployment.folder / "run.toml")
    out = tmp_path / "results"

    def command(user: str, program: list[str]) -> list[str]:
        told = "run.toml" if user == "world" else f"agents/{user}.toml"  # an agent: its brief
        return [sys.executable, "-m", *program, "--config", str(deployment.folder / told),
                "--connect", connect, "--user", user,
                "--password-file", str(deployment.secret(user, "password")),
                "--tls-ca", str(deployment.secret(user, "ca.pem")),
                "--tls-cert", str(deployment.secret(user, "cert.pem")),
                "--tls-key", str(deployment.secret(user, "key.pem"))]

    commands = {"world": command("world", ["world", "--out", str(out)]),
                "leader": command("leader", ["agents.leader"])}
    for k in range(1, N + 1):
        commands[agent_user(k)] = command(agent_user(k), ["agents.follower", "--id", str(k),
                                                          "--state-dir", str(tmp_path / f"s{k}")])
    codes, output = run_processes(deployment.router_config(listen), commands, tmp_path, ROOT,
                                  RUN_TIMEOUT_S)
    assert codes == dict.fromkeys(commands, 0), output
    check_complete_run(out, config)


# --- swarm run's embedded router ---------------------------------------------------------------


def test_swarm_run_router_admits_only_the_runs_users_under_the_same_rules(tmp_path):
    """The world's router of ``swarm run``: per-run random passwords in private files, no
    anonymous client, and the deployment's rules (no one but the world ends the run)."""
    config = RunConfig(run_id="embedded", followers=2)
    credentials = RunCredentials.create(tmp_path / "credentials", config.followers)
    assert stat.S_IMODE(credentials.folder.stat().st_mode) == 0o700
    files = sorted(p.name for p in credentials.folder.iterdir())
    assert files == sorted(["credentials.txt", "leader.password", "follower-1.password",
                            "follower-2.password", "observer.password"])  # none for the world
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in credentials.folder.iterdir())
    assert len(set(credentials.passwords.values())) == len(credentials.passwords)
    endpoint = free_tcp_endpoint()

    def client(user: str | None, password: str | None = None) -> zenoh.Session:
        if user is not None and password is None:
            password = credentials.password_file(user).read_text().strip()
        return zenoh.open(zenoh_config("client", connect=[endpoint], user=user,
                                       password=password, connect_timeout=1.0))

    with zenoh.open(embedded_router_config(config, endpoint, credentials)) as world:
        for user, password in ((None, None), ("follower-1", "wrong"), ("world", "")):
            with pytest.raises(zenoh.ZError):
                client(user, password).close()
        done = keys.done(config.run_id)
        with client("leader") as leader, client("follower-1") as follower:
            inbox = Inbox()
            handles = [leader.declare_subscriber(done, inbox)]
            assert delivered(lambda: world.put(done, b"world"), inbox, (done, b"world"))
            follower.put(done, b"forged")
            assert not inbox.wait_for((done, b"forged"), ABSENT_S)
            handles.append(world.declare_queryable(keys.sense(config.run_id),
                                                   lambda q: q.reply(q.key_expr, b"world")))
            assert until(lambda: replies(follower, keys.sense(config.run_id, 1))
                         == [(True, b"world")])
            assert replies(follower, keys.sense(config.run_id, 2), ABSENT_S) == []
            undeclare_all(handles)
