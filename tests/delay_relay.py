"""A TCP relay that delays every byte by a fixed time in each direction: link latency injected
from outside, for machines whose kernel has no ``tc netem``.

``python -m tests.delay_relay --listen 127.0.0.1:0 --to 127.0.0.1:7447 --delay-ms 10`` accepts
connections on ``--listen`` (port 0: a free one; the line ``relay listening on HOST:PORT`` says
which), opens one connection to ``--to`` for each, and forwards the bytes both ways, each chunk
sent ``--delay-ms`` after it arrived, in order. Zenoh clients connect to the relay instead of
the router; TLS passes through untouched (the relay never looks at the bytes), so the name in
the client's endpoint must still be one the router's certificate holds (``tls/localhost:PORT``).

What it emulates: a link with a fixed one-way delay and unlimited bandwidth (the relay reads as
fast as the sender writes and buffers without bound). What it cannot emulate: loss. Over TCP a
lost segment is retransmitted by the kernel, below the relay; ``tc netem`` on the link is the
way to lose packets.
"""
from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import selectors
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

CHUNK = 65536
READY = "relay listening on "


def _address(text: str, name: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"{name} must be HOST:PORT, got {text!r}")
    return host, int(port)


async def _forward(reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                   delay_s: float) -> None:
    """Copy ``reader`` to ``writer``, each chunk ``delay_s`` after it arrived; then half-close."""
    loop = asyncio.get_running_loop()
    held: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def receive() -> None:
        try:
            while data := await reader.read(CHUNK):
                held.put_nowait((loop.time() + delay_s, data))
        except ConnectionError:
            pass
        held.put_nowait((loop.time() + delay_s, b""))  # the end, delayed like the bytes

    receiving = asyncio.create_task(receive())
    try:
        while True:
            due, data = await held.get()
            if (wait := due - loop.time()) > 0:
                await asyncio.sleep(wait)
            if not data:
                if writer.can_write_eof():
                    writer.write_eof()
                return
            writer.write(data)
            await writer.drain()
    except ConnectionError:
        return
    finally:
        receiving.cancel()


async def _connection(client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter,
                      target: tuple[str, int], delay_s: float) -> None:
    try:
        server_reader, server_writer = await asyncio.open_connection(*target)
    except OSError as exc:
        print(f"relay: cannot reach {target[0]}:{target[1]}: {exc}", file=sys.stderr, flush=True)
        client_writer.close()
        return
    try:
        await asyncio.gather(_forward(client_reader, server_writer, delay_s),
                             _forward(server_reader, client_writer, delay_s))
    finally:
        for writer in (client_writer, server_writer):
            writer.close()


async def serve(listen: tuple[str, int], target: tuple[str, int], delay_s: float) -> None:
    """Relay every connection to ``listen`` to ``target`` until cancelled."""
    server = await asyncio.start_server(
        lambda r, w: _connection(r, w, target, delay_s), *listen)
    host, port = server.sockets[0].getsockname()[:2]
    print(f"{READY}{host}:{port}", flush=True)
    async with server:
        await server.serve_forever()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="TCP relay delaying each direction by a fixed time.")
    p.add_argument("--listen", required=True, help="HOST:PORT to accept on (port 0: any free)")
    p.add_argument("--to", required=True, help="HOST:PORT to forward each connection to")
    p.add_argument("--delay-ms", type=float, required=True,
                   help="one-way delay added in each direction, milliseconds (>= 0)")
    args = p.parse_args(argv)
    if not args.delay_ms >= 0:
        raise ValueError(f"--delay-ms must be >= 0, got {args.delay_ms}")
    listen, target = _address(args.listen, "--listen"), _address(args.to, "--to")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(listen, target, args.delay_ms / 1000.0))
    return 0


@contextlib.contextmanager
def relay_process(to: str, delay_ms: float, *, listen: str = "127.0.0.1:0",
                  timeout: float = 10.0) -> Iterator[int]:
    """Run the relay as its own process (``python -m tests.delay_relay``) for the ``with``
    block; yield the port it listens on. The process is ended by its handle on leaving."""
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (
        str(root), os.environ.get("PYTHONPATH"))))}
    proc = subprocess.Popen([sys.executable, "-m", "tests.delay_relay", "--listen", listen,
                             "--to", to, "--delay-ms", repr(delay_ms)],
                            cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        line = ""
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            deadline = time.monotonic() + timeout
            while not line.startswith(READY):
                left = deadline - time.monotonic()
                if left <= 0 or not sel.select(left):
                    raise RuntimeError(f"the delay relay did not start within {timeout} s")
                line = proc.stdout.readline()
                if not line:
                    raise RuntimeError(f"the delay relay exited: {proc.stderr.read()[-2000:]}")
        yield int(line.strip().rpartition(":")[2])
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


if __name__ == "__main__":
    sys.exit(main())
