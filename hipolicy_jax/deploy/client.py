"""The policy server's client, and remote evaluation through it.

``PolicyClient(url)`` is one robot's connection, speaking the server's protocol (openpi's, ``protocol``; so
``openpi_client.websocket_client_policy.WebsocketClientPolicy`` is an equivalent client): ``metadata()`` (the frame
the server sends on connect), ``infer(obs, key=None, seed=None, reset=False, chunks=False)``, ``health()`` (HTTP
``GET /healthz``). ``api_key`` (default: the ``HIPOLICY_API_KEY`` environment variable) is sent as
``Authorization: Api-Key <key>``, as openpi's client does.

``RemoteEvaluator`` (``evaluate_remote`` / ``rollout_remote`` for one-off use) runs an MJX evaluation through the
server: one connection per episode (the server's execution memory is per connection), every decision round's
requests sent at once so the server batches them, each decision's key (the in-process rollout's) sent with it:
the result is the in-process evaluation's on the same keys.
"""

from __future__ import annotations

import json
import os
import threading
import urllib.request

import jax
import jax.numpy as jnp
import numpy as np
from websockets.sync.client import connect

from hipolicy_jax.checkpoint import config_from_dict
from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.server import API_KEY_ENV
from hipolicy_jax.envs import make_for_encoder
from hipolicy_jax.evaluation.execution import make_execution
from hipolicy_jax.evaluation.rollout import EvalResult, PolicyOutput, Recording, Rollout


class PolicyServerError(RuntimeError):
    """The server answered with an error frame."""


class PolicyClient:
    """A connection to ``experiments.serve`` at ``url`` (``ws://127.0.0.1:8000``)."""

    def __init__(self, url: str, timeout: float = 60.0, api_key: str | None = None):
        self.url, self._timeout = url, timeout
        self.api_key = os.environ.get(API_KEY_ENV, "") if api_key is None else api_key
        headers = {"Authorization": f"Api-Key {self.api_key}"} if self.api_key else None
        self._connection = connect(url, max_size=None, compression=None, open_timeout=timeout,
                                   additional_headers=headers)
        self._ws = self._connection.__enter__()
        self._lock = threading.Lock()
        self._metadata = self._receive()

    def _receive(self):
        reply = self._ws.recv(timeout=self._timeout)
        if isinstance(reply, str):
            raise PolicyServerError(reply)
        return protocol.unpack(reply)

    def metadata(self) -> dict:
        """The manifest the server sent on connect (``backend.make_metadata`` plus ``"server"``)."""
        return self._metadata

    def send(self, message: dict) -> None:
        """Send one frame (pair with ``receive``; ``infer`` does both)."""
        self._ws.send(protocol.pack(message))

    def receive(self) -> dict:
        """The next reply; ``PolicyServerError`` for an error frame."""
        return self._receive()

    def request(self, message: dict) -> dict:
        with self._lock:
            self.send(message)
            return self.receive()

    def message(self, obs: dict[str, np.ndarray], key=None, *, seed: int | None = None, reset: bool = False,
                chunks: bool = False) -> dict:
        """The frame of one observation history ``obs`` {key: (obs_span, ...)} (cast to the manifest's dtypes)."""
        spec = self._metadata["obs"]
        message = {k: np.asarray(v, spec[k]["dtype"]) if k in spec else np.asarray(v) for k, v in obs.items()}
        if key is not None:
            message["key"] = np.asarray(key, np.uint32)
        if seed is not None:
            message["seed"] = int(seed)
        if reset:
            message["reset"] = True
        if chunks:
            message["chunks"] = True
        return message

    def infer(self, obs: dict[str, np.ndarray], key=None, *, seed: int | None = None, reset: bool = False,
              chunks: bool = False) -> dict:
        """One decision for one observation history: ``key`` (2,) uint32 raw key data or ``seed`` (neither: the
        connection's next default key, ``protocol.decision_key``) → the reply (``actions`` (n, A) to execute,
        ``stride``, ``freq_index``, ``entropy``, ``decision``, ``server_timing``[, ``chunks``])."""
        return self.request(self.message(obs, key, seed=seed, reset=reset, chunks=chunks))

    def health(self) -> dict:
        """``GET /healthz`` → the server's counters."""
        url = "http" + self.url[2:] if self.url.startswith("ws") else self.url
        with urllib.request.urlopen(url.rstrip("/") + "/healthz", timeout=self._timeout) as r:
            return json.loads(r.read())

    def close(self) -> None:
        self._connection.__exit__(None, None, None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def policy_config(metadata: dict) -> PolicyConfig:
    """The served policy's configuration (windowing, encoder), from its manifest."""
    return config_from_dict(PolicyConfig, metadata["policy"])


class _EpisodeConnections:
    """One connection per episode row; a decision round sends every row's request before reading any reply."""

    def __init__(self, url: str, api_key: str | None, timeout: float):
        self.url, self.api_key, self.timeout = url, api_key, timeout
        self.clients: list[PolicyClient] = []

    def open(self) -> PolicyClient:
        if not self.clients:
            self.clients.append(PolicyClient(self.url, self.timeout, self.api_key))
        return self.clients[0]

    def decide(self, obs: dict[str, np.ndarray], key_data: np.ndarray) -> list[dict]:
        rows = key_data.shape[0]
        while len(self.clients) < rows:
            self.clients.append(PolicyClient(self.url, self.timeout, self.api_key))
        for i in range(rows):
            c = self.clients[i]
            c.send(c.message({k: v[i] for k, v in obs.items()}, key_data[i]))
        return [self.clients[i].receive() for i in range(rows)]

    def close(self) -> None:
        for c in self.clients:
            c.close()
        self.clients = []


class RemoteEvaluator:
    """Closed-loop evaluation of a served policy on its task through the server: one compiled rollout (MJX, the
    decision a ``jax.pure_callback`` per round) for every server of a policy with this manifest's task, observations,
    configuration and execution strategy (other parameters, other checkpoints)."""

    COMPATIBLE = ("task", "obs", "action_dim", "policy", "inference")

    def __init__(self, metadata: dict, *, max_steps: int | None = None, timeout: float = 120.0):
        self.metadata, self.timeout = metadata, timeout
        cfg = policy_config(metadata)
        chunk, action_dim = cfg.chunk, int(metadata["action_dim"])
        strategy = make_execution(InferenceConfig(**metadata["inference"]))
        exec_len, keys = strategy.exec_len(chunk), tuple(metadata["obs"])
        self._connections: _EpisodeConnections | None = None

        def call_server(obs, key_data):  # obs (E, obs_span, ...), key_data (E, 2): one row per episode
            lead = key_data.shape[:-1]
            replies = self._connections.decide(
                {k: np.asarray(v).reshape(-1, *v.shape[len(lead):]) for k, v in obs.items()},
                np.asarray(key_data, np.uint32).reshape(-1, 2))
            actions = np.zeros((len(replies), exec_len, action_dim), np.float32)
            for i, r in enumerate(replies):
                actions[i, :len(r["actions"])] = r["actions"]
            return {"actions": actions.reshape(*lead, exec_len, action_dim),
                    "num_actions": np.array([len(r["actions"]) for r in replies], np.int32).reshape(lead),
                    "stride": np.array([r["stride"] for r in replies], np.int32).reshape(lead),
                    "entropy": np.array([r["entropy"] for r in replies], np.float32).reshape(lead)}

        shapes = {"actions": jax.ShapeDtypeStruct((exec_len, action_dim), jnp.float32),
                  "num_actions": jax.ShapeDtypeStruct((), jnp.int32), "stride": jax.ShapeDtypeStruct((), jnp.int32),
                  "entropy": jax.ShapeDtypeStruct((), jnp.float32)}

        def policy_fn(obs_history, key, state, args=()):
            out = jax.pure_callback(call_server, shapes, {k: obs_history[k] for k in keys}, jax.random.key_data(key),
                                    vmap_method="broadcast_all")
            return PolicyOutput(out["actions"], out["stride"], out["entropy"], out["num_actions"]), state

        def init_fn(obs, key):
            return ()

        self._rollout = Rollout(make_for_encoder(metadata["task"], cfg.encoder), policy_fn, init_fn,
                                history_len=chunk.obs_span, chunk_len=exec_len, max_steps=max_steps,
                                min_actions=strategy.min_actions(chunk))

    def rollout(self, client: PolicyClient | str, num_episodes: int, key: jax.Array, *,
                api_key: str | None = None) -> tuple[EvalResult, Recording]:
        """Episodes from ``key`` (as ``Evaluator.rollout``) through the server of ``client`` (a ``PolicyClient``:
        its url and key; or a url) → (result, qpos recording)."""
        url = client if isinstance(client, str) else client.url
        api_key = api_key if api_key is not None or isinstance(client, str) else client.api_key
        self._connections = _EpisodeConnections(url, api_key, self.timeout)
        try:
            meta = self._connections.open().metadata()
            differ = [k for k in self.COMPATIBLE if meta.get(k) != self.metadata.get(k)]
            if differ:
                raise ValueError(f"{url}: the served policy differs from this evaluator's in {differ}; build a "
                                 f"RemoteEvaluator from its metadata")
            return jax.block_until_ready(self._rollout(num_episodes, key, ()))  # every callback done before closing
        finally:
            self._connections.close()
            self._connections = None


def rollout_remote(client: PolicyClient | str, num_episodes: int, key: jax.Array, *, max_steps: int | None = None,
                   api_key: str | None = None, timeout: float = 120.0) -> tuple[EvalResult, Recording]:
    """One-off ``RemoteEvaluator``: the served policy's closed-loop evaluation on its task → (result, recording).
    Compiles on every call; keep a ``RemoteEvaluator`` to evaluate repeatedly."""
    url = client if isinstance(client, str) else client.url
    api_key = api_key if api_key is not None or isinstance(client, str) else client.api_key
    with PolicyClient(url, timeout, api_key) as probe:
        meta = probe.metadata()
    return RemoteEvaluator(meta, max_steps=max_steps, timeout=timeout).rollout(url, num_episodes, key,
                                                                               api_key=api_key)


def evaluate_remote(client: PolicyClient | str, num_episodes: int, key: jax.Array, *,
                    max_steps: int | None = None, api_key: str | None = None) -> EvalResult:
    """``rollout_remote`` without the recording."""
    return rollout_remote(client, num_episodes, key, max_steps=max_steps, api_key=api_key)[0]


__all__ = ["PolicyClient", "PolicyServerError", "RemoteEvaluator", "evaluate_remote", "policy_config", "rollout_remote"]
