"""Deployment: the exported policy against the in-process one (in this process and in a process without the model
code), the websocket server and client (round trip, every bad request, remote evaluation = in-process
evaluation), a bounded load test, and the two entry points."""

import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import jax
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from experiments import export as export_cli
from experiments import serve as serve_cli
from hipolicy_jax import envs
from hipolicy_jax.config import EvalConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.backend import ExportedBackend, InProcessBackend
from hipolicy_jax.deploy.client import PolicyClient, PolicyServerError, evaluate_remote
from hipolicy_jax.deploy.export import export_backend
from hipolicy_jax.deploy.server import PolicyServer
from hipolicy_jax.evaluation import calibration
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
    backend = InProcessBackend.from_run(run_dir)
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
        out = program.call(leaves, {{"state": x["state"]}}, x["keys"])
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
    _, directory = exported
    srv = PolicyServer(ExportedBackend(directory), port=0, max_message_bytes=64 * 1024, max_batch=64,
                       log=lambda msg: None)
    srv.start_in_thread()
    yield srv
    srv.stop()


def test_server_round_trip_metadata_and_health(exported, server):
    backend, _ = exported
    with PolicyClient(f"ws://127.0.0.1:{server.port}") as client:
        assert client.metadata()["obs"] == backend.metadata["obs"]
        assert client.health()["status"] == "ok"
        obs, keys = _obs(backend.metadata, 3), _keys(3)
        reply = client.infer(obs, keys, chunks=True)
        ref = backend.decide(obs, keys)
        for k in ref:
            np.testing.assert_allclose(reply[k], ref[k], atol=1e-5, err_msg=k)
        assert reply["server_ms"] > 0
        single = client.infer({k: v[0] for k, v in obs.items()}, keys[0])  # unbatched in, unbatched out
        assert single["actions"].shape == (8, 4) and isinstance(single["stride"], int) and "chunks" not in single
        np.testing.assert_allclose(single["actions"], ref["actions"][0], atol=1e-5)
        by_seed = client.infer({k: v[0] for k, v in obs.items()}, seed=7)
        same = client.infer({k: v[0] for k, v in obs.items()},
                            np.asarray(jax.random.key_data(jax.random.key(7))))
        np.testing.assert_array_equal(by_seed["actions"], same["actions"])


BAD_REQUESTS = [
    ("unknown key", {"type": "infer", "obs": {"state": np.zeros((7, 7), np.float32), "image": np.zeros((2,), np.uint8)},
                     "seed": 0}, r"obs: keys \['image', 'state'\] do not match the policy's \['state'\] \(unknown: \['image'\]"),
    ("missing key", {"type": "infer", "obs": {}, "seed": 0}, r"missing: \['state'\]"),
    ("wrong shape", {"type": "infer", "obs": {"state": np.zeros((7, 6), np.float32)}},
     r"obs\['state'\]: expected shape \(7, 7\) or \(B, \*\(7, 7\)\), got \(7, 6\)"),
    ("wrong dtype", {"type": "infer", "obs": {"state": np.zeros((7, 7), np.int32)}},
     r"obs\['state'\]: expected floating values \(float32\), got dtype int32"),
    ("NaN", {"type": "infer", "obs": {"state": np.full((7, 7), np.nan, np.float32)}}, r"obs\['state'\]: holds NaN or Inf"),
    ("Inf", {"type": "infer", "obs": {"state": np.full((2, 7, 7), np.inf, np.float32)}}, r"holds NaN or Inf"),
    ("not an array", {"type": "infer", "obs": {"state": [1, 2]}}, r"obs\['state'\]: expected an array of shape"),
    ("bad key", {"type": "infer", "obs": {"state": np.zeros((7, 7), np.float32)}, "key": np.zeros((2,), np.int64)},
     r"key: expected uint32 raw PRNG key data of shape \(2,\)"),
    ("bad seed", {"type": "infer", "obs": {"state": np.zeros((7, 7), np.float32)}, "seed": -1}, r"seed: expected an int"),
    ("too big a batch", {"type": "infer", "obs": {"state": np.zeros((65, 7, 7), np.float32)}},
     r"obs: batch of 65 observation histories, the server takes 1 to 64"),
    ("unknown type", {"type": "teleport"}, r"type: expected 'infer', 'metadata' or 'health', got 'teleport'"),
    ("obs not a map", {"type": "infer", "obs": 3}, r"obs: expected a map of observation key to array, got int"),
]


@pytest.mark.parametrize("name,message,pattern", BAD_REQUESTS, ids=[b[0] for b in BAD_REQUESTS])
def test_bad_requests_get_an_error_reply_and_the_server_keeps_serving(server, name, message, pattern):
    with connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:
        ws.send(protocol.pack({**message, "id": 41}))
        reply = protocol.unpack(ws.recv(timeout=60))
        assert reply["type"] == "error" and reply["id"] == 41 and re.search(pattern, reply["error"]), reply
        ws.send(protocol.pack({"type": "infer", "obs": {"state": np.zeros((7, 7), np.float32)}, "seed": 1}))
        assert protocol.unpack(ws.recv(timeout=60))["type"] == "result"


def test_malformed_frames_get_an_error_reply(server):
    with connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:
        for frame, pattern in [(b"\xc1\xff garbage", r"request is not a msgpack message"),
                               ("a text frame", r"expected a binary msgpack frame, got a text frame"),
                               (protocol.pack([1, 2]), r"expected a msgpack map with a 'type', got list"),
                               (b"\x81\xa1x\xc7\x03\x05abc", r"unknown msgpack extension type 5"),
                               (b"\x00" * (100 * 1024), r"message of 102400 bytes exceeds the server's limit of "
                                                        r"65536 bytes")]:
            ws.send(frame)
            reply = protocol.unpack(ws.recv(timeout=60))
            assert reply["type"] == "error" and re.search(pattern, reply["error"]), (frame[:20], reply)
    with connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:  # above twice the limit: refused unread
        ws.send(b"\x00" * (200 * 1024))
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=60)
        assert closed.value.rcvd.code == 1009
    with PolicyClient(f"ws://127.0.0.1:{server.port}") as client:  # still serving
        assert client.health()["errors"] >= 5
        with pytest.raises(PolicyServerError, match="missing"):
            client.request({"type": "infer", "obs": {}})


def test_remote_evaluation_matches_in_process(run_dir, server):
    """An MJX evaluation through the server (decisions over the socket, execution here) reproduces the in-process
    evaluation on the same keys: the same successes, steps and strides."""
    run = load_run(run_dir)
    inference = run_inference(run)
    thresholds, _ = calibration.resolve_thresholds(inference, 3, calibration.read_calibration(run_dir))
    local = make_evaluator(run, inference, max_steps=24).evaluate(run.policy.params, run.policy.normalizer, 3,
                                                                    eval_key(0), thresholds)
    with PolicyClient(f"ws://127.0.0.1:{server.port}") as client:
        remote = evaluate_remote(client, 3, eval_key(0), max_steps=24)
        with pytest.raises(ValueError, match="prefix inpainting runs inside the sampler, in-process only"):
            evaluate_remote(client, 1, eval_key(0), execution=InferenceConfig(num_samples=4, delay=1,
                                                                              handover="inpaint"))
    for field in ("success", "steps", "stride", "valid", "start", "executed"):
        np.testing.assert_array_equal(np.asarray(getattr(remote, field)), np.asarray(getattr(local, field)), field)
    np.testing.assert_allclose(np.asarray(remote.entropy), np.asarray(local.entropy), atol=1e-4)


def test_load_four_clients_no_lost_or_mixed_replies(exported, server):
    """4 concurrent clients × 250 requests on loopback, bounded in time: every reply carries its request's id and
    the decision of its own observation and seed."""
    backend, _ = exported
    meta = backend.metadata
    histories = _obs(meta, 8, seed=3)
    expected = backend.decide(histories, np.stack([[0, s] for s in range(8)]).astype(np.uint32))["actions"]
    latencies, failures = [], []

    def client_loop(c):
        try:
            with PolicyClient(f"ws://127.0.0.1:{server.port}") as client:
                for i in range(250):
                    j = (c * 250 + i) % 8
                    t0 = time.perf_counter()
                    reply = client.request({"type": "infer", "obs": {k: v[j] for k, v in histories.items()},
                                            "seed": j, "id": c * 1000 + i})
                    latencies.append(time.perf_counter() - t0)
                    if reply["id"] != c * 1000 + i or not np.allclose(reply["actions"], expected[j], atol=1e-5):
                        failures.append((c, i, reply.get("id")))
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
    assert len(latencies) == 1000
    p50, p99 = np.percentile(latencies, [50, 99]) * 1e3
    print(f"\n4 clients x 250 requests: {1000 / wall:.0f} requests/s, round trip p50 {p50:.1f} ms, p99 {p99:.1f} ms")


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
    proc = subprocess.Popen([sys.executable, "-m", "experiments.serve", "--export", out, "--port", str(port)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = proc.stdout.readline()
        assert f"on ws://127.0.0.1:{port}" in line, line
        with PolicyClient(f"ws://127.0.0.1:{port}") as client:
            assert client.infer({"state": np.zeros((7, 7), np.float32)}, seed=0)["actions"].shape == (8, 4)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0 and "stopped after 2 requests (0 errors)" in rest, rest
    finally:
        proc.kill()
    bad = subprocess.run([sys.executable, "-m", "experiments.serve", "--export", str(tmp_path / "nope")], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and bad.stderr.strip().splitlines()[-1].startswith("error: export: ")
    assert "Traceback" not in bad.stderr
