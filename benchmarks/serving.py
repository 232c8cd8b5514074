"""Policy serving latency and throughput: the in-process decision, the exported program and the websocket round
trip on loopback side by side; the decision's cost per batch size; then load tests of one and of several
concurrent clients against the micro-batching server (and against the same server without batching).

    python -m benchmarks.serving                     # the cpu-budget HiPolicy press_button policy
    python -m benchmarks.serving --run RUN_DIR --clients 8 --requests 20 --rounds 4 --time-limit 120

The policy is the trained run ``--run`` when it exists, else the same network (the cpu budget's HiPolicy config:
CPU U-Net, strides 1/2/3, N = 16, DDIM 10) freshly initialised: the compute is the same. One observation history
per request. The single-call paths are timed interleaved (in-process jit, exported program in-process, client →
``experiments.serve --export`` in a subprocess → client), each call ending when its result is on the host. The
load tests are bounded: fixed request counts per client, a wall-clock limit (clients stop issuing requests once
it is spent; reported), loopback only (``127.0.0.1``). Clients send observations only (as openpi's client does),
each its own. The rounds alternate one client and each server, and the throughput ratio is the median over
rounds of N clients' requests/s over the same round's one client's. Targets: ``--clients`` clients reach ≥ 1.4x
the requests/s of one client, with a p99 round trip ≤ 3x one client's p50. On a shared machine pause other jobs
first. Writes
``benchmarks/results/serving_<device>.json`` (with the CPU model from ``lscpu``).
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

from benchmarks.common import base_parser, example_obs, latency_stats, markdown_table, report_rows
from hipolicy_jax import envs
from hipolicy_jax.data.normalizer import Normalizer
from hipolicy_jax.deploy.backend import ExportedBackend, InProcessBackend
from hipolicy_jax.runs.serve import run_backend
from hipolicy_jax.deploy.client import PolicyClient
from hipolicy_jax.deploy.export import export_backend
from hipolicy_jax.deploy.server import ServerConfig
from hipolicy_jax.models.policy_net import init_policy_params
from hipolicy_jax.campaigns.budgets import BUDGETS
from hipolicy_jax.runs.cli import prepare_process

NAME = "serving"
TARGET_THROUGHPUT = 1.4  # requests/s of N clients over one client's
TARGET_P99 = 3.0  # N clients' p99 round trip over one client's p50


def parse_args(argv=None):
    p = base_parser(NAME, __doc__)
    p.add_argument("--run", default="runs/paper/cpu/press_button/state/hipolicy/seed0")
    p.add_argument("--calls", type=int, default=20, help="timed calls per single-call path (interleaved)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 2, 4, 8], help="batch sizes of the scaling rows")
    p.add_argument("--clients", type=int, default=8, help="concurrent clients of the load test")
    p.add_argument("--requests", type=int, default=20, help="requests per client per load-test round")
    p.add_argument("--max-batch", type=int, default=ServerConfig.max_batch, help="the server's micro-batch limit")
    p.add_argument("--batch-window-ms", type=float, default=ServerConfig.batch_window_ms)
    p.add_argument("--workers", type=int, nargs="+", default=[ServerConfig.workers],
                   help="concurrent batches of the servers under test (e.g. 1 2); the targets are read on the first")
    p.add_argument("--rounds", type=int, default=4, help="load-test rounds (one client, then each server)")
    p.add_argument("--time-limit", type=float, default=120.0, help="seconds per load test at most")
    p.add_argument("--no-unbatched", action="store_true", help="skip the load test against --max-batch 1")
    return p.parse_args(argv)


def cpu_model() -> str:
    """``lscpu``'s model name (``/proc/cpuinfo`` when lscpu is missing)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        out = open("/proc/cpuinfo").read() if os.path.exists("/proc/cpuinfo") else ""
    for line in out.splitlines():
        if line.lower().startswith(("model name", "model name\t")):
            return line.split(":", 1)[1].strip()
    return "unknown"


def make_backend(run: str) -> tuple[InProcessBackend, str]:
    """The run's policy, else the cpu budget's HiPolicy press_button network freshly initialised."""
    if os.path.isdir(run):
        return run_backend(run), os.path.relpath(run)
    budget, env = BUDGETS["cpu"], envs.make("press_button")
    cfg, key = budget.policy, jax.random.key(0)
    params = init_policy_params(cfg, env.action_dim, example_obs(cfg, 1, key, env.state_dim), key)
    rng = np.random.default_rng(0)
    normalizer = Normalizer.fit({"state": rng.random((256, env.state_dim), np.float32),
                                 "action": rng.random((256, env.action_dim), np.float32)})
    backend = InProcessBackend(task="press_button", cfg=cfg, action_dim=env.action_dim, params=params,
                               normalizer=normalizer, inference=budget.inference,
                               thresholds=np.array([-np.inf, 0.0, 1.0, np.inf], np.float32),
                               thresholds_source="benchmark (untrained network)")
    return backend, f"{run} is missing: the cpu-budget HiPolicy network, freshly initialised (same compute)"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(export_dir: str, port: int, max_batch: int, window_ms: float, workers: int) -> subprocess.Popen:
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.Popen([sys.executable, "-m", "experiments.serve", "--export", export_dir, "--port", str(port),
                             "--max-batch", str(max_batch), "--batch-window-ms", str(window_ms),
                             "--workers", str(workers)],
                            cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "HIPOLICY_API_KEY": ""})
    line = proc.stdout.readline()
    if "serving" not in line:
        proc.kill()
        raise RuntimeError(f"the server did not start: {line}{proc.stdout.read()}")
    print(line.strip())
    return proc


def load_test(url: str, histories: list[dict], clients: int, requests: int, time_limit: float) -> dict:
    """``clients`` threads, one connection each, ``requests`` requests each (fewer once ``time_limit`` is spent)
    → raw latencies (s), batch sizes, failures, wall time."""
    latencies, batches, failures = [], [], []
    deadline = time.perf_counter() + time_limit

    def loop(c):
        try:
            with PolicyClient(url) as client:
                obs = histories[c % len(histories)]
                client.infer(obs)  # connect and warm this connection (not timed)
                for i in range(requests):
                    if time.perf_counter() > deadline:
                        break
                    t0 = time.perf_counter()
                    reply = client.infer(obs)
                    latencies.append(time.perf_counter() - t0)
                    batches.append(reply["server_timing"]["batch"])
                    if reply["decision"] != i + 1:
                        failures.append((c, i, reply["decision"]))
        except Exception as e:  # noqa: BLE001 - counted as a failure
            failures.append((c, repr(e)))

    threads = [threading.Thread(target=loop, args=(c,)) for c in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"latencies": latencies, "batches": batches, "failures": len(failures), "wall": time.perf_counter() - t0,
            "planned": clients * requests}


def summarize(raws: list[dict], clients: int, requests: int, **about) -> dict:
    """Pooled statistics of load-test rounds: requests/s = all replies / all wall time."""
    lat = np.concatenate([r["latencies"] for r in raws]) * 1e3
    replies, wall = len(lat), sum(r["wall"] for r in raws)
    return {**about, "clients": clients, "requests_per_client": requests, "rounds": len(raws), "replies": replies,
            "failures": sum(r["failures"] for r in raws),
            "stopped_by_time_limit": replies < sum(r["planned"] for r in raws), "wall_s": wall,
            "requests_per_s": replies / wall,
            "requests_per_s_by_round": [len(r["latencies"]) / r["wall"] for r in raws],
            "p50_ms": float(np.percentile(lat, 50)), "p90_ms": float(np.percentile(lat, 90)),
            "p99_ms": float(np.percentile(lat, 99)), "max_ms": float(lat.max()),
            "mean_batch": float(np.mean(np.concatenate([r["batches"] for r in raws])))}


def main(argv=None) -> dict:
    args = parse_args(argv)
    prepare_process()
    backend, source = make_backend(args.run)
    meta = backend.metadata
    rng = np.random.default_rng(0)
    histories = [{k: rng.normal(size=s["shape"]).astype(s["dtype"]) for k, s in meta["obs"].items()}
                 for _ in range(max(args.clients, 1))]
    obs = histories[0]
    key = lambda i: np.asarray(jax.random.key_data(jax.random.key(i)))[None]  # noqa: E731
    procs = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            directory = os.path.join(tmp, "policy")
            export_backend(backend, directory)
            exported = ExportedBackend(directory)
            port = _free_port()
            procs.append(start_server(directory, port, args.max_batch, args.batch_window_ms, args.workers[0]))
            url = f"ws://127.0.0.1:{port}"
            load_avg = [os.getloadavg()]  # the load tests first: the longest quiet stretch on a shared machine
            servers = [(f"{args.clients} clients, batches of <= {args.max_batch}, {args.workers[0]} worker(s)", url,
                        {"max_batch": args.max_batch, "workers": args.workers[0]}, args.requests)]
            for w in args.workers[1:]:
                port = _free_port()
                procs.append(start_server(directory, port, args.max_batch, args.batch_window_ms, w))
                servers.append((f"{args.clients} clients, batches of <= {args.max_batch}, {w} worker(s)",
                                f"ws://127.0.0.1:{port}", {"max_batch": args.max_batch, "workers": w}, args.requests))
            if not args.no_unbatched:
                port = _free_port()
                procs.append(start_server(directory, port, 1, 0.0, 1))
                servers.append((f"{args.clients} clients, no batching", f"ws://127.0.0.1:{port}",
                                {"max_batch": 1, "workers": 1}, max(args.requests // 2, 1)))
            raw_one, raw_many = [], {name: [] for name, *_ in servers}
            for _ in range(args.rounds):  # interleaved, so that drift of the machine hits every row alike
                raw_one.append(load_test(url, histories, 1, args.requests, args.time_limit))
                for name, server_url, _, requests in servers:
                    raw_many[name].append(load_test(server_url, histories, args.clients, requests, args.time_limit))
            one = summarize(raw_one, 1, args.requests, server={"max_batch": args.max_batch, "workers": args.workers[0]})
            loads = [("1 client", one)] + [(name, summarize(raw_many[name], args.clients, requests, server=config))
                                           for name, _, config, requests in servers]
            many = loads[1][1]
            client = PolicyClient(url)
            batch = {k: v[None] for k, v in obs.items()}
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
                        server_ms.append(out["server_timing"]["infer_ms"])
            client.close()
            scaling = []
            for b in args.batches:  # the exported program's cost per batch size (what the server runs)
                rows = {k: np.stack([histories[i % len(histories)][k] for i in range(b)]) for k in meta["obs"]}
                keys = np.stack([key(i)[0] for i in range(b)])
                exported.decide(rows, keys)
                t = []
                for _ in range(max(3, args.calls // 2)):
                    t0 = time.perf_counter()
                    exported.decide(rows, keys)
                    t.append(time.perf_counter() - t0)
                scaling.append({"batch": b, "median_ms": 1e3 * float(np.median(t))})
            for b in args.batches[:2]:  # two calls at once from two threads (ms per round of two): a 2nd worker?
                rows = {k: np.stack([histories[i % len(histories)][k] for i in range(b)]) for k in meta["obs"]}
                keys = np.stack([key(i)[0] for i in range(b)])
                calls = max(3, args.calls // 2)
                threads = [threading.Thread(target=lambda: [exported.decide(rows, keys) for _ in range(calls)])
                           for _ in range(2)]
                t0 = time.perf_counter()
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                scaling.append({"batch": b, "threads": 2, "median_ms": 1e3 * (time.perf_counter() - t0) / calls})
            for row in scaling:
                row.setdefault("threads", 1)
                row["ms_per_row"] = row["median_ms"] / (row["batch"] * row["threads"])
                row["throughput_x_batch1"] = scaling[0]["ms_per_row"] / row["ms_per_row"]
            load_avg.append(os.getloadavg())
    finally:
        for p in procs:
            p.terminate()
            p.wait(timeout=60)
    base = np.median(times["in-process (jit)"])
    rows = [{"path": name, **{k: v * 1e3 if k.endswith("_s") else v for k, v in latency_stats(t).items()},
             "ratio_to_in_process": float(np.median(t) / base)} for name, t in times.items()]
    for r in rows:
        r["median_ms"], r["p90_ms"], r["min_ms"] = r.pop("median_s"), r.pop("p90_s"), r.pop("min_s")
    rows[-1]["server_side_median_ms"] = float(np.median(server_ms))
    # each round's N-client requests/s over the same round's one-client requests/s (adjacent in time, so a busy
    # spell of a shared machine hits both), and their median
    by_round = [n / o for n, o in zip(many["requests_per_s_by_round"], one["requests_per_s_by_round"])]
    targets = {"throughput_ratio": float(np.median(by_round)), "throughput_ratio_by_round": by_round,
               "throughput_ratio_pooled": many["requests_per_s"] / one["requests_per_s"],
               "p99_over_one_client_p50": many["p99_ms"] / one["p50_ms"]}
    # the best the compute allows: the largest throughput gain of one batched call (batch <= max_batch), and by
    # Little's law the closed-loop clients' mean round trip >= clients / throughput
    best = max(s["throughput_x_batch1"] for s in scaling if s["threads"] == 1 and s["batch"] <= args.max_batch)
    targets.update(best_batch_throughput_x=best, mean_latency_bound_x_p50=args.clients / best)
    # a busy machine shows as a round trip of one client well above the in-process decision
    targets.update(one_client_p50_over_in_process=one["p50_ms"] / rows[0]["median_ms"], load_average=load_avg)
    targets.update(throughput_target=TARGET_THROUGHPUT, p99_target=TARGET_P99,
                   throughput_met=targets["throughput_ratio"] >= TARGET_THROUGHPUT,
                   p99_met=targets["p99_over_one_client_p50"] <= TARGET_P99)
    table = markdown_table(["path", "median ms", "p90 ms", "x in-process"],
                           [[r["path"], r["median_ms"], r["p90_ms"], r["ratio_to_in_process"]] for r in rows])
    table += "\n\n" + markdown_table(["batch", "threads", "ms per call", "ms per row", "throughput x batch 1"],
                                     [[s["batch"], s["threads"], s["median_ms"], s["ms_per_row"],
                                       s["throughput_x_batch1"]] for s in scaling])
    table += "\n\n" + markdown_table(
        ["load test", "replies", "requests/s", "p50 ms", "p99 ms", "mean batch", "failures"],
        [[name, r["replies"], r["requests_per_s"], r["p50_ms"], r["p99_ms"], r["mean_batch"], r["failures"]]
         for name, r in loads])
    table += (f"\n\n{args.clients} clients / 1 client: {targets['throughput_ratio']:.2f}x requests/s (median of the "
              f"rounds {', '.join(f'{r:.2f}' for r in by_round)}; target >= "
              f"{TARGET_THROUGHPUT}: {'met' if targets['throughput_met'] else 'NOT met'}); p99 / one client's p50: "
              f"{targets['p99_over_one_client_p50']:.2f} (target <= {TARGET_P99}: "
              f"{'met' if targets['p99_met'] else 'NOT met'}). The compute bounds both: one call of up to "
              f"{args.max_batch} rows decides at most {best:.2f}x the rows/s of batch 1, so {args.clients} closed-loop "
              f"clients wait >= {args.clients}/{best:.2f} = {targets['mean_latency_bound_x_p50']:.2f}x one decision "
              f"on average")
    return report_rows(NAME, argv, args, rows, table, cpu_model=cpu_model(), cpu_count=os.cpu_count(),
                       policy_source=source, batch_scaling=scaling, load_one_client=one, load=many,
                       loads={name: r for name, r in loads[1:]}, targets=targets,
                       policy={k: meta[k] for k in ("task", "strides", "num_samples", "inference", "obs")})


if __name__ == "__main__":
    main()
