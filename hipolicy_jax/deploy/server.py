"""The policy server: a ``PolicyBackend`` behind a websocket (``websockets``, asyncio), msgpack messages
(``protocol``).

The backend compiles and runs once before the socket opens (``warmup``), so the first request is as fast as the
rest. Every connection is served concurrently; inference runs on one worker thread (one decision at a time, in
arrival order) while the event loop keeps answering health and metadata requests and rejecting bad ones. A bad
request gets an error reply naming the problem and the connection stays open; a frame above the server's limit
gets an error reply too, and one above twice the limit is refused by the websocket layer itself (close code 1009)
before it is read into memory.
"""

from __future__ import annotations

import asyncio
import signal
import concurrent.futures
import threading
import time
from typing import Callable

from websockets.asyncio.server import serve

from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.backend import OUTPUT_KEYS, PolicyBackend


class PolicyServer:
    """Serve ``backend`` on ``ws://host:port`` (``port`` 0: any free port, see ``port`` once ``started``)."""

    def __init__(self, backend: PolicyBackend, host: str = "127.0.0.1", port: int = 8000, *,
                 max_message_bytes: int = protocol.DEFAULT_MAX_MESSAGE_BYTES,
                 max_batch: int = protocol.DEFAULT_MAX_BATCH, log: Callable[[str], None] = print):
        self.backend, self.host, self.port = backend, host, port
        self.max_message_bytes, self.max_batch, self.log = max_message_bytes, max_batch, log
        self.requests = self.errors = 0
        self.started = threading.Event()
        self._worker = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="policy")
        self._t0 = time.monotonic()
        self._stop: asyncio.Future | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ---------------------------------------------------------------------------------------------- requests
    def _infer(self, request: dict) -> dict:
        obs, key_data, batched = protocol.check_infer(request, self.backend.metadata, self.max_batch)
        t0 = time.perf_counter()
        out = self.backend.decide(obs, key_data)
        ms = 1e3 * (time.perf_counter() - t0)
        keys = OUTPUT_KEYS if request.get("chunks") else tuple(k for k in OUTPUT_KEYS if k != "chunks")
        reply = {k: (out[k] if batched else out[k][0]) for k in keys}
        return {"type": "result", **reply, "server_ms": ms}

    async def _answer(self, data) -> dict:
        request_id = None
        try:
            if not isinstance(data, str) and len(data) > self.max_message_bytes:
                raise protocol.ProtocolError(f"message of {len(data)} bytes exceeds the server's limit of "
                                             f"{self.max_message_bytes} bytes")
            request = protocol.unpack(data)
            if not isinstance(request, dict):
                raise protocol.ProtocolError(f"expected a msgpack map with a 'type', got {type(request).__name__}")
            request_id = request.get("id")
            kind = request.get("type")
            if kind == "infer":
                loop = asyncio.get_running_loop()
                reply = await loop.run_in_executor(self._worker, self._infer, request)
            elif kind == "metadata":
                reply = {"type": "metadata", "metadata": self.backend.metadata}
            elif kind == "health":
                reply = {"type": "health", "status": "ok", "requests": self.requests, "errors": self.errors,
                         "uptime_s": time.monotonic() - self._t0}
            else:
                raise protocol.ProtocolError(f"type: expected 'infer', 'metadata' or 'health', got {kind!r}")
        except protocol.ProtocolError as e:
            self.errors += 1
            return protocol.error_reply(str(e), request_id)
        except Exception as e:  # noqa: BLE001 - the server keeps serving whatever one request does
            self.errors += 1
            return protocol.error_reply(f"internal error: {type(e).__name__}: {e}", request_id)
        self.requests += 1
        return reply if request_id is None else {**reply, "id": request_id}

    async def _handler(self, websocket):
        async for data in websocket:
            await websocket.send(protocol.pack(await self._answer(data)))

    # ------------------------------------------------------------------------------------------------- serving
    async def serve_async(self) -> None:
        """Warm up, then serve until ``stop()``."""
        self._loop = asyncio.get_running_loop()
        self._stop = self._loop.create_future()
        seconds = await self._loop.run_in_executor(self._worker, self.backend.warmup, 1)
        async with serve(self._handler, self.host, self.port, max_size=2 * self.max_message_bytes,
                         compression=None) as server:
            self.port = server.sockets[0].getsockname()[1]
            meta = self.backend.metadata
            self.log(f"serving the {meta['task']} policy (strides {meta['strides']}, N={meta['num_samples']}) on "
                     f"ws://{self.host}:{self.port} (compiled and warmed up in {seconds:.1f} s)")
            self.started.set()
            await self._stop
        self._worker.shutdown(wait=False)

    def run(self) -> None:
        """Serve in this thread until ``stop()`` (from another thread) or Ctrl-C / SIGINT.

        In the main thread SIGINT is set to raise ``KeyboardInterrupt`` first: a process started in the background
        by a non-interactive shell (``cmd &``) inherits SIGINT as *ignored*, and ``kill -INT`` would not stop it."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.default_int_handler)
        asyncio.run(self.serve_async())

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(lambda: self._stop.done() or self._stop.set_result(None))

    def start_in_thread(self, timeout: float = 600.0) -> threading.Thread:
        """Serve from a daemon thread; returns once the socket accepts connections."""
        thread = threading.Thread(target=self.run, name="policy-server", daemon=True)
        thread.start()
        if not self.started.wait(timeout):
            raise TimeoutError(f"the policy server did not start within {timeout} s")
        return thread


__all__ = ["PolicyServer"]
