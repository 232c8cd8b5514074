"""Policy serving latency and throughput: the in-process decision, the exported program, and the websocket round
trip on loopback, side by side; then a load test of concurrent clients.

    python -m benchmarks.serving                     # the cpu-budget HiPolicy press_button run
    python -m benchmarks.serving --run RUN_DIR --calls 30 --clients 4 --requests 250

One observation history (B = 1) per call. The three single-call paths are timed interleaved (in-process jit,
exported program in-process, client → ``experiments.serve --export`` in a subprocess → client), each call ending
when its result is on the host; the load test then runs ``--clients`` threads of ``--requests`` requests each
against the same server and reports requests/s and the round-trip p50 / p99. Writes
``benchmarks/results/serving_<device>.json``.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import threading
import time

import jax
import numpy as np

from benchmarks.common import base_parser, latency_stats, markdown_table, report_rows
from hipolicy_jax.deploy.backend import ExportedBackend, InProcessBackend
from hipolicy_jax.deploy.client import PolicyClient
from hipolicy_jax.deploy.export import export_backend

NAME = "serving"


def parse_args(argv=None):
    p = base_parser(NAME, __doc__)
    p.add_argument("--run", default="runs/paper/cpu/press_button/state/hipolicy/seed0")
    p.add_argument("--calls", type=int, default=30, help="timed calls per path (interleaved)")
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--requests", type=int, default=250, help="requests per client in the load test")
    return p.parse_args(argv)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(export_dir: str, port: int) -> subprocess.Popen:
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.Popen([sys.executable, "-m", "experiments.serve", "--export", export_dir, "--port", str(port)],
                            cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    line = proc.stdout.readline()
    if "serving" not in line:
        proc.kill()
        raise RuntimeError(f"the server did not start: {line}{proc.stdout.read()}")
    print(line.strip())
    return proc


def load_test(url: str, obs: dict, clients: int, requests: int) -> dict:
    latencies, failures = [], []

    def loop(c):
        try:
            with PolicyClient(url) as client:
                for i in range(requests):
                    t0 = time.perf_counter()
                    reply = client.request({"type": "infer", "obs": obs, "seed": i, "id": c * requests + i})
                    latencies.append(time.perf_counter() - t0)
                    if reply.get("id") != c * requests + i:
                        failures.append((c, i))
        except Exception as e:  # noqa: BLE001 - counted as a failure
            failures.append((c, repr(e)))

    threads = [threading.Thread(target=loop, args=(c,)) for c in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    lat = np.asarray(latencies) * 1e3
    return {"clients": clients, "requests_per_client": requests, "replies": len(latencies), "failures": len(failures),
            "wall_s": wall, "requests_per_s": len(latencies) / wall, "p50_ms": float(np.percentile(lat, 50)),
            "p99_ms": float(np.percentile(lat, 99))}


def main(argv=None) -> dict:
    args = parse_args(argv)
    backend = InProcessBackend.from_run(args.run)
    meta = backend.metadata
    rng = np.random.default_rng(0)
    obs = {k: rng.normal(size=s["shape"]).astype(s["dtype"]) for k, s in meta["obs"].items()}
    with tempfile.TemporaryDirectory() as tmp:
        export_backend(backend, os.path.join(tmp, "policy"))
        exported = ExportedBackend(os.path.join(tmp, "policy"))
        port = _free_port()
        server = start_server(os.path.join(tmp, "policy"), port)
        try:
            url = f"ws://127.0.0.1:{port}"
            client = PolicyClient(url)
            batch = {k: v[None] for k, v in obs.items()}
            key = lambda i: np.asarray(jax.random.key_data(jax.random.key(i)))[None]  # noqa: E731
            paths = {"in-process (jit)": lambda i: backend.decide(batch, key(i)),
                     "exported program": lambda i: exported.decide(batch, key(i)),
                     "websocket round trip": lambda i: client.infer(obs, key(i)[0])}
            times = {name: [] for name in paths}
            server_ms = []
            for name, fn in paths.items():  # warm-up (compiles) and first-call times
                fn(-1)
            for i in range(args.calls):
                for name, fn in paths.items():
                    t0 = time.perf_counter()
                    out = fn(i)
                    times[name].append(time.perf_counter() - t0)
                    if name == "websocket round trip":
                        server_ms.append(out["server_ms"])
            client.close()
            load = load_test(url, obs, args.clients, args.requests)
        finally:
            server.terminate()
            server.wait(timeout=60)
    base = np.median(times["in-process (jit)"])
    rows = [{"path": name, **{k: v * 1e3 if k.endswith("_s") else v for k, v in latency_stats(t).items()},
             "ratio_to_in_process": float(np.median(t) / base)} for name, t in times.items()]
    for r in rows:
        r["median_ms"], r["p90_ms"], r["min_ms"] = r.pop("median_s"), r.pop("p90_s"), r.pop("min_s")
    rows[-1]["server_side_median_ms"] = float(np.median(server_ms))
    table = markdown_table(["path", "median ms", "p90 ms", "x in-process"],
                           [[r["path"], r["median_ms"], r["p90_ms"], r["ratio_to_in_process"]] for r in rows])
    table += (f"\n\nload test: {load['clients']} clients x {load['requests_per_client']} requests: "
              f"{load['requests_per_s']:.1f} requests/s, round trip p50 {load['p50_ms']:.1f} ms, p99 "
              f"{load['p99_ms']:.1f} ms, {load['failures']} failures")
    return report_rows(NAME, argv, args, rows, table, load=load, run=os.path.relpath(args.run),
                       policy={k: meta[k] for k in ("task", "strides", "num_samples", "inference", "obs")})


if __name__ == "__main__":
    main()
