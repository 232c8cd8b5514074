"""Shared pieces of the benchmark scripts: benchmark policies, timing, memory, FLOPs, machine peak, JSON output.

Every benchmark prints a table and writes ``benchmarks/results/<name>_<device>.json`` (``device`` = ``cpu`` /
``gpu`` / ``tpu``, from ``jax.default_backend()``); a finished study (``benchmarks.studies``) writes to
``benchmarks/studies/results/`` instead (``default_results_dir``). Latencies are wall-clock seconds of calls that
end in ``jax.block_until_ready``; on a shared machine compare ratios taken in one run, not absolute numbers across
runs.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import threading
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.machine import machine_info
from hipolicy_jax import jsonio
from hipolicy_jax.config import PolicyConfig, replace
from hipolicy_jax.data.normalizer import Normalizer
from hipolicy_jax.models.policy_net import PolicyNet, init_policy_params, param_count

RESULTS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
STUDIES_RESULTS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "studies", "results")


def default_results_dir(module: str) -> str:
    """Where the JSON of ``benchmarks.<module>`` goes without ``--out-dir``: ``STUDIES_RESULTS_DIR`` for a finished
    study (``studies.<name>``), else ``RESULTS_DIR``."""
    return STUDIES_RESULTS_DIR if module.startswith("studies.") else RESULTS_DIR

STATE_DIM = 10  # synthetic proprioceptive state size (D)
ACTION_DIM = 4  # synthetic action size (A): end-effector xyz + gripper, as the MJX tasks

# Per benchmark size: config overrides (dotted keys of PolicyConfig). 'paper' is the paper's U-Net and the
# Diffusion Policy / DP3 encoders at their default widths; 'cpu' the CPU-sized U-Net with a narrower ResNet;
# 'tiny' is for the smoke tests only.
SIZES: dict[str, dict[str, Any]] = {
    "paper": {"model.size": "paper"},
    "cpu": {"model.size": "cpu", "encoder.image_channels": (16, 32, 64, 128)},
    "tiny": {"model.size": "tiny", "model.fusion_heads": 2, "encoder.state_hidden": (16,), "encoder.state_out": 8,
             "encoder.image_size": 32, "encoder.crop_size": 28, "encoder.image_channels": (8, 16),
             "encoder.num_keypoints": 4, "encoder.image_out": 8, "encoder.num_points": 64, "encoder.point_out": 8},
}


# The shapes of the PyTorch Diffusion Policy comparison (PERFORMANCE.md), at paper size (down dims 256/512/1024,
# kernel 5, a 256-dim step embedding) with the raw observation window as the condition (identity state encoder):
# name -> (PolicyConfig changes, state dim, action dim). 'dp-lowdim' is Diffusion Policy's low-dim U-Net to the
# parameter (65,783,298); 'hipolicy' the HiPolicy shape (strides 1/2/3, L_c 8 → T = 24, A = 14) with CLS fusion,
# 'hipolicy-nofusion' the same U-Net body without it; 'hipolicy-lightfusion' with the lighter fusion (segment
# tokens projected to 256 features before the attention, ``model.fusion_token_dim``: a model change).
_PYTORCH_BODY = {"model.size": "paper", "model.step_embed_dim": 256, "encoder.state_encoder": "identity",
                 "chunk.obs_horizon": 2}
SHAPES: dict[str, tuple[dict[str, Any], int, int]] = {
    "dp-lowdim": ({**_PYTORCH_BODY, "chunk.strides": (1,), "chunk.chunk_len": 16}, 20, 2),
    "hipolicy": ({**_PYTORCH_BODY, "chunk.strides": (1, 2, 3), "chunk.chunk_len": 8}, 20, 14),
    "hipolicy-lightfusion": ({**_PYTORCH_BODY, "chunk.strides": (1, 2, 3), "chunk.chunk_len": 8,
                              "model.fusion_token_dim": 256}, 20, 14),
    "hipolicy-nofusion": ({**_PYTORCH_BODY, "chunk.strides": (1, 2, 3), "chunk.chunk_len": 8, "model.fusion": False},
                          20, 14),
}


class BenchModel(NamedTuple):
    """One benchmarked model: its row labels (size or shape name, obs type), config changes and dims."""

    size: str
    obs: str
    changes: dict
    state_dim: int
    action_dim: int

    @property
    def dtype(self) -> str:
        """The U-Net's ``model.compute_dtype`` of this row."""
        return self.changes.get("model.compute_dtype", "float32")

    def policy(self, seed: int = 0, **more) -> "BenchPolicy":
        base = "paper" if self.size in SHAPES else self.size
        return make_bench_policy(base, self.obs, seed, self.state_dim, self.action_dim, **{**self.changes, **more})


def bench_models(args) -> list[BenchModel]:
    """``--shapes`` when given (each a ``SHAPES`` entry, state observations), else the ``--sizes`` x ``--obs`` grid."""
    if getattr(args, "shapes", None):
        models = [BenchModel(s, "state", *SHAPES[s]) for s in args.shapes]
    else:
        models = [BenchModel(size, obs, {}, STATE_DIM, ACTION_DIM) for size in args.sizes for obs in args.obs]
    dtypes = getattr(args, "compute_dtypes", None) or ["float32"]
    return [m._replace(changes={**m.changes, "model.compute_dtype": dt}) for m in models for dt in dtypes]


def peer_shape_args(args, **quick):
    """The default model set of the paper-size benchmarks: the PyTorch comparison's DP low-dim and HiPolicy shapes
    on a CPU unless ``--shapes`` / ``--sizes`` say otherwise; with ``--quick`` the tiny size and ``quick``'s
    attribute values (the smoke tests). Returns ``args``."""
    if args.quick:
        args.shapes, args.sizes = None, ["tiny"]
        for name, value in quick.items():
            setattr(args, name, value)
    elif args.shapes is None and device_kind() == "cpu" and args.sizes == ["cpu"]:
        args.shapes = ["dp-lowdim", "hipolicy"]
    return args


def device_kind() -> str:
    """``cpu``, ``gpu`` or ``tpu``: the default backend, used in result file names."""
    return jax.default_backend()


def base_parser(name: str, doc: str | None, *, grid: bool = False) -> argparse.ArgumentParser:
    """The flags every benchmark shares: ``--out-dir``, ``--matmul-precision`` and, with ``grid``, the
    ``--sizes`` / ``--obs`` grid (a small CPU default, the full grid on an accelerator). ``name``: the module under
    ``benchmarks`` (``sampling``, ``studies.precision``)."""
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{name}", description=doc,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    if grid:
        cpu = device_kind() == "cpu"
        p.add_argument("--sizes", nargs="+", default=["cpu"] if cpu else ["cpu", "paper"],
                       choices=["tiny", "cpu", "paper"])
        p.add_argument("--obs", nargs="+", default=["state"] if cpu else ["state", "image", "pointcloud"],
                       choices=["state", "image", "pointcloud"])
        p.add_argument("--shapes", nargs="+", default=None, choices=sorted(SHAPES),
                       help="the PyTorch comparison's paper-size shapes instead of the --sizes x --obs grid")
        p.add_argument("--compute-dtypes", nargs="+", default=["float32"], choices=["float32", "bfloat16"],
                       help="model.compute_dtype per row (bf16 convolution / attention operands, fp32 accumulation)")
    p.add_argument("--matmul-precision", default="default",
                   help="jax.default_matmul_precision, e.g. 'bfloat16' (bf16 matmuls on a GPU)")
    default_dir = os.path.relpath(default_results_dir(name), os.path.dirname(os.path.dirname(RESULTS_DIR)))
    p.add_argument("--out-dir", default=None, help=f"where the JSON goes (default {default_dir})")
    return p


def device_description() -> str:
    """Human-readable description of the default device, e.g. ``cpu (2 cores)`` or ``NVIDIA H100``."""
    dev = jax.devices()[0]
    if dev.platform == "cpu":
        return f"cpu ({os.cpu_count()} cores)"
    return getattr(dev, "device_kind", dev.platform)


def bench_config(size: str, obs: str, **changes) -> PolicyConfig:
    """The benchmark ``PolicyConfig`` of one size (``SIZES``) and observation type (state | image | pointcloud),
    plus dotted-field ``changes`` (``replace``'s keys)."""
    if size not in SIZES:
        raise ValueError(f"size: must be one of {sorted(SIZES)}, got {size!r}")
    return replace(PolicyConfig(), **{"encoder.obs_type": obs, **SIZES[size], **changes})


class BenchPolicy(NamedTuple):
    """An initialised (untrained) policy for benchmarks: config, network, variables, normaliser and one raw
    observation window ``{key: (1, M, L_h, ...)}`` plus the matching random batch maker."""

    cfg: PolicyConfig
    net: PolicyNet
    params: Any
    normalizer: Normalizer
    obs: dict[str, jax.Array]


def example_obs(cfg: PolicyConfig, batch: int, key: jax.Array, state_dim: int = STATE_DIM) -> dict[str, jax.Array]:
    """Random raw observation windows ``{key: (batch, M, L_h, ...)}`` for ``cfg.encoder.obs_type``.

    state ``(.., state_dim)``; image ``(.., S, S, 3)`` in [-1, 1]; point cloud ``(.., P, point_dims)``.
    """
    m, lh, e = cfg.chunk.num_freqs, cfg.chunk.obs_horizon, cfg.encoder
    k1, k2 = jax.random.split(key)
    obs = {"state": jax.random.uniform(k1, (batch, m, lh, state_dim))}
    if e.obs_type == "image":
        obs["image"] = jax.random.uniform(k2, (batch, m, lh, e.image_size, e.image_size, 3), minval=-1.0, maxval=1.0)
    elif e.obs_type == "pointcloud":
        obs["point_cloud"] = jax.random.normal(k2, (batch, m, lh, e.num_points, e.point_dims))
    return obs


def make_bench_policy(size: str, obs_type: str, seed: int = 0, state_dim: int = STATE_DIM,
                      action_dim: int = ACTION_DIM, **changes) -> BenchPolicy:
    """Initialise ``PolicyNet`` for ``bench_config(size, obs_type)`` with a normaliser fitted on uniform [0, 1) data
    of ``state_dim`` / ``action_dim`` features (so raw observations in [0, 1) map to [-1, 1)); ``changes`` go to
    ``bench_config``."""
    cfg = bench_config(size, obs_type, **changes)
    obs = example_obs(cfg, 1, jax.random.key(seed), state_dim)
    params = init_policy_params(cfg, action_dim, obs, jax.random.key(seed))
    rng = np.random.default_rng(seed)
    normalizer = Normalizer.fit({"state": rng.random((256, state_dim), np.float32),
                                 "action": rng.random((256, action_dim), np.float32)})
    return BenchPolicy(cfg, PolicyNet(cfg, action_dim), params, normalizer, obs)


def timed_calls(fn: Callable[[int], Any], repeats: int, budget_s: float | None = None, warmup: int = 1,
                min_calls: int = 2) -> tuple[list[float], float]:
    """Time ``fn(i)`` (its result is ``block_until_ready``-ed) after ``warmup`` untimed calls.

    Runs ``repeats`` timed calls, or stops early once ``budget_s`` seconds are spent (after ``min_calls``).
    Returns (per-call seconds, seconds of the first warm-up call, i.e. compile + run when not yet compiled).
    """
    first = math.nan
    for i in range(warmup):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(-1 - i))
        if i == 0:
            first = time.perf_counter() - t0
    times: list[float] = []
    start = time.perf_counter()
    for i in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(i))
        times.append(time.perf_counter() - t0)
        if budget_s is not None and len(times) >= min_calls and time.perf_counter() - start > budget_s:
            break
    return times, first


def latency_stats(times: list[float]) -> dict[str, float]:
    """median / p90 / min (seconds) and the number of calls of a list of call times."""
    a = np.asarray(times, np.float64)
    return {"median_s": float(np.median(a)), "p90_s": float(np.percentile(a, 90)), "min_s": float(a.min()),
            "calls": int(a.size)}


class MemoryMonitor(contextlib.AbstractContextManager):
    """Peak memory inside a ``with`` block: device ``peak_bytes_in_use`` on an accelerator, process RSS on a CPU.

    On a CPU a thread polls the RSS every ``interval_s``; ``peak_mb`` is the largest RSS seen and ``delta_mb`` its
    excess over the RSS at entry. On an accelerator ``peak_mb`` is the allocator's peak so far (it never resets,
    so it is meaningful when sizes grow monotonically) and ``delta_mb`` its excess over the bytes in use at entry.
    """

    def __init__(self, interval_s: float = 0.005):
        self.interval_s = interval_s
        self.peak_mb = math.nan
        self.delta_mb = math.nan
        self.kind = "rss" if device_kind() == "cpu" else "device"

    def _rss(self) -> int:
        import psutil

        return psutil.Process().memory_info().rss

    def __enter__(self):
        if self.kind == "device":
            stats = jax.devices()[0].memory_stats() or {}
            self._base = stats.get("bytes_in_use", 0)
            return self
        self._base = self._peak = self._rss()
        self._stop = threading.Event()

        def poll():
            while not self._stop.is_set():
                self._peak = max(self._peak, self._rss())
                self._stop.wait(self.interval_s)

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        if self.kind == "device":
            stats = jax.devices()[0].memory_stats() or {}
            peak = stats.get("peak_bytes_in_use", math.nan)
        else:
            self._stop.set()
            self._thread.join()
            peak = max(self._peak, self._rss())
        self.peak_mb = peak / 2**20
        self.delta_mb = (peak - self._base) / 2**20
        return False


def compiled_flops(fn: Callable, *args) -> float:
    """FLOPs of one call of ``jax.jit(fn)(*args)`` from XLA's cost analysis (NaN if unavailable).

    XLA counts a ``while`` / ``scan`` body once, so cost loop bodies by compiling the body itself.
    """
    analysis = jax.jit(fn).lower(*args).compile().cost_analysis()
    if isinstance(analysis, (list, tuple)):
        analysis = analysis[0] if analysis else {}
    return float((analysis or {}).get("flops", math.nan))


def matmul_peak_gflops(n: int | None = None, repeats: int = 10, dtype=jnp.float32) -> dict[str, float]:
    """Estimated machine peak: the best GFLOP/s of an ``n x n`` matmul (default 2048 on a CPU, 8192 otherwise), with
    ``dtype`` operands and float32 accumulation (bf16 operands use the BF16 dot-product instructions where XLA
    has them)."""
    n = n or (2048 if device_kind() == "cpu" else 8192)
    a = jax.random.normal(jax.random.key(0), (n, n), dtype)
    b = jax.random.normal(jax.random.key(1), (n, n), dtype)
    mm = jax.jit(lambda x, y: jax.lax.dot(x, y, preferred_element_type=jnp.float32))
    times, _ = timed_calls(lambda i: mm(a, b), repeats, warmup=2)
    return {"n": n, "dtype": jnp.dtype(dtype).name, "gflops": 2.0 * n**3 / min(times) / 1e9,
            "median_gflops": 2.0 * n**3 / float(np.median(times)) / 1e9}


def memory_bandwidth_gbs(mbytes: int = 512, repeats: int = 10) -> dict[str, float]:
    """Estimated read bandwidth: the best GB/s of summing a ``mbytes`` MB float32 array (far larger than the
    caches). At small N one denoising step reads every U-Net weight once, so weight bytes / this bandwidth bounds
    its latency from below."""
    a = jnp.ones((mbytes * 2**20 // 4,), jnp.float32)
    total = jax.jit(jnp.sum)
    times, _ = timed_calls(lambda i: total(a), repeats, warmup=2)
    return {"mbytes": mbytes, "gbs": a.nbytes / min(times) / 1e9, "median_gbs": a.nbytes / float(np.median(times)) / 1e9}


def machine_peaks() -> dict[str, float]:
    """The machine peaks of the default JAX device, measured now (~2–4 s on a 2-core CPU): the best float32
    matmul GFLOP/s (``matmul_peak_gflops``) and read GB/s (``memory_bandwidth_gbs``, 256 MB)."""
    mm = matmul_peak_gflops(repeats=5)
    bw = memory_bandwidth_gbs(mbytes=256, repeats=5)
    return {"matmul_f32_gflops": mm["gflops"], "matmul_n": mm["n"], "matmul_f32_median_gflops": mm["median_gflops"],
            "bandwidth_gbs": bw["gbs"], "bandwidth_mbytes": bw["mbytes"], "bandwidth_median_gbs": bw["median_gbs"]}


def write_results(name: str, payload: dict, out_dir: str | None = None, peaks: dict | None = None) -> str:
    """Write ``payload`` (plus device metadata and ``machine``: the CPU model, core count, load average and the
    machine peaks, ``benchmarks.machine``) to ``<out_dir>/<name>_<device>.json``; returns the path. ``peaks``:
    figures measured earlier in this process (default: ``machine_peaks()`` now, as the JSON is written)."""
    out_dir = out_dir or RESULTS_DIR
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, f"{name}_{device_kind()}.json")
    meta = {"benchmark": name, "device": device_kind(), "device_description": device_description(),
            "jax_version": jax.__version__, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "machine": machine_info(machine_peaks if peaks is None else lambda: peaks)}
    with open(path, "w") as f:
        f.write(jsonio.dumps({**meta, **payload}, indent=1))
        f.write("\n")
    return path


def report_rows(name: str, argv, args, rows: list[dict], table: str, module: str | None = None,
                peaks: dict | None = None, **extra) -> dict:
    """Print ``table``, write ``{command, args, **extra, rows, table_md}`` as the benchmark's JSON; → the payload.
    ``argv``: the ``main(argv)`` argument (None: ``sys.argv[1:]``); ``args``: the parsed namespace; ``module``:
    the benchmark's module under ``benchmarks`` when the JSON's ``name`` is not (``profile_eval`` for
    ``profile_eval_compare``, ``studies.precision`` for ``precision``). The JSON goes to ``args.out_dir``, else
    ``default_results_dir(module)``; ``peaks``: the machine peaks measured earlier in this process, for the JSON's
    ``machine`` entry (default: measured as it is written, ``write_results``)."""
    import sys

    print(table)
    payload = {"command": f"python -m benchmarks.{module or name} " + " ".join(sys.argv[1:] if argv is None else argv),
               "args": {k: v for k, v in vars(args).items() if k != "out_dir"}, **extra, "rows": rows,
               "table_md": table}
    print(f"wrote {write_results(name, payload, args.out_dir or default_results_dir(module or name), peaks)}")
    return payload


def markdown_table(headers: list[str], rows: list[list[Any]]) -> str:
    """A GitHub markdown table; floats are printed with 4 significant digits."""
    def fmt(v):
        if isinstance(v, float):
            return "nan" if math.isnan(v) else f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def precision_context(precision: str | None):
    """``jax.default_matmul_precision(precision)`` (e.g. 'bfloat16' for bf16 matmuls on a GPU), or a no-op."""
    return jax.default_matmul_precision(precision) if precision and precision != "default" else contextlib.nullcontext()


__all__ = ["ACTION_DIM", "BenchPolicy", "MemoryMonitor", "RESULTS_DIR", "SIZES", "STATE_DIM", "STUDIES_RESULTS_DIR",
           "bench_config", "compiled_flops", "default_results_dir", "device_description", "device_kind", "example_obs",
           "latency_stats",
           "machine_peaks", "make_bench_policy", "SHAPES", "BenchModel", "bench_models", "markdown_table", "matmul_peak_gflops", "memory_bandwidth_gbs", "param_count", "precision_context",
           "timed_calls", "write_results"]
