"""The policy server's client, and a remote policy with the evaluator's interface.

``PolicyClient(url)`` speaks ``protocol`` over one websocket (synchronous; thread-safe by a lock): ``metadata()``,
``health()``, ``infer(obs, key_data)``. ``remote_policy(client)`` returns ``(policy_fn, init_fn)`` as
``evaluation.policy.make_policy_fn`` does, so ``rollout.Rollout`` runs an MJX evaluation through the server: the
decision comes back over the socket (a ``jax.pure_callback`` inside the compiled rollout, one request per decision
round carrying every episode's history and key), the execution strategy runs here. With the same keys it computes
what the in-process evaluation computes (``evaluate_remote``).
"""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np
from websockets.sync.client import connect

from hipolicy_jax.checkpoint import config_from_dict
from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.deploy import protocol
from hipolicy_jax.envs import make_for_encoder
from hipolicy_jax.evaluation.execution import Decision, make_execution
from hipolicy_jax.evaluation.rollout import EvalResult, Rollout


class PolicyServerError(RuntimeError):
    """The server answered with an error reply."""


class PolicyClient:
    """A connection to ``experiments.serve`` at ``url`` (``ws://127.0.0.1:8000``)."""

    def __init__(self, url: str, timeout: float = 60.0):
        self.url = url
        self._connection = connect(url, max_size=None, compression=None, open_timeout=timeout)
        self._ws = self._connection.__enter__()
        self._timeout = timeout
        self._lock = threading.Lock()
        self._metadata = None

    def request(self, message: dict) -> dict:
        """Send one message, return its reply; raises ``PolicyServerError`` on an error reply."""
        with self._lock:
            self._ws.send(protocol.pack(message))
            reply = protocol.unpack(self._ws.recv(timeout=self._timeout))
        if reply.get("type") == "error":
            raise PolicyServerError(reply["error"])
        return reply

    def metadata(self) -> dict:
        if self._metadata is None:
            self._metadata = self.request({"type": "metadata"})["metadata"]
        return self._metadata

    def health(self) -> dict:
        return self.request({"type": "health"})

    def infer(self, obs: dict[str, np.ndarray], key_data: np.ndarray | None = None, *, seed: int | None = None,
              chunks: bool = False) -> dict:
        """One decision per observation history: ``obs`` {key: (obs_span, ...) or (B, obs_span, ...)}, ``key_data``
        (2,) / (B, 2) uint32 raw keys (or ``seed``) → the reply (``actions``, ``stride``, ``freq_index``,
        ``entropy``[, ``chunks``], ``server_ms``)."""
        spec = self.metadata()["obs"]
        message = {"type": "infer", "obs": {k: np.asarray(v, spec[k]["dtype"]) if k in spec else np.asarray(v)
                                            for k, v in obs.items()}, "chunks": chunks}
        if key_data is not None:
            message["key"] = np.asarray(key_data, np.uint32)
        elif seed is not None:
            message["seed"] = int(seed)
        return self.request(message)

    def close(self) -> None:
        self._connection.__exit__(None, None, None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def policy_config(metadata: dict) -> PolicyConfig:
    """The served policy's configuration (windowing, encoder), from its manifest."""
    return config_from_dict(PolicyConfig, metadata["policy"])


def remote_policy(client: PolicyClient, execution: InferenceConfig | None = None):
    """``(policy_fn, init_fn)`` for ONE episode (vmap over episodes), computed by the server: the decision over
    the socket, the execution strategy of ``execution`` (default: the served inference settings) here. The
    ``policy_args`` of the rollout are unused (pass ``()``)."""
    meta = client.metadata()
    chunk, action_dim, n = policy_config(meta).chunk, int(meta["action_dim"]), int(meta["num_samples"])
    execution = execution or InferenceConfig(**meta["inference"])
    if execution.num_samples != n:
        raise ValueError(f"execution.num_samples: the server draws N={n} samples, got {execution.num_samples}")
    if execution.delay and execution.handover == "inpaint":
        raise ValueError("inference.handover: prefix inpainting runs inside the sampler, in-process only; a remote "
                         "policy hands over 'naive'")
    strategy = make_execution(execution)
    shapes = {"actions": ((chunk.chunk_len, action_dim), jnp.float32), "stride": ((), jnp.int32),
              "freq_index": ((), jnp.int32), "entropy": ((), jnp.float32),
              "chunks": ((n, chunk.horizon, action_dim), jnp.float32)}
    keys = tuple(meta["obs"])

    def call_server(obs, key_data):
        reply = client.infer(obs, key_data.reshape(-1, 2), chunks=True)  # obs (E, obs_span, ...), one row per episode
        return {k: np.asarray(reply[k], dt).reshape(key_data.shape[:-1] + s) for k, (s, dt) in shapes.items()}

    def policy_fn(obs_history, key, state, args=()):
        out_shape = {k: jax.ShapeDtypeStruct(s, dt) for k, (s, dt) in shapes.items()}
        out = jax.pure_callback(call_server, out_shape, {k: obs_history[k] for k in keys},
                                jax.random.key_data(key), vmap_method="broadcast_all")
        d = Decision(chunks=out["chunks"], entropy=out["entropy"], freq_index=out["freq_index"],
                     stride=out["stride"], actions=out["actions"])
        return strategy.decide(d, state, chunk)

    def init_fn(obs, key):
        return strategy.init(chunk, action_dim)

    return policy_fn, init_fn, strategy


def evaluate_remote(client: PolicyClient, num_episodes: int, key: jax.Array, *,
                    execution: InferenceConfig | None = None, max_steps: int | None = None) -> EvalResult:
    """Closed-loop evaluation of the served policy on its task (episodes from ``key``, as ``Evaluator.evaluate``)."""
    meta = client.metadata()
    policy_fn, init_fn, strategy = remote_policy(client, execution)
    cfg = policy_config(meta)
    chunk, env = cfg.chunk, make_for_encoder(meta["task"], cfg.encoder)
    rollout = Rollout(env, policy_fn, init_fn, history_len=chunk.obs_span, chunk_len=strategy.exec_len(chunk),
                      max_steps=max_steps, min_actions=strategy.min_actions(chunk))
    return rollout(num_episodes, key, ())[0]


__all__ = ["PolicyClient", "PolicyServerError", "evaluate_remote", "policy_config", "remote_policy"]
