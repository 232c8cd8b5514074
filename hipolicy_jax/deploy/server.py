"""The policy server: a ``PolicyBackend`` behind a websocket (``websockets``, asyncio) speaking openpi's protocol
(``protocol``), with micro-batching, server-side execution and an optional API key.

- **Connections.** Each connection is one robot (one episode at a time): on connect it gets the manifest, then
  sends observation frames and gets the actions to execute. It carries its decision count (the default PRNG keys,
  ``protocol.decision_key``) and the execution strategy's memory (``te``, ``delay``), both reset by a ``reset``
  entry. Under an inference delay with ``handover='inpaint'`` that memory's committed actions go into the batched
  decision as the row's prefix (``backend``: ``prefix``, ``prefix_valid``), as in-process rollouts pass them to the
  sampler; every other row passes an invalid (or empty) prefix, which decides as without one. Health
  (``GET /healthz``) and the API key check (``Authorization: Api-Key <key>``, HTTP 401 at the handshake, before any
  inference) run in websockets' ``process_request`` hook.
- **Micro-batching.** Validated requests go to one queue; whenever a worker is free, a batcher takes the first,
  then keeps collecting until ``max_batch`` are in, every open connection not being decided has one in (with
  ``workers`` > 1: its share of the open connections), or ``batch_window_ms`` has passed since the first, and
  decides them in ONE backend call on that worker's thread (requests that arrive meanwhile wait for the next call).
  The batch is padded to a power of two (≤ ``max_batch``; every size compiled at warm-up) and each row answers its
  own request: a row's decision depends on its own history and key only. ``workers`` (default 1) batches run at
  the same time; on 2 CPU cores a second one gained ~3 % requests/s at 8 clients with a longer tail
  (``benchmarks.serving``).
- **Robustness.** A bad request gets a one-line text frame naming the problem and the connection stays open; an
  internal failure sends its line and closes the connection with 1011; a frame above ``max_message_bytes`` gets an
  error, one above twice that is refused by the websocket layer itself (close code 1009) before it is read.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import hmac
import http
import json
import signal
import threading
import time
from typing import Callable

import jax
import numpy as np
from websockets.asyncio.server import serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode

from hipolicy_jax.checkpoint import config_from_dict
from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.backend import PolicyBackend, zeros_obs
from hipolicy_jax.evaluation.execution import Decision, make_execution

API_KEY_ENV = "HIPOLICY_API_KEY"


@dataclasses.dataclass(frozen=True)
class ServerConfig:
    """Where and how the server listens, batches and draws keys."""

    host: str = "127.0.0.1"  # localhost only; "0.0.0.0" serves every interface
    port: int = 8000  # 0: any free port (``PolicyServer.port`` once started)
    max_message_bytes: int = protocol.DEFAULT_MAX_MESSAGE_BYTES  # larger frames get an error
    max_batch: int = 8  # observations decided in one backend call
    batch_window_ms: float = 5.0  # how long the first request of a batch waits for more
    workers: int = 1  # batches decided at the same time (threads calling the backend)
    seed: int = 0  # default keys: decision n of a connection uses fold_in(key(seed), n)
    api_key: str = dataclasses.field(default="", repr=False)  # non-empty: "Authorization: Api-Key <api_key>"

    def __post_init__(self):
        if not isinstance(self.port, int) or not 0 <= self.port < 2**16:
            raise ValueError(f"port: expected an int in [0, 65535], got {self.port!r}")
        if self.max_message_bytes < 1024:
            raise ValueError(f"max_message_bytes: expected at least 1024, got {self.max_message_bytes}")
        if not 1 <= self.max_batch <= 1024:
            raise ValueError(f"max_batch: expected 1 to 1024 observations per call, got {self.max_batch}")
        if not 1 <= self.workers <= 16:
            raise ValueError(f"workers: expected 1 to 16 concurrent batches, got {self.workers}")
        if not 0 <= self.batch_window_ms <= 1000:
            raise ValueError(f"batch_window_ms: expected 0 to 1000 ms, got {self.batch_window_ms}")
        if not 0 <= self.seed < 2**32:
            raise ValueError(f"seed: expected an int in [0, 2**32), got {self.seed}")
        if self.api_key and (self.api_key != self.api_key.strip() or any(ord(c) < 33 or ord(c) > 126
                                                                        for c in self.api_key)):
            raise ValueError("api_key: expected printable ASCII without spaces")

    @property
    def batch_sizes(self) -> tuple[int, ...]:
        """The compiled batch sizes: powers of two below ``max_batch``, and ``max_batch``."""
        sizes = [1 << i for i in range(self.max_batch.bit_length()) if 1 << i < self.max_batch]
        return tuple(sizes + [self.max_batch])


@dataclasses.dataclass
class _Session:
    """One connection's decision count and execution memory."""

    state: object
    decisions: int = 0


@dataclasses.dataclass
class _Pending:
    request: protocol.Request
    session: _Session
    decision: int
    enqueued: float
    future: asyncio.Future


class PolicyServer:
    """Serve ``backend`` on ``ws://host:port`` as ``config`` says (``port`` 0: any free port, see ``port`` once
    ``started``)."""

    def __init__(self, backend: PolicyBackend, config: ServerConfig = ServerConfig(), *,
                 log: Callable[[str], None] = print):
        self.backend, self.config, self.log = backend, config, log
        self.host, self.port = config.host, config.port
        meta = backend.metadata
        clash = sorted(set(meta["obs"]) & set(protocol.RESERVED))
        if clash:
            raise ValueError(f"obs: the policy's observation keys {clash} clash with the protocol's reserved "
                             f"entries {list(protocol.RESERVED)}")
        self.inference = InferenceConfig(**meta["inference"])
        self.strategy = make_execution(self.inference)
        self.chunk = config_from_dict(PolicyConfig, meta["policy"]).chunk
        self.exec_len = self.strategy.exec_len(self.chunk)
        strategy, chunk = self.strategy, self.chunk
        self._execute = jax.jit(lambda d, state: strategy.decide(d, state, chunk))
        self._initial_state = strategy.init(chunk, int(meta["action_dim"]))
        self._prefix_of = getattr(strategy, "prefix", lambda state: None)
        committed = self._prefix_of(self._initial_state)
        want = (0 if committed is None else int(committed[0].shape[0]), int(meta["action_dim"]))
        if tuple(meta["inputs"]["prefix"][1:]) != want:
            raise ValueError(f"inputs.prefix: the policy's decision takes a prefix of shape "
                             f"{meta['inputs']['prefix']}, its execution (delay {self.inference.delay}, handover "
                             f"{self.inference.handover!r}) commits {want[0]} actions of {want[1]}; re-export it")
        self._no_prefix = np.zeros(want, np.float32)
        self.metadata = {**meta, "server": {
            "protocol": protocol.PROTOCOL, "reserved": list(protocol.RESERVED), "execution": strategy.name,
            "delay": int(self.inference.delay), "handover": self.inference.handover, "exec_len": int(self.exec_len),
            "seed": int(config.seed),
            "max_batch": int(config.max_batch), "batch_window_ms": float(config.batch_window_ms),
            "workers": int(config.workers),
            "batch_sizes": list(config.batch_sizes), "api_key": bool(config.api_key)}}
        self._metadata_frame = protocol.pack(self.metadata)
        self.requests = self.errors = self.refused = self.batches = self.rows = 0
        self.largest_batch = 0
        self.connections = 0
        self.started = threading.Event()
        self._worker = concurrent.futures.ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="policy")
        self._deciding = 0
        self._t0 = time.monotonic()
        self._stop: asyncio.Future | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queue: asyncio.Queue | None = None

    # --------------------------------------------------------------------------------------------- inference
    def _warmup(self) -> float:
        t0 = time.perf_counter()
        for size in self.config.batch_sizes:
            self.backend.warmup(size)
        out = self.backend.decide(zeros_obs(self.backend.metadata, 1), np.zeros((1, 2), np.uint32))
        self._run_execution(out, 0, self._initial_state)
        protocol.decision_key(self.config.seed, 0)
        return time.perf_counter() - t0

    def _bucket(self, rows: int) -> int:
        return next(s for s in self.config.batch_sizes if s >= rows)

    def _run_execution(self, out: dict, i: int, state):
        d = Decision(chunks=out["chunks"][i], entropy=out["entropy"][i], freq_index=out["freq_index"][i],
                     stride=out["stride"][i], actions=out["actions"][i])
        po, state = self._execute(d, state)
        n = self.exec_len if po.num_actions is None else int(np.clip(int(po.num_actions), 1, self.exec_len))
        return np.asarray(po.actions, np.float32)[:n], state

    def _prefix(self, state) -> tuple[np.ndarray, bool]:
        """A connection's committed actions (P, A) and whether there are any (P = 0 without inpainting)."""
        committed = self._prefix_of(state)
        if committed is None:
            return self._no_prefix, False
        return np.asarray(committed[0], np.float32), bool(committed[1])

    def _decide_batch(self, items: list[_Pending]) -> list[dict]:
        """Worker thread: one backend call for ``items`` (padded to a compiled size), then each row's execution."""
        started = time.perf_counter()
        rows = len(items)
        keys = [it.request.key_data if it.request.key_data is not None
                else protocol.decision_key(self.config.seed, it.decision) for it in items]
        padded = items + [items[-1]] * (self._bucket(rows) - rows)
        keys += [keys[-1]] * (len(padded) - rows)
        obs = {k: np.stack([it.request.obs[k] for it in padded]) for k in self.backend.metadata["obs"]}
        prefixes = [self._prefix(it.session.state) for it in padded]  # a connection's requests come one at a time
        t0 = time.perf_counter()
        out = self.backend.decide(obs, np.stack(keys), np.stack([p for p, _ in prefixes]),
                                  np.array([v for _, v in prefixes], bool))
        infer_ms = 1e3 * (time.perf_counter() - t0)
        replies = []
        for i, it in enumerate(items):
            actions, it.session.state = self._run_execution(out, i, it.session.state)
            reply = {"actions": actions, "stride": int(out["stride"][i]), "freq_index": int(out["freq_index"][i]),
                     "entropy": float(out["entropy"][i]), "decision": it.decision,
                     "server_timing": {"infer_ms": infer_ms, "queue_ms": 1e3 * (started - it.enqueued),
                                       "batch": rows}}
            if it.request.chunks:
                reply["chunks"] = np.asarray(out["chunks"][i])
            replies.append(reply)
        return replies

    async def _batch_loop(self) -> None:
        """Collect a batch whenever a worker is free; hand it to the worker and collect the next."""
        loop, cfg = asyncio.get_running_loop(), self.config
        free = asyncio.Semaphore(cfg.workers)
        running: set[asyncio.Task] = set()
        while True:
            await free.acquire()
            batch = [await self._queue.get()]
            deadline = loop.time() + cfg.batch_window_ms / 1e3
            while len(batch) < cfg.max_batch:
                while len(batch) < cfg.max_batch and not self._queue.empty():
                    batch.append(self._queue.get_nowait())
                # every connection not being decided has a request in (no other can come), or this batch has its
                # share of the open connections across the workers
                waiting = self.connections - self._deciding
                share = -(-self.connections // cfg.workers)
                if len(batch) >= min(cfg.max_batch, waiting, share) or loop.time() >= deadline:
                    break
                try:
                    batch.append(await asyncio.wait_for(self._queue.get(), deadline - loop.time()))
                except TimeoutError:
                    break
            live = [it for it in batch if not it.future.done()]
            if not live:
                free.release()
                continue
            self._deciding += len(live)
            task = asyncio.create_task(self._run_batch(live, free))
            running.add(task)
            task.add_done_callback(running.discard)

    async def _run_batch(self, live: list[_Pending], free: asyncio.Semaphore) -> None:
        try:
            replies = await asyncio.get_running_loop().run_in_executor(self._worker, self._decide_batch, live)
        except Exception as e:  # noqa: BLE001 - every request of the batch gets the error
            replies = [e] * len(live)
        finally:
            self._deciding -= len(live)
            free.release()
        self.batches += 1
        self.rows += len(live)
        self.largest_batch = max(self.largest_batch, len(live))
        for it, reply in zip(live, replies):
            if it.future.done():
                continue
            if isinstance(reply, Exception):
                it.future.set_exception(reply)
            else:
                it.future.set_result(reply)

    # ---------------------------------------------------------------------------------------------- requests
    async def _answer(self, data, session: _Session) -> dict:
        if not isinstance(data, str) and len(data) > self.config.max_message_bytes:
            raise protocol.ProtocolError(f"message of {len(data)} bytes exceeds the server's limit of "
                                         f"{self.config.max_message_bytes} bytes")
        request = protocol.parse_request(protocol.unpack(data), self.backend.metadata)
        if request.reset:
            session.state, session.decisions = self._initial_state, 0
        pending = _Pending(request, session, session.decisions, time.perf_counter(),
                           asyncio.get_running_loop().create_future())
        session.decisions += 1
        self._queue.put_nowait(pending)
        return await pending.future

    async def _handler(self, websocket):
        session = _Session(self._initial_state)
        self.connections += 1
        try:
            await websocket.send(self._metadata_frame)
            async for data in websocket:
                try:
                    reply = await self._answer(data, session)
                except protocol.ProtocolError as e:
                    self.errors += 1
                    await websocket.send(protocol.one_line(str(e)))
                    continue
                except Exception as e:  # noqa: BLE001 - the server keeps serving whatever one request does
                    self.errors += 1
                    await websocket.send(protocol.one_line(f"internal error: {type(e).__name__}: {e}"))
                    await websocket.close(CloseCode.INTERNAL_ERROR, "internal error, see the previous frame")
                    return
                self.requests += 1
                await websocket.send(protocol.pack(reply))
        except ConnectionClosed:
            pass
        finally:
            self.connections -= 1

    def health(self) -> dict:
        return {"status": "ok", "requests": self.requests, "errors": self.errors, "refused": self.refused,
                "batches": self.batches, "mean_batch": self.rows / max(self.batches, 1),
                "largest_batch": self.largest_batch, "connections": self.connections,
                "uptime_s": time.monotonic() - self._t0}

    def _process_request(self, connection, request):
        """Before the websocket handshake: ``/healthz``, then the API key."""
        if request.path.split("?")[0] == "/healthz":
            return connection.respond(http.HTTPStatus.OK, json.dumps(self.health()) + "\n")
        if self.config.api_key:
            got = request.headers.get("Authorization", "")
            if not hmac.compare_digest(got.encode(), f"Api-Key {self.config.api_key}".encode()):
                self.refused += 1
                return connection.respond(http.HTTPStatus.UNAUTHORIZED,
                                          "missing or wrong API key: send 'Authorization: Api-Key <key>'\n")
        return None

    # ------------------------------------------------------------------------------------------------- serving
    async def serve_async(self) -> None:
        """Warm up, then serve until ``stop()``."""
        self._loop = asyncio.get_running_loop()
        self._stop = self._loop.create_future()
        self._queue = asyncio.Queue()
        seconds = await self._loop.run_in_executor(self._worker, self._warmup)
        batcher = asyncio.create_task(self._batch_loop())
        try:
            async with serve(self._handler, self.host, self.port, max_size=2 * self.config.max_message_bytes,
                             compression=None, process_request=self._process_request) as server:
                self.port = server.sockets[0].getsockname()[1]
                meta, cfg = self.metadata, self.config
                self.log(f"serving the {meta['task']} policy (strides {meta['strides']}, N={meta['num_samples']}, "
                         f"execution {self.strategy.name}) on ws://{self.host}:{self.port} (batches of up to "
                         f"{cfg.max_batch} within {cfg.batch_window_ms:g} ms; "
                         f"{'API key required' if cfg.api_key else 'no API key'}; compiled and warmed up in "
                         f"{seconds:.1f} s)")
                self.started.set()
                await self._stop
        finally:
            batcher.cancel()
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


__all__ = ["API_KEY_ENV", "PolicyServer", "ServerConfig"]
