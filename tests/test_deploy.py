"""Deployment: the exported policy against the in-process one (in this process and in a process without the model
code), the exported program's committed-prefix inputs (an invalid prefix decides exactly as none, a valid one is
inpainted; an old artifact is refused), the websocket server (openpi's wire protocol) and its clients (round trip,
default keys, every bad request, micro-batching, the API key, openpi's own client in closed loop = in-process,
remote evaluation = in-process evaluation for two parameter sets and under delay d = 2 with remote inpainting), a
bounded load test, and the two entry points."""

import contextlib
import copy
import dataclasses
import json
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
import urllib.request

import jax
import jax.numpy as jnp
import msgpack
import numpy as np
import pytest
import shutil
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from experiments import export as export_cli
from experiments import serve as serve_cli
from hipolicy_jax import envs
from hipolicy_jax.config import EvalConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.backend import ExportedBackend, InProcessBackend, PolicyBackend
from hipolicy_jax.deploy.client import PolicyClient, PolicyServerError, RemoteEvaluator, policy_config
from hipolicy_jax.deploy.export import export_backend
from hipolicy_jax.deploy.server import API_KEY_ENV, PolicyServer, ServerConfig
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.runs.serve import run_backend
from hipolicy_jax.runs.store import eval_key, load_run, make_evaluator, run_inference
from hipolicy_jax.runs.train import RunConfig, train

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A 2-step tiny press_button run (strides 1/2/3, N = 4, DDIM 2) on a synthetic demo buffer."""
    tmp = tmp_path_factory.mktemp("deploy")
    env, rng = envs.make("press_button"), np.random.default_rng(0)
    data = tmp / "demos.zarr"
    ReplayBuffer(data={"state": rng.random((180, env.state_dim), np.float32),
                       "action": rng.random((180, env.action_dim), np.float32)},
                 episode_ends=np.arange(30, 181, 30)).save(data)
    out = tmp / "run"
    train(RunConfig(task="press_button", out=str(out), data=str(data), episodes=6, val_ratio=0.34,
                    policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
                    train=TrainConfig(batch_size=16, num_steps=2, warmup_steps=1, log_every=1, ckpt_every=2),
                    eval=EvalConfig(episodes=1, every=0),
                    inference=InferenceConfig(num_samples=4, num_steps=2, calib_windows=8), progress=False,
                    final_eval=False))
    return str(out)


@pytest.fixture(scope="module")
def exported(run_dir, tmp_path_factory):
    backend = run_backend(run_dir)
    directory = str(tmp_path_factory.mktemp("export") / "policy")
    export_backend(backend, directory)
    return backend, directory


def _obs(meta, batch, seed=0):
    rng = np.random.default_rng(seed)
    return {k: rng.normal(size=(batch, *s["shape"])).astype(s["dtype"]) for k, s in meta["obs"].items()}


def _keys(batch, seed=0):
    return np.asarray(jax.random.key_data(jax.random.split(jax.random.key(seed), batch)))


def test_export_round_trip_matches_in_process(exported):
    backend, directory = exported
    meta = backend.metadata
    env = envs.make("press_button")
    assert meta["obs"] == {"state": {"shape": [7, env.state_dim], "dtype": "float32"}}  # obs_span = (3-1)·3 + 1
    assert str(env.reset(jax.random.key(0)).obs["state"].dtype) == meta["obs"]["state"]["dtype"]
    assert meta["strides"] == [1, 2, 3] and meta["action_dim"] == 4 and meta["num_samples"] == 4
    assert meta["thresholds_source"] == "calibration.json" and len(meta["thresholds"]) == 4
    assert meta["version"] == 2 and meta["inputs"]["prefix"] == ["B", 0, 4]  # no inpainting: an empty prefix
    assert meta["inputs"]["prefix_valid"] == ["B"] and meta["inputs"]["obs"] == {"state": ["B", 7, env.state_dim]}
    loaded = ExportedBackend(directory)
    assert loaded.metadata["obs"] == meta["obs"] and loaded.metadata["platforms"] == ["cpu"]
    for batch in (1, 3):  # one artifact, any batch size
        obs, keys = _obs(meta, batch), _keys(batch)
        a, b = backend.decide(obs, keys), loaded.decide(obs, keys)
        assert a["actions"].shape == (batch, 8, 4) and a["chunks"].shape == (batch, 4, 24, 4)
        for k in a:
            np.testing.assert_allclose(b[k], a[k], atol=1e-5, err_msg=k)
    # a row's decision depends on its own history and key only
    one = loaded.decide({k: v[1:2] for k, v in _obs(meta, 3).items()}, _keys(3)[1:2])
    np.testing.assert_allclose(one["actions"][0], backend.decide(_obs(meta, 3), _keys(3))["actions"][1], atol=1e-5)


def test_export_loads_without_the_model_code(exported, tmp_path):
    """A fresh process with only jax and numpy (hipolicy_jax cannot be imported there) runs the artifact."""
    backend, directory = exported
    obs, keys = _obs(backend.metadata, 2), _keys(2)
    np.savez(tmp_path / "in.npz", state=obs["state"], keys=keys)
    script = textwrap.dedent(f"""
        import sys, json
        sys.modules["hipolicy_jax"] = None  # importing the project fails from here on
        import numpy as np, jax
        from jax import export
        d = {directory!r}
        program = export.deserialize(bytearray(open(d + "/policy.jaxexport", "rb").read()))
        z = np.load(d + "/params.npz")
        leaves = [z[n] for n in sorted(z.files)]
        x = np.load({str(tmp_path / "in.npz")!r})
        batch = x["keys"].shape[0]
        out = program.call(leaves, {{"state": x["state"]}}, x["keys"], np.zeros((batch, 0, 4), np.float32),
                           np.zeros((batch,), bool))
        np.savez({str(tmp_path / "out.npz")!r}, **{{k: np.asarray(v) for k, v in out.items()}})
    """)
    subprocess.run([sys.executable, "-c", script], check=True, timeout=300,
                   env={**os.environ, "PYTHONPATH": ""}, cwd=str(tmp_path))
    out, ref = np.load(tmp_path / "out.npz"), backend.decide(obs, keys)
    for k in ref:
        np.testing.assert_allclose(out[k], ref[k], atol=1e-5, err_msg=k)


def test_export_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="is not a directory; expected what experiments.export wrote"):
        ExportedBackend(str(tmp_path / "nope"))
    (tmp_path / "bad").mkdir()
    with pytest.raises(FileNotFoundError, match=r"lacks \['policy.jaxexport', 'params.npz', 'manifest.json'\]"):
        ExportedBackend(str(tmp_path / "bad"))


@pytest.fixture(scope="module")
def server(exported):
    """The exported policy behind the server: batches of up to 4 within 500 ms (a batch leaves as soon as every
    open connection has a request in it)."""
    _, directory = exported
    srv = PolicyServer(ExportedBackend(directory), ServerConfig(port=0, max_message_bytes=64 * 1024, max_batch=4,
                                                                batch_window_ms=500), log=lambda msg: None)
    srv.start_in_thread()
    yield srv
    srv.stop()


def _url(srv) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def test_server_config_errors_name_the_field():
    for kwargs, pattern in [({"max_batch": 0}, r"max_batch: expected 1 to 1024"),
                            ({"port": 70000}, r"port: expected an int in \[0, 65535\]"),
                            ({"batch_window_ms": -1}, r"batch_window_ms: expected 0 to 1000 ms"),
                            ({"seed": -1}, r"seed: expected an int"),
                            ({"workers": 0}, r"workers: expected 1 to 16 concurrent batches"),
                            ({"api_key": "two words"}, r"api_key: expected printable ASCII without spaces")]:
        with pytest.raises(ValueError, match=pattern):
            ServerConfig(**kwargs)
    assert ServerConfig(max_batch=8).batch_sizes == (1, 2, 4, 8)
    assert ServerConfig(max_batch=6).batch_sizes == (1, 2, 4, 6)
    assert ServerConfig(max_batch=1).batch_sizes == (1,)


def test_server_round_trip_metadata_and_health(exported, server):
    backend, _ = exported
    meta = backend.metadata
    with PolicyClient(_url(server)) as client:
        sent = client.metadata()  # the frame the server sends on connect
        assert sent["obs"] == meta["obs"] and sent["strides"] == [1, 2, 3]
        assert sent["server"]["protocol"] == "openpi-msgpack-numpy" and sent["server"]["execution"] == "chunk"
        assert sent["server"]["reserved"] == ["key", "seed", "reset", "chunks"]
        obs, keys = _obs(meta, 2), _keys(2)
        ref = backend.decide(obs, keys)
        for i in range(2):
            reply = client.infer({k: v[i] for k, v in obs.items()}, keys[i], chunks=True)
            assert reply["actions"].shape == (8, 4) and reply["actions"].dtype == np.float32  # L_c actions
            np.testing.assert_allclose(reply["actions"], ref["actions"][i], atol=1e-5)
            np.testing.assert_allclose(reply["chunks"], ref["chunks"][i], atol=1e-5)
            assert reply["stride"] == ref["stride"][i] and reply["freq_index"] == ref["freq_index"][i]
            assert isinstance(reply["stride"], int) and isinstance(reply["entropy"], float)
            np.testing.assert_allclose(reply["entropy"], ref["entropy"][i], atol=1e-4)
            assert reply["decision"] == i and reply["server_timing"]["infer_ms"] > 0
            assert reply["server_timing"]["batch"] == 1
        first = {k: v[0] for k, v in obs.items()}
        assert "chunks" not in client.infer(first, keys[0])
        by_seed = client.infer(first, seed=7)
        same = client.infer(first, np.asarray(jax.random.key_data(jax.random.key(7))))
        np.testing.assert_array_equal(by_seed["actions"], same["actions"])
        health = client.health()
        assert health["status"] == "ok" and health["requests"] >= 5
    with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=30) as r:
        assert r.status == 200 and json.loads(r.read())["status"] == "ok"


def test_default_keys_count_the_connections_decisions(exported, server):
    """Without key or seed (openpi clients send only observations), decision n of a connection uses
    fold_in(key(server seed), n); a new connection or a ``reset`` entry starts again from n = 0."""
    backend, _ = exported
    n2 = np.asarray(jax.random.key_data(jax.random.fold_in(jax.random.key(0), 2)))
    np.testing.assert_array_equal(protocol.decision_key(0, 2), n2)
    obs = {k: v[0] for k, v in _obs(backend.metadata, 1, seed=4).items()}
    with PolicyClient(_url(server)) as client:
        replies = [client.infer(obs) for _ in range(3)]
        assert [r["decision"] for r in replies] == [0, 1, 2]
        for n, r in enumerate(replies):
            explicit = client.infer(obs, protocol.decision_key(0, n))
            np.testing.assert_array_equal(r["actions"], explicit["actions"])
        assert not np.allclose(replies[0]["actions"], replies[1]["actions"])
        again = client.infer(obs, reset=True)
        assert again["decision"] == 0
        np.testing.assert_array_equal(again["actions"], replies[0]["actions"])
    with PolicyClient(_url(server)) as fresh:
        np.testing.assert_array_equal(fresh.infer(obs)["actions"], replies[0]["actions"])


GOOD = {"state": np.zeros((7, 7), np.float32)}
BAD_REQUESTS = [
    ("unknown key", {**GOOD, "image": np.zeros((2,), np.uint8)},
     r"observation keys \['image', 'state'\] do not match the policy's \['state'\] \(unknown: \['image'\]"),
    ("missing key", {"seed": 0}, r"missing: \['state'\]"),
    ("wrong shape", {"state": np.zeros((7, 6), np.float32)}, r"state: expected shape \(7, 7\), got \(7, 6\)$"),
    ("a batch", {"state": np.zeros((3, 7, 7), np.float32)},
     r"state: expected shape \(7, 7\), got \(3, 7, 7\) \(one observation history per request\)"),
    ("wrong dtype", {"state": np.zeros((7, 7), np.int32)},
     r"state: expected floating values \(float32\), got dtype int32"),
    ("NaN", {"state": np.full((7, 7), np.nan, np.float32)}, r"state: holds NaN or Inf"),
    ("Inf", {"state": np.full((7, 7), np.inf, np.float64)}, r"state: holds NaN or Inf"),
    ("not an array", {"state": [1, 2]}, r"state: expected an array of shape \(7, 7\), got list"),
    ("bad key", {**GOOD, "key": np.zeros((2,), np.int64)}, r"key: expected uint32 raw PRNG key data of shape \(2,\)"),
    ("key and seed", {**GOOD, "key": np.zeros((2,), np.uint32), "seed": 1}, r"key, seed: pass at most one"),
    ("bad seed", {**GOOD, "seed": -1}, r"seed: expected an int in \[0, 2\*\*32\), got -1"),
    ("bad reset", {**GOOD, "reset": "yes"}, r"reset: expected true or false, got 'yes'"),
    ("not a map", [1, 2], r"expected a map of observation key to array, got list"),
]


@contextlib.contextmanager
def _raw(srv):
    """A bare websocket to ``srv`` past the metadata frame."""
    with connect(_url(srv), max_size=None) as ws:
        assert protocol.unpack(ws.recv(timeout=60))["task"] == "press_button"
        yield ws


@pytest.mark.parametrize("name,message,pattern", BAD_REQUESTS, ids=[b[0] for b in BAD_REQUESTS])
def test_bad_requests_get_an_error_frame_and_the_server_keeps_serving(server, name, message, pattern):
    with _raw(server) as ws:
        ws.send(protocol.pack(message))
        reply = ws.recv(timeout=60)
        assert isinstance(reply, str) and "\n" not in reply and re.search(pattern, reply), reply
        ws.send(protocol.pack({**GOOD, "seed": 1}))  # the same connection still serves
        assert protocol.unpack(ws.recv(timeout=60))["actions"].shape == (8, 4)


def _ndarray(data: bytes, dtype: str, shape) -> bytes:
    return msgpack.packb({"state": {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}})


def test_malformed_frames_get_an_error_frame(server):
    with _raw(server) as ws:
        for frame, pattern in [(b"\xc1\xff garbage", r"frame is not a msgpack message"),
                               ("a text frame", r"expected a binary msgpack frame, got a text frame"),
                               (_ndarray(b"\x00" * 12, "<f4", [7, 7]),
                                r"array payload: 12 data bytes for shape \(7, 7\) of float32 \(expected 196\)"),
                               (_ndarray(b"\x00" * 8, "|O", [1]), r"array payload: dtype object is not numeric"),
                               (_ndarray(b"", "<f4", "7x7"), r"array payload: shape must be a list"),
                               (_ndarray(b"", "nope", [0]), r"array payload: unknown dtype 'nope'"),
                               (b"\x00" * (100 * 1024), r"message of 102400 bytes exceeds the server's limit of "
                                                        r"65536 bytes")]:
            ws.send(frame)
            reply = ws.recv(timeout=60)
            assert isinstance(reply, str) and re.search(pattern, reply), (frame[:20], reply)
    with _raw(server) as ws:  # above twice the limit: refused unread
        ws.send(b"\x00" * (200 * 1024))
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=60)
        assert closed.value.rcvd.code == 1009
    with PolicyClient(_url(server)) as client:  # still serving
        assert client.health()["errors"] >= 7
        with pytest.raises(PolicyServerError, match="missing"):
            client.request({})


class _Flaky(PolicyBackend):
    """A backend that fails on demand."""

    def __init__(self, inner):
        self.inner, self.metadata, self.fail = inner, inner.metadata, False

    def decide(self, obs, key_data, *prefix):
        if self.fail:
            raise RuntimeError("the accelerator fell over")
        return self.inner.decide(obs, key_data, *prefix)


def test_internal_error_sends_its_line_and_closes_with_1011(exported):
    backend, _ = exported
    flaky = _Flaky(backend)
    srv = PolicyServer(flaky, ServerConfig(port=0, max_batch=1), log=lambda msg: None)
    srv.start_in_thread()
    try:
        with _raw(srv) as ws:
            flaky.fail = True
            ws.send(protocol.pack(GOOD))
            assert ws.recv(timeout=60) == "internal error: RuntimeError: the accelerator fell over"
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=60)
            assert closed.value.rcvd.code == 1011
        flaky.fail = False
        with PolicyClient(_url(srv)) as client:  # the server itself keeps serving
            assert client.infer(GOOD, seed=0)["actions"].shape == (8, 4)
            assert client.health()["errors"] == 1
    finally:
        srv.stop()


def test_concurrent_requests_are_decided_in_one_batch(exported, server):
    """Four connections send at once: ONE backend call decides them (padded to a compiled size) and each gets its
    own answer, the one it gets alone; with max_batch 4 a fifth waits for the next call; a lone request waits the
    window only while another connection is open."""
    backend, _ = exported
    obs, keys = _obs(backend.metadata, 5, seed=9), _keys(5, seed=9)
    clients = [PolicyClient(_url(server)) for _ in range(5)]
    try:
        alone = [clients[0].infer({k: v[i] for k, v in obs.items()}, keys[i]) for i in range(5)]
        batches = server.batches
        for i in range(4):
            clients[i].send(clients[i].message({k: v[i] for k, v in obs.items()}, keys[i]))
        together = [c.receive() for c in clients[:4]]
        assert server.batches == batches + 1
        for i, reply in enumerate(together):
            assert reply["server_timing"]["batch"] == 4
            np.testing.assert_allclose(reply["actions"], alone[i]["actions"], atol=1e-5)
            assert reply["stride"] == alone[i]["stride"]
        for i in range(5):  # five at once, max_batch 4: two calls
            clients[i].send(clients[i].message({k: v[i] for k, v in obs.items()}, keys[i]))
        five = [c.receive() for c in clients]
        assert sorted(r["server_timing"]["batch"] for r in five) == [1, 4, 4, 4, 4]
        for i, reply in enumerate(five):
            np.testing.assert_allclose(reply["actions"], alone[i]["actions"], atol=1e-5)
        lone = clients[0].infer({k: v[0] for k, v in obs.items()}, keys[0])  # 4 idle connections: the full window
        assert lone["server_timing"]["batch"] == 1 and lone["server_timing"]["queue_ms"] >= 400
    finally:
        for c in clients:
            c.close()
    time.sleep(0.2)
    with PolicyClient(_url(server)) as client:  # alone again: no wait
        assert client.infer({k: v[0] for k, v in obs.items()}, keys[0])["server_timing"]["queue_ms"] < 400


def test_load_four_clients_no_lost_or_mixed_replies(exported, server):
    """4 concurrent clients × 150 requests on loopback, bounded in time: every reply is the decision of its own
    observation and seed, and the server batched them."""
    backend, _ = exported
    meta = backend.metadata
    histories = _obs(meta, 8, seed=3)
    expected = backend.decide(histories, np.stack([[0, s] for s in range(8)]).astype(np.uint32))["actions"]
    latencies, failures = [], []
    batches, rows = server.batches, server.rows

    def client_loop(c):
        try:
            with PolicyClient(_url(server)) as client:
                for i in range(150):
                    j = (c * 150 + i) % 8
                    t0 = time.perf_counter()
                    reply = client.infer({k: v[j] for k, v in histories.items()}, seed=j)
                    latencies.append(time.perf_counter() - t0)
                    if reply["decision"] != i or not np.allclose(reply["actions"], expected[j], atol=1e-5):
                        failures.append((c, i, reply["decision"]))
        except Exception as e:  # noqa: BLE001 - reported below
            failures.append((c, repr(e)))

    threads = [threading.Thread(target=client_loop, args=(c,)) for c in range(4)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    wall = time.perf_counter() - t0
    assert not any(t.is_alive() for t in threads), "load test did not finish within 300 s"
    assert not failures, failures[:5]
    assert len(latencies) == 600 and server.rows - rows == 600
    mean_batch = 600 / (server.batches - batches)
    assert mean_batch > 1.5, mean_batch
    p50, p99 = np.percentile(latencies, [50, 99]) * 1e3
    print(f"\n4 clients x 150 requests: {600 / wall:.0f} requests/s, mean batch {mean_batch:.2f}, round trip p50 "
          f"{p50:.1f} ms, p99 {p99:.1f} ms")


# ------------------------------------------------------------------------------------------------ openpi client
def _episode(env, step, key, decide, max_steps):
    """One closed-loop episode driven from the host: ``decide(history, r) -> actions (n, A)`` at each decision r,
    executed one per control step → (success, steps, executed actions (steps, A))."""
    state = env.reset(key)
    span = decide.span
    history = {k: np.repeat(np.asarray(state.obs[k])[None], span, axis=0) for k in decide.keys}
    executed, r = [], 0

    def over(s):
        return bool(s.done) or int(s.step) >= max_steps

    while not over(state):
        for a in decide(history, r):
            if over(state):
                break
            state = step(state, jnp.asarray(a))
            executed.append(np.asarray(a))
            history = {k: np.concatenate([h[1:], np.asarray(state.obs[k])[None]]) for k, h in history.items()}
        r += 1
    return bool(state.success), int(state.step), np.stack(executed)


class _Decide:
    def __init__(self, fn, meta):
        self.fn, self.keys, self.span = fn, tuple(meta["obs"]), int(meta["obs_span"])

    def __call__(self, history, r):
        return self.fn(history, r)


def _openpi():
    """openpi's client modules (``openpi-client`` 0.1.2), or skip: it pins numpy<2, so it is installed apart."""
    reason = "pip install --no-deps openpi-client==0.1.2 (it pins numpy<2; README, Deployment)"
    return (pytest.importorskip("openpi_client.websocket_client_policy", reason=reason),
            pytest.importorskip("openpi_client.action_chunk_broker", reason=reason))


# openpi's client connects without a context manager, which websockets >= 16 warns about
OPENPI_WARNING = "ignore:connect\\(\\) must be used as a context manager:DeprecationWarning"


@pytest.fixture(scope="module")
def keyed_server(exported):
    """The in-process policy (the test's own backend object) behind a server that wants an API key, with key
    seed 5 and no batching."""
    backend, _ = exported
    srv = PolicyServer(backend, ServerConfig(port=0, max_batch=1, seed=5, api_key="s3cret-key"),
                       log=lambda msg: None)
    srv.start_in_thread()
    yield srv
    srv.stop()


@pytest.mark.filterwarnings(OPENPI_WARNING)
def test_openpi_client_closed_loop_matches_in_process(exported, keyed_server):
    """openpi's own client (``WebsocketClientPolicy``, observations only) and ``ActionChunkBroker`` drive MJX episodes
    through the server; the in-process policy on the same keys (decision r: fold_in(key(5), r)) gives the same
    success, steps and executed actions."""
    websocket_client_policy, action_chunk_broker = _openpi()

    backend, _ = exported
    meta = backend.metadata
    env = envs.make_for_encoder("press_button", policy_config(meta).encoder)
    step = jax.jit(env.step)
    lc = meta["chunk_len"]

    def in_process(history, r):
        out = backend.decide({k: v[None] for k, v in history.items()}, protocol.decision_key(5, r)[None])
        return out["actions"][0]  # the 'chunk' execution: the selected stride's L_c actions

    outcomes = {}
    for episode in range(2):
        key = jax.random.key(100 + episode)
        ref = _episode(env, step, key, _Decide(in_process, meta), 24)
        policy = websocket_client_policy.WebsocketClientPolicy("127.0.0.1", keyed_server.port, api_key="s3cret-key")
        assert policy.get_server_metadata()["obs"] == meta["obs"]
        remote = _episode(env, step, key, _Decide(lambda h, r: policy.infer(dict(h))["actions"], meta), 24)
        broker = action_chunk_broker.ActionChunkBroker(websocket_client_policy.WebsocketClientPolicy(
            f"ws://127.0.0.1:{keyed_server.port}", api_key="s3cret-key"), action_horizon=lc)
        brokered = _episode(env, step, key, _Decide(lambda h, r: broker.infer(dict(h))["actions"][None], meta), 24)
        for got in (remote, brokered):
            assert got[:2] == ref[:2]
            np.testing.assert_array_equal(got[2], ref[2])
        outcomes[episode] = ref
        policy._ws.close()
        broker._policy._ws.close()
    assert outcomes[0][2].shape == (24, 4)
    assert not np.allclose(outcomes[0][2], outcomes[1][2])  # other initial states, other observations, other actions
    # the decision depends on the observation, not only on the key
    obs = _obs(meta, 2, seed=11)
    same_key = np.repeat(protocol.decision_key(5, 0)[None], 2, axis=0)
    out = backend.decide(obs, same_key)
    assert not np.allclose(out["actions"][0], out["actions"][1])


@pytest.mark.filterwarnings(OPENPI_WARNING)
def test_openpi_client_reset_entry_and_error_frame(exported, keyed_server):
    """An observation dict may carry the reserved entries (here ``reset``); an error reaches openpi's client as
    the RuntimeError it raises on a text frame, and the connection keeps serving."""
    websocket_client_policy, _ = _openpi()
    meta = exported[0].metadata
    policy = websocket_client_policy.WebsocketClientPolicy("127.0.0.1", keyed_server.port, api_key="s3cret-key")
    obs = {k: v[0] for k, v in _obs(meta, 1, seed=2).items()}
    first, second = policy.infer(obs), policy.infer(obs)
    again = policy.infer({**obs, "reset": True})
    assert (first["decision"], second["decision"], again["decision"]) == (0, 1, 0)
    np.testing.assert_array_equal(again["actions"], first["actions"])
    assert set(first["server_timing"]) == {"infer_ms", "queue_ms", "batch"}
    with pytest.raises(RuntimeError, match=r"Error in inference server:\nstate: holds NaN or Inf"):
        policy.infer({"state": np.full((7, 7), np.nan, np.float32)})
    assert policy.infer(obs)["decision"] == 1
    policy._ws.close()


def test_api_key_refused_at_the_handshake_before_any_inference(exported, keyed_server, monkeypatch):
    """No key, a wrong key (ours or openpi's client), a malformed header: HTTP 401 at the handshake, nothing
    decided; /healthz needs no key; the right key (argument or $HIPOLICY_API_KEY) is served."""
    monkeypatch.delenv(API_KEY_ENV, raising=False)
    requests, refused = keyed_server.requests, keyed_server.refused
    attempts = [lambda: PolicyClient(_url(keyed_server), api_key=""),
                lambda: PolicyClient(_url(keyed_server), api_key="wrong-key"),
                lambda: connect(_url(keyed_server), additional_headers={"Authorization": "Bearer s3cret-key"})]
    try:
        from openpi_client.websocket_client_policy import WebsocketClientPolicy
        attempts.append(lambda: WebsocketClientPolicy("127.0.0.1", keyed_server.port, api_key="s3cret-kez"))
    except ImportError:  # not installed (README, Deployment)
        pass
    for attempt in attempts:
        with pytest.raises(InvalidStatus) as refusal:
            attempt()
        assert refusal.value.response.status_code == 401
        assert b"missing or wrong API key" in refusal.value.response.body
    assert keyed_server.requests == requests and keyed_server.refused == refused + len(attempts)
    with urllib.request.urlopen(f"http://127.0.0.1:{keyed_server.port}/healthz", timeout=30) as r:
        assert r.status == 200  # health needs no key
    monkeypatch.setenv(API_KEY_ENV, "s3cret-key")  # the client reads the key from the environment too
    with PolicyClient(_url(keyed_server)) as client:
        assert client.infer(GOOD, seed=0)["actions"].shape == (8, 4)
    assert keyed_server.requests == requests + 1


# ------------------------------------------------------------------------------------------- remote evaluation
def test_remote_evaluation_matches_in_process(run_dir, exported, server):
    """An MJX evaluation through the server (one connection per episode, batched decisions, the keys of the
    in-process rollout) reproduces the in-process one: successes, steps, strides, entropies and the joint
    positions of every control step. Two parameter sets: each matches its in-process evaluation, and they differ
    from each other, so the comparison can fail."""
    backend, _ = exported
    run = load_run(run_dir)
    inference = run_inference(run)
    thresholds, _ = calibration.resolve_thresholds(inference, 3, calibration.read_calibration(run_dir))
    evaluator = make_evaluator(run, inference, max_steps=24)
    noise = jax.random.split(jax.random.key(1), len(jax.tree.leaves(run.policy.params)))
    other = jax.tree.unflatten(jax.tree.structure(run.policy.params), [
        x + 0.3 * jnp.std(x) * jax.random.normal(k, x.shape, x.dtype) if x.ndim > 1 else x
        for x, k in zip(jax.tree.leaves(run.policy.params), noise)])
    other_backend = copy.copy(backend)  # the same compiled decision, other parameters
    other_backend._args = backend._args._replace(params=other)
    other_server = PolicyServer(other_backend, ServerConfig(port=0, max_batch=4, batch_window_ms=500),  # as `server`
                                log=lambda msg: None)
    other_server.start_in_thread()
    try:
        with PolicyClient(_url(server)) as client:
            remote_evaluator = RemoteEvaluator(client.metadata(), max_steps=24)  # one compile for both servers
        results = {}
        for name, params, srv in [("trained", run.policy.params, server), ("perturbed", other, other_server)]:
            local, local_rec = evaluator.rollout(params, run.policy.normalizer, 3, eval_key(0), thresholds)
            batches = srv.batches
            remote, remote_rec = remote_evaluator.rollout(_url(srv), 3, eval_key(0))
            assert srv.batches - batches == int(np.asarray(remote.valid).any(axis=0).sum())  # a batch per round
            for field in ("success", "steps", "stride", "valid", "start", "executed"):
                np.testing.assert_array_equal(np.asarray(getattr(remote, field)), np.asarray(getattr(local, field)),
                                              f"{name}: {field}")
            np.testing.assert_allclose(np.asarray(remote.entropy), np.asarray(local.entropy), atol=1e-4)
            np.testing.assert_allclose(np.asarray(remote_rec.qpos), np.asarray(local_rec.qpos), atol=1e-4)
            results[name] = (remote, remote_rec)
        assert remote_evaluator._rollout.traces == 1
        te = RemoteEvaluator({**remote_evaluator.metadata, "inference": {**inference.__dict__, "execution": "te"}})
        with pytest.raises(ValueError, match=r"the served policy differs from this evaluator's in \['inference'\]"):
            te.rollout(_url(server), 1, eval_key(0))
    finally:
        other_server.stop()
    (a, a_rec), (b, b_rec) = results["trained"], results["perturbed"]
    assert np.abs(np.asarray(a_rec.qpos) - np.asarray(b_rec.qpos)).max() > 1e-2
    assert not np.allclose(np.asarray(a.entropy), np.asarray(b.entropy), equal_nan=True)


def test_two_workers_decide_two_batches(exported):
    """With 2 workers, 4 connections sending at once are split into two batches of 2 (each connection's share),
    decided on two threads; every answer is still its own."""
    backend, _ = exported
    srv = PolicyServer(backend, ServerConfig(port=0, max_batch=2, workers=2, batch_window_ms=500),
                       log=lambda msg: None)
    srv.start_in_thread()
    obs, keys = _obs(backend.metadata, 4, seed=6), _keys(4, seed=6)
    alone = backend.decide(obs, keys)
    clients = [PolicyClient(_url(srv)) for _ in range(4)]
    try:
        for i, c in enumerate(clients):
            c.send(c.message({k: v[i] for k, v in obs.items()}, keys[i]))
        replies = [c.receive() for c in clients]
        assert [r["server_timing"]["batch"] for r in replies] == [2, 2, 2, 2] and srv.batches == 2
        for i, reply in enumerate(replies):
            np.testing.assert_allclose(reply["actions"], alone["actions"][i], atol=1e-5)
        assert clients[0].metadata()["server"]["workers"] == 2
    finally:
        for c in clients:
            c.close()
        srv.stop()


# --------------------------------------------------------------------------------------- remote inpainting
INPAINT = dict(delay=2, handover="inpaint")


@pytest.fixture(scope="module")
def inpaint_exported(run_dir, tmp_path_factory):
    """The run's policy under delay d = 2 with the inpainting hand-over, in process and exported."""
    inference = dataclasses.replace(run_inference(load_run(run_dir)), **INPAINT)
    backend = run_backend(run_dir, inference)
    directory = str(tmp_path_factory.mktemp("export_inpaint") / "policy")
    export_backend(backend, directory)
    return backend, directory


def test_exported_prefix_inputs(exported, inpaint_exported):
    """The exported program's prefix inputs: a row whose prefix_valid is False is exactly the decision without a
    prefix (the plain export's), a valid row's chunks start on the committed actions in every sample and at every
    frequency, and in-process = exported with prefixes too."""
    backend, directory = inpaint_exported
    loaded, plain = ExportedBackend(directory), ExportedBackend(exported[1])
    meta = loaded.metadata
    assert meta["inputs"]["prefix"] == ["B", 2, 4] and meta["inference"]["handover"] == "inpaint"
    obs, keys = _obs(meta, 4, seed=12), _keys(4, seed=12)
    prefix = np.random.default_rng(12).uniform(-1, 1, (4, 2, 4)).astype(np.float32)
    valid = np.array([True, False, True, False])
    out, ref = loaded.decide(obs, keys, prefix, valid), plain.decide(obs, keys)
    for k in ref:  # not valid: the no-prefix decision, bit for bit
        np.testing.assert_array_equal(out[k][~valid], ref[k][~valid], err_msg=k)
        np.testing.assert_array_equal(loaded.decide(obs, keys)[k], ref[k], err_msg=k)  # no prefix given: none valid
    segments = out["chunks"].reshape(4, 4, 3, 8, 4)  # (B, N, M, L_c, A)
    np.testing.assert_allclose(segments[valid][:, :, :, :2], np.broadcast_to(prefix[valid][:, None, None],
                                                                          (2, 4, 3, 2, 4)), atol=1e-5)
    np.testing.assert_allclose(out["actions"][valid][:, :2], prefix[valid], atol=1e-5)
    assert np.abs(out["actions"][valid][:, 2:] - ref["actions"][valid][:, 2:]).max() > 1e-3  # the rest re-sampled
    in_process = backend.decide(obs, keys, prefix, valid)
    for k in ref:
        np.testing.assert_allclose(out[k], in_process[k], atol=1e-5, err_msg=k)
    with pytest.raises(ValueError, match=r"prefix, prefix_valid: expected shapes \(4, 2, 4\) and \(4,\)"):
        loaded.decide(obs, keys, prefix[:, :1], valid)


def test_old_artifact_version_is_refused(exported, tmp_path):
    """A manifest of version 1 (its program takes no prefix) is refused, naming the file and asking to re-export."""
    old = tmp_path / "old"
    shutil.copytree(exported[1], old)
    manifest = json.loads((old / "manifest.json").read_text())
    (old / "manifest.json").write_text(json.dumps({**manifest, "version": 1}))
    with pytest.raises(ValueError, match=re.escape(f"export: {old / 'manifest.json'} is manifest version 1, this "
                                                   f"code reads version 2") + r".*re-export the policy"):
        ExportedBackend(str(old))


class _Recording(_Flaky):
    """A backend that records the prefix_valid of every call."""

    def __init__(self, inner):
        super().__init__(inner)
        self.valid = []

    def decide(self, obs, key_data, *prefix):
        if prefix:  # the server's calls (warm-up passes none)
            self.valid.append(np.asarray(prefix[1]).copy())
        return super().decide(obs, key_data, *prefix)


def test_remote_inpainting_matches_in_process(run_dir, inpaint_exported):
    """Delay d = 2 with the inpainting hand-over through the server (exported program, one connection per episode,
    batched decisions): each connection's committed actions go into the batched decision as its prefix, and the
    MJX evaluation reproduces the in-process one on the same keys: successes, steps, strides, entropies and the
    joint positions of every control step."""
    _, directory = inpaint_exported
    run = load_run(run_dir)
    inference = dataclasses.replace(run_inference(run), **INPAINT)
    thresholds, _ = calibration.resolve_thresholds(inference, 3, calibration.read_calibration(run_dir))
    backend = _Recording(ExportedBackend(directory))
    srv = PolicyServer(backend, ServerConfig(port=0, max_batch=4, batch_window_ms=500), log=lambda msg: None)
    srv.start_in_thread()
    try:
        with PolicyClient(_url(srv)) as client:
            meta = client.metadata()
            remote_evaluator = RemoteEvaluator(meta, max_steps=24)
        assert meta["server"]["delay"] == 2 and meta["inference"]["handover"] == "inpaint"
        backend.valid.clear()  # the warm-up's calls
        remote, remote_rec = remote_evaluator.rollout(_url(srv), 3, eval_key(0))
    finally:
        srv.stop()
    local, local_rec = make_evaluator(run, inference, max_steps=24).rollout(
        run.policy.params, run.policy.normalizer, 3, eval_key(0), thresholds)
    for field in ("success", "steps", "stride", "valid", "start", "executed"):
        np.testing.assert_array_equal(np.asarray(getattr(remote, field)), np.asarray(getattr(local, field)), field)
    np.testing.assert_allclose(np.asarray(remote.entropy), np.asarray(local.entropy), atol=1e-4)
    np.testing.assert_allclose(np.asarray(remote_rec.qpos), np.asarray(local_rec.qpos), atol=1e-4)
    # each episode's first decision has nothing committed, every later one inpaints its connection's d actions
    assert [v[:3].tolist() for v in backend.valid] == [[False] * 3] + [[True] * 3] * (len(backend.valid) - 1)
    assert len(backend.valid) >= 3 and np.asarray(local.executed).max() == 6  # L_c − d actions per decision


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_export_and_serve_entry_points(run_dir, tmp_path):
    out = str(tmp_path / "exp")
    paths = export_cli.main(export_cli.ExportArgs(checkpoint=run_dir, out=out))
    assert sorted(os.path.basename(p) for p in paths.values()) == ["manifest.json", "params.npz", "policy.jaxexport"]
    with pytest.raises(ValueError, match="pass exactly one of --checkpoint RUN_DIR and --export DIR"):
        serve_cli.main(serve_cli.ServeArgs())
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "experiments.serve", "--export", out, "--port", str(port),
                             "--max-batch", "1"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env={**os.environ, API_KEY_ENV: "from-the-env"})
    try:
        line = proc.stdout.readline()
        assert f"on ws://127.0.0.1:{port}" in line and "API key required" in line, line
        with pytest.raises(InvalidStatus):
            PolicyClient(f"ws://127.0.0.1:{port}", api_key="")
        with PolicyClient(f"ws://127.0.0.1:{port}", api_key="from-the-env") as client:
            assert client.infer(GOOD, seed=0)["actions"].shape == (8, 4)
            assert client.infer(GOOD, seed=0)["decision"] == 1
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0 and "stopped after 2 requests (0 errors, 1 refused)" in rest, rest
    finally:
        proc.kill()
    bad = subprocess.run([sys.executable, "-m", "experiments.serve", "--export", str(tmp_path / "nope")], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and bad.stderr.strip().splitlines()[-1].startswith("error: export: ")
    assert "Traceback" not in bad.stderr
