"""The page server: a Bokeh server on its own thread, serving BokehJS from the package.

``PageServer(store, port=…).start()`` returns the page's address; ``stop()`` ends the thread.
Every asset (BokehJS, CSS) comes from this server (Bokeh's ``server`` resources), so the
page works with no internet access.
"""
from __future__ import annotations

import asyncio
import functools
import logging
import threading

from protocol.distribution import needs
from protocol.session import free_port
from swarm.live import DEFAULT_PORT
from swarm.live.page import build_page
from swarm.live.store import RunStore

with needs("live"):
    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler
    from bokeh.server.server import Server
    from bokeh.settings import settings
    from tornado.ioloop import IOLoop

START_TIMEOUT_S = 15.0


def _not_a_closed_tab(record: logging.LogRecord) -> bool:
    """False for Bokeh's note that a push found the viewer's tab already closed: closing a tab
    while the page plays is how a viewer leaves, not something for the operator's log."""
    return "connection was closed" not in record.getMessage()


logging.getLogger("bokeh.server.views.ws").addFilter(_not_a_closed_tab)


class PageServer:
    """Serve ``store`` as a live page (``replay=False``) or a replay page on ``address:port``.

    ``port=0`` picks a free port. Raises ValueError for a bad port and RuntimeError (from
    :meth:`start`) when the server cannot listen.
    """

    def __init__(self, store: RunStore, *, port: int = DEFAULT_PORT, address: str = "127.0.0.1",
                 replay: bool = False) -> None:
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port must be an integer in [0, 65535], got {port!r}")
        self.store, self.address, self.replay = store, address, replay
        self.port = port or free_port(address)
        self._ready = threading.Event()
        self._error: str | None = None
        self._loop: IOLoop | None = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://{self.address}:{self.port}/"

    def start(self) -> str:
        """Start serving on a background thread; return the page's address."""
        if self._thread is not None:
            raise RuntimeError("the page server is already started")
        self._thread = threading.Thread(target=self._serve, name="live-view", daemon=True)
        self._thread.start()
        if not self._ready.wait(START_TIMEOUT_S):
            raise RuntimeError(f"the page server did not start within {START_TIMEOUT_S:g} s")
        if self._error is not None:
            self._thread.join(START_TIMEOUT_S)
            raise RuntimeError(f"cannot serve the page on {self.url}: {self._error}")
        return self.url

    def _serve(self) -> None:
        asyncio.set_event_loop(asyncio.new_event_loop())
        self._loop = IOLoop.current()
        settings.resources.set_value("server")  # BokehJS from this server, never a CDN
        app = Application(FunctionHandler(functools.partial(
            build_page, store=self.store, replay=self.replay)))
        origins = [f"{host}:{self.port}" for host in ("localhost", "127.0.0.1", self.address)]
        try:
            server = Server({"/": app}, io_loop=self._loop, port=self.port, address=self.address,
                            allow_websocket_origin=origins, num_procs=1)
            server.start()
        except OSError as exc:
            self._error = str(exc)
            self._ready.set()
            self._loop.close()
            return
        self._ready.set()
        self._loop.start()
        server.stop()
        server.unlisten()
        self._loop.close(all_fds=True)

    def stop(self, timeout: float = 5.0) -> None:
        """Stop serving and wait for the thread (idempotent)."""
        if self._thread is None or not self._thread.is_alive() or self._loop is None:
            return
        self._loop.add_callback(self._loop.stop)
        self._thread.join(timeout)
