"""Where the time goes: a ``jax.profiler`` trace of the N-sample sampler and of the train step, per model part.

    python -m benchmarks.profile                                   # CPU default: the PyTorch comparison's shapes
    python -m benchmarks.profile --shapes hipolicy --compute-dtypes float32 bfloat16 --n 100 --batch 128

For each model (``--shapes`` / ``--sizes`` x ``--obs``, per ``--compute-dtypes``) it traces ``--calls`` calls
(after a warm-up) of (a) the one-call sampler with ``--n`` samples and ``--steps`` DDIM steps (the loop body is
the same denoiser call for DDPM; per-step time scales to 100 steps) and (b) the real train step at ``--batch``.
The trace's XLA operations (thunks) are matched to the compiled HLO by name and grouped by the model part their
``op_name`` metadata names (the flax module path) and by pass (forward, backward, optimizer):

- ``convolution``: the residual blocks' convolutions, their 1x1 residual / final convs (native or im2col matmul);
- ``down-sampling conv``, ``up-sampling conv`` (the transposed conv, computed as a stride-1 conv);
- ``GroupNorm``, ``Mish``, ``FiLM`` (the heads and the per-segment scale/bias), ``fusion attention``;
- ``layout`` (copies, transposes, concatenations, slices, pads with no arithmetic);
- ``encoder / step embedding``, ``sampler update + noise`` (the DDIM / DDPM update between denoiser calls),
  ``loss + noise``, ``optimizer + EMA`` (AdamW, the cosine schedule, the EMA update, the non-finite guard).

A fused XLA operation is counted under the part its root instruction belongs to. Thunk times are summed over
both threads' events; their total can exceed the wall time when operations overlap. XLA's native (Eigen)
convolutions, which the float32 path runs where ``T >= k``, hand their work to Eigen's thread pool: their events
do not cover it, and ``wall − op ms`` is then mostly that convolution time.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import re
import tempfile
import time

import jax

from benchmarks.common import base_parser, bench_models, markdown_table, peer_shape_args, report_rows
from benchmarks.sampling import compiled_sampler
from benchmarks.train_step import train_setup

NAME = "profile"
PARTS = ("convolution", "down-sampling conv", "up-sampling conv", "GroupNorm", "Mish", "FiLM", "fusion attention",
         "layout", "encoder / step embedding", "sampler update + noise", "loss + noise", "optimizer + EMA", "other")
_LAYOUT_OPS = {"parameter", "bitcast", "copy", "transpose", "concatenate", "slice", "pad", "reshape", "broadcast",
               "reverse", "constant", "dynamic-slice", "dynamic-update-slice", "tuple", "get-tuple-element", "convert", "iota"}
_CONTROL_OPS = {"while", "call", "conditional"}


def parse_args(argv=None):
    p = base_parser(NAME, __doc__, grid=True)
    p.add_argument("--n", type=int, default=100, help="samples per sampler call")
    p.add_argument("--steps", type=int, default=10, help="DDIM steps per sampler call")
    p.add_argument("--batch", type=int, default=128, help="train-step batch")
    p.add_argument("--calls", type=int, default=3, help="traced calls per workload (after one warm-up)")
    p.add_argument("--workloads", nargs="+", default=["sample", "train"], choices=["sample", "train"])
    p.add_argument("--quick", action="store_true", help="tiny size, N 4, batch 8, one call (the smoke test)")
    return peer_shape_args(p.parse_args(argv), n=4, batch=8, calls=1, steps=2)


class HloIndex:
    """Instruction name -> (opcode, op_name metadata, opcodes of the fused computation) of a compiled module."""

    _INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*\S+(?:\[[^\]]*\])?(?:\{[^}]*\})?\s+([\w\-]+)\(")
    _COMP = re.compile(r"^\s*(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")

    def __init__(self, hlo_text: str):
        self.instr: dict[str, tuple[str, str, str]] = {}  # name -> (opcode, op_name, called computation)
        self.comp_ops: dict[str, set[str]] = collections.defaultdict(set)
        self.comp_op_name: dict[str, str] = {}  # a fused computation's root op_name, else its first non-empty one
        comp = None
        for line in hlo_text.splitlines():
            m = self._COMP.match(line)
            if m and "=" not in line.split("{")[0]:
                comp = m.group(1)
                continue
            m = self._INSTR.match(line)
            if not m:
                continue
            name, opcode = m.group(1), m.group(2)
            op_name = re.search(r'op_name="([^"]*)"', line)
            calls = re.search(r"calls=%?([\w.\-]+)", line)
            self.instr[name] = (opcode, op_name.group(1) if op_name else "", calls.group(1) if calls else "")
            if comp is not None:
                self.comp_ops[comp].add(opcode)
                if op_name and (comp not in self.comp_op_name or line.lstrip().startswith("ROOT")):
                    self.comp_op_name[comp] = op_name.group(1)

    def part(self, name: str, workload: str = "train") -> tuple[str, str] | None:
        """(part, pass) of the thunk ``name``; None for control-flow thunks (their children are counted) and for
        events that are not HLO instructions."""
        if name not in self.instr:
            return None
        opcode, op_name, calls = self.instr[name]
        if opcode in _CONTROL_OPS:
            return None
        ops = self.comp_ops.get(calls, {opcode}) if opcode == "fusion" else {opcode}
        return classify(op_name or self.comp_op_name.get(calls, ""), ops, workload)


def classify(op_name: str, ops: set[str], workload: str = "train") -> tuple[str, str]:
    """(part, pass) from an instruction's ``op_name`` (flax module path + primitive) and its (fused) opcodes;
    ``workload`` ('sample' | 'train') names what the operations outside the network are."""
    if "transpose(jvp(" in op_name:
        phase = "backward"
    elif "PolicyNet" in op_name or "unet" in op_name.split("/"):
        phase = "forward"
    else:
        phase = "other"
    path = op_name.split("/")
    if ops <= _LAYOUT_OPS:
        part = "layout"
    elif any(p.endswith("_upsample") for p in path):
        part = "up-sampling conv"
    elif any(p.endswith("_downsample") for p in path):
        part = "down-sampling conv"
    elif "fusion" in path:
        part = "fusion attention"
    elif "norm" in path:
        part = "GroupNorm"
    elif any(p in ("conv", "residual", "final_conv") for p in path):
        part = "convolution"
    elif "film" in path or any(re.fullmatch(r"(down|mid|up)\d*_res\d", p) for p in path[-2:]):
        part = "FiLM"
    elif any(re.fullmatch(r"block\d|final_block", p) for p in path):
        part = "Mish"
    elif "obs_encoder" in path or any(p.startswith("step_dense") or p == "step_encoder" for p in path) \
            or "encode" in op_name:
        part = "encoder / step embedding"
    elif phase == "other" and workload == "sample":
        part = "sampler update + noise"
    elif phase == "other" and re.search(r"_normal|threefry|randint|random|erf_inv|loss|mse|mean", op_name):
        part = "loss + noise"
    elif phase == "other":
        part = "optimizer + EMA"
    else:
        part = "other"
    return part, ("update" if part == "optimizer + EMA" else phase)


def trace_events(fn, calls: int) -> tuple[list[dict], float]:
    """Run ``fn()`` ``calls`` times under ``jax.profiler.trace``; (complete events, wall seconds per call)."""
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d, create_perfetto_trace=True):
            t0 = time.perf_counter()
            for _ in range(calls):
                jax.block_until_ready(fn())
            wall = (time.perf_counter() - t0) / calls
        paths = glob.glob(os.path.join(d, "**", "*.trace.json.gz"), recursive=True)
        if not paths:
            raise RuntimeError(f"profile: jax.profiler wrote no perfetto trace under {d}")
        with gzip.open(paths[0]) as f:
            trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    return [e for e in events if e.get("ph") == "X"], wall


def breakdown(events: list[dict], index: HloIndex, calls: int, workload: str = "train") -> dict:
    """Per-part and per-(part, pass) milliseconds per call, and the top operations."""
    parts = collections.Counter()
    passes = collections.Counter()
    ops = collections.Counter()
    part_ops: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for e in events:
        pp = index.part(e["name"], workload)
        if pp is None:
            continue
        ms = e.get("dur", 0) / 1e3 / calls
        parts[pp[0]] += ms
        passes[f"{pp[0]} ({pp[1]})"] += ms
        label = f"{e['name']} [{index.instr[e['name']][1].split('/', 1)[-1][:90]}]"
        ops[label] += ms
        part_ops[pp[0]][label] += ms
    total = sum(parts.values())
    return {"total_op_ms": total, "parts_ms": dict(parts), "passes_ms": dict(passes),
            "top_ops_ms": dict(ops.most_common(12)),
            "top_ops_per_part_ms": {p: dict(c.most_common(4)) for p, c in part_ops.items()}}


def sample_workload(model, args):
    policy = model.policy()
    fn = compiled_sampler(policy, "ddim", args.steps, args.n)
    key = jax.random.key(0)
    call = lambda: fn(policy.params, policy.normalizer, policy.obs, key).chunks  # noqa: E731
    hlo = fn.lower(policy.params, policy.normalizer, policy.obs, key).compile().as_text()
    return call, hlo


def train_workload(model, args):
    _, step, batch, key, holder = train_setup(model, args.batch)
    hlo = step.lower(holder["state"], batch, key).compile().as_text()

    def call():
        holder["state"], metrics = step(holder["state"], batch, key)  # the state is donated
        return metrics["loss"]

    return call, hlo


def main(argv=None) -> dict:
    args = parse_args(argv)
    rows = []
    for model in bench_models(args):
        for workload in args.workloads:
            make = sample_workload if workload == "sample" else train_workload
            call, hlo = make(model, args)
            jax.block_until_ready(call())  # compile + warm-up
            events, wall = trace_events(call, args.calls)
            res = breakdown(events, HloIndex(hlo), args.calls, workload)
            label = (f"sample N={args.n}, DDIM {args.steps}" if workload == "sample"
                     else f"train step, batch {args.batch}")
            rows.append({"model": model.size, "obs": model.obs, "dtype": model.dtype, "workload": workload,
                         "label": label, "wall_ms": wall * 1e3, **res})
            top = ", ".join(f"{k} {v:.0f}" for k, v in sorted(res["parts_ms"].items(), key=lambda kv: -kv[1])[:5])
            print(f"[{model.size}/{model.dtype}] {label}: wall {wall * 1e3:.1f} ms, ops {res['total_op_ms']:.1f} "
                  f"ms ({top})", flush=True)
    headers = ["model", "dtype", "workload", "wall ms", "op ms", "wall − op ms"] + [p for p in PARTS]
    table = markdown_table(headers, [[r["model"], r["dtype"], r["label"], r["wall_ms"], r["total_op_ms"],
                                      max(r["wall_ms"] - r["total_op_ms"], 0.0)]
                                     + [_pct(r, p) for p in PARTS] for r in rows])
    return report_rows(NAME, argv, args, rows, table,
                       note="Cells of each part: % of the summed XLA operation time (`op ms`), from a "
                            "`jax.profiler` trace; see the module docstring for the grouping.")


def _pct(row: dict, part: str) -> str:
    ms = row["parts_ms"].get(part, 0.0)
    return "–" if ms == 0 else f"{100 * ms / row['total_op_ms']:.1f}"


if __name__ == "__main__":
    main()
