"""Test support: a run over Zenoh (`swarm run`'s embedded router, agents in-process) with an
attacker thread holding the run's credentials, and a clean run of the same config to compare.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import zenoh

from protocol import keys
from protocol.config import RunConfig
from protocol.session import free_tcp_endpoint
from swarm.launch import RunCredentials, launch

Attack = Callable[[str, RunCredentials, threading.Event], None]


def wait_for_world(session: zenoh.Session, run_id: str, stop: threading.Event) -> None:
    """Until the world's liveliness token shows (its queryables are declared before it)."""
    up = threading.Event()
    watch = session.liveliness().declare_subscriber(keys.alive(run_id, "world"),
                                                    lambda _: up.set(), history=True)
    while not up.wait(0.05) and not stop.is_set():
        pass
    watch.undeclare()


def run_under_attack(config: RunConfig, tmp_path: Path, attack: Attack) -> tuple[dict, dict]:
    """(clean summary, attacked summary): ``config`` run in ``tmp_path/clean`` alone, then in
    ``tmp_path/attacked`` while ``attack(endpoint, credentials, stop)`` runs in a thread (it
    must return once ``stop`` is set). Fails if the attacker does not end or the attacked run
    is incomplete."""
    clean = launch(config, tmp_path / "clean", in_process=True)
    endpoint, stop = free_tcp_endpoint(), threading.Event()
    credentials = RunCredentials.create(tmp_path / "credentials", config.followers)
    attacker = threading.Thread(target=attack, args=(endpoint, credentials, stop))
    attacker.start()
    try:
        attacked = launch(config, tmp_path / "attacked", in_process=True, endpoint=endpoint,
                          credentials=credentials)
    finally:
        stop.set()
        attacker.join(timeout=60)
    assert not attacker.is_alive(), "the attacker did not stop"
    assert attacked["complete"], attacked["reason"]
    return clean, attacked


def same_results(tmp_path: Path) -> bool:
    """Whether the attacked run's ticks.csv and observations.csv equal the clean run's."""
    return all((tmp_path / "attacked" / name).read_bytes()
               == (tmp_path / "clean" / name).read_bytes()
               for name in ("ticks.csv", "observations.csv"))
