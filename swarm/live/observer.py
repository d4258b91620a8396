"""``LiveView``: a page server plus, once connected, the read-only observer session feeding it.

The command-line subcommands (``run --live``, ``watch``, ``replay``) are thin wrappers of it.
"""
from __future__ import annotations

import threading

import zenoh

from protocol import keys
from protocol.cli import describe
from protocol.session import open_session
from swarm.live.feed import ZenohFeed
from swarm.live.server import PageServer
from swarm.live.store import REPLAY_HINT, RunStore


class LiveView:
    """Serve ``store`` (a new empty one by default) on ``port``; :meth:`connect` feeds it from
    Zenoh as run ``run_id``'s observer. A replay passes a loaded store and ``replay=True``."""

    def __init__(self, *, port: int, run_id: str | None = None, store: RunStore | None = None,
                 replay: bool = False) -> None:
        self.run_id = None if run_id is None else keys.check_run_id(run_id)
        self.store = RunStore() if store is None else store
        self.server = PageServer(self.store, port=port, replay=replay)
        self._session: zenoh.Session | None = None
        self._feed: ZenohFeed | None = None

    def start(self) -> str:
        """Start the page server; return the page's address (RuntimeError if it cannot)."""
        return self.server.start()

    def connect(self, conf: zenoh.Config) -> None:
        """Open the observer session and subscribe (RuntimeError if Zenoh cannot connect)."""
        if self.run_id is None:
            raise RuntimeError("a replay has no run to observe")
        try:
            self._session = open_session(conf)
        except zenoh.ZError as exc:
            raise RuntimeError(f"the live view cannot connect to Zenoh: {describe(exc)} (is the "
                               "run's router up? `swarm run` ends its router with the run; "
                               f"{REPLAY_HINT})") from None
        self._feed = ZenohFeed(self._session, self.run_id, self.store)

    def serve_until_interrupted(self) -> None:
        """Block until Ctrl-C (the page keeps serving meanwhile)."""
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        if self._feed is not None:
            self._feed.close()
            self._feed = None
        if self._session is not None:
            self._session.close()
            self._session = None
        self.server.stop()
