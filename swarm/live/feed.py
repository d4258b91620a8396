"""The observer's Zenoh side: read-only subscriptions that fill a :class:`RunStore`.

It declares subscribers and a liveliness subscriber only (no publisher, no query), which is
all the ``observer`` role of the router's access control allows.
"""
from __future__ import annotations

import logging

import zenoh

from protocol import keys
from protocol.messages import Done, Observation, ProtocolError, decode
from protocol.session import undeclare_all
from protocol.view import decode_map, decode_tick
from swarm.live.store import RunStore, choice_label

log = logging.getLogger(__name__)


class ZenohFeed:
    """Subscribe to run ``run_id``'s view, observations and end on ``session``, into ``store``."""

    def __init__(self, session: zenoh.Session, run_id: str, store: RunStore) -> None:
        run = keys.check_run_id(run_id)
        self.store = store
        self._handles = [
            session.declare_subscriber(keys.view(run, "map"), self._on_map),
            session.declare_subscriber(keys.view(run, "tick"), self._on_tick),
            session.declare_subscriber(keys.obs(run), self._on_obs),
            session.declare_subscriber(keys.done(run), self._on_done),
            session.liveliness().declare_subscriber(keys.alive(run, "world"), self._on_world,
                                                    history=True),
        ]

    def _on_map(self, sample: zenoh.Sample) -> None:
        try:
            self.store.set_map(decode_map(sample.payload.to_bytes()))
        except ProtocolError as exc:
            log.warning("live view: dropped map on %s: %s", sample.key_expr, exc)

    def _on_tick(self, sample: zenoh.Sample) -> None:
        try:
            self.store.add_tick(decode_tick(sample.payload.to_bytes()))
        except ProtocolError as exc:
            log.warning("live view: dropped tick on %s: %s", sample.key_expr, exc)

    def _on_obs(self, sample: zenoh.Sample) -> None:
        try:
            agent = keys.agent_from_key(str(sample.key_expr))
            msg = decode(sample.payload.to_bytes(), Observation)
        except (ProtocolError, ValueError) as exc:
            log.warning("live view: dropped observation on %s: %s", sample.key_expr, exc)
            return
        self.store.add_choice(msg.tick, agent, choice_label(
            msg.estimator, msg.followed, msg.fallback, msg.prediction is not None))

    def _on_done(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), Done)
        except ProtocolError as exc:
            log.warning("live view: dropped done on %s: %s", sample.key_expr, exc)
            return
        self.store.finish(msg.complete, msg.reason)

    def _on_world(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.store.world_gone()
        else:
            self.store.world_seen()

    def close(self) -> None:
        undeclare_all(self._handles)
