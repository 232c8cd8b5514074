"""Assemble ``benchmarks/results/PERFORMANCE.md`` (the README "Performance" section) from the result JSONs.

    python -m benchmarks.report [--device cpu] [--notes benchmarks/results/notes_cpu.md]

Each benchmark's section gives the command it was run with and its markdown table; ``--notes`` (markdown) is
inserted after the heading, for the figures that need prose (the ratios quoted in the summary).
"""

from __future__ import annotations

import argparse
import os

from benchmarks.common import RESULTS_DIR, device_kind
from hipolicy_jax import jsonio

SECTIONS = (("sampling", "One-call N-sample latency (the paper's sample-times table)"),
            ("optimisation", "Sampler optimisations, before / after (interleaved, one run)"),
            ("convolutions", "Short-sequence U-Net convolutions, before / after (interleaved, one run)"),
            ("train_step", "Train-step throughput"),
            ("sampling_shapes", "One-call N-sample latency at the PyTorch comparison's shapes (paper size)"),
            ("train_step_shapes", "Train-step throughput at the PyTorch comparison's shapes (paper size)"),
            ("compute_dtype", "Throughput changes, before / after (interleaved, one run)"),
            ("profile", "Where the time goes: profile by model part (jax.profiler trace)"),
            ("precision", "bf16 vs float32: sample statistics of trained runs"),
            ("rollout", "Closed-loop rollout throughput (MJX, policy in the loop)"),
            ("tradeoff", "Latency–success trade-off"),
            ("delay", "Asynchronous execution: success under inference delay"),
            ("serving", "Policy serving: in-process, exported, websocket round trip"))


def _load(results_dir: str, name: str, device: str):
    path = os.path.join(results_dir, f"{name}_{device}.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return jsonio.loads(f.read())


# (our shape, the PyTorch peer's shape) per comparison row; the light fusion is compared with the paper's fusion
PEER_ROWS = (("dp-lowdim", "dp-lowdim"), ("hipolicy-nofusion", "hipolicy-nofusion"), ("hipolicy", "hipolicy"),
             ("hipolicy-lightfusion", "hipolicy"))


def peer_comparison(device: str, results_dir: str = RESULTS_DIR) -> str:
    """The PyTorch comparison table from ``pytorch_peer``, ``sampling --shapes`` and ``train_step --shapes`` JSONs:
    per workload, the PyTorch time, ours in float32 and bfloat16, the ratios, GFLOP/s and % of the measured peaks.
    Empty when a JSON is missing."""
    peer, samp, train = (_load(results_dir, n, device) for n in ("pytorch_peer", "sampling_shapes",
                                                                  "train_step_shapes"))
    if not (peer and samp and train):
        return ""
    rows = []
    for ours, theirs in PEER_ROWS:
        for workload, n in (("sample", 1), ("sample", 100), ("train", None)):
            ref = [r for r in peer["rows"] if r["shape"] == theirs and r["workload"] == workload
                   and (n is None or r.get("n") == n)]
            src = train["rows"] if workload == "train" else [r for r in samp["rows"] if r["sampler"] == "ddpm"
                                                              and r["n"] == n and r["mode"] == "vmap"]
            mine = {r.get("dtype", "float32"): r for r in src if r["size"] == ours}
            if not ref or not mine or "float32" not in mine:
                continue
            # GFLOP/s on equal work: XLA counts the bf16 im2col matmuls' zero padding too, so every dtype's rate
            # uses the float32 model's FLOP count
            if workload == "train":
                work = mine["float32"]["flops_per_step"]
            else:
                work = next(m["flops_per_sample_step"] for m in samp["models"]
                            if m["size"] == ours and m.get("dtype", "float32") == "float32") * n * 100
            label = f"{ours}: " + (f"sample N={n}, DDPM 100" if workload == "sample" else
                                   f"train step, batch {train['args']['batch']}")
            cells = [label, f"{ref[0]['median_s']:.3f}"]
            for dt in ("float32", "bfloat16"):
                r = mine.get(dt)
                if r is None:
                    cells += ["–"] * 3
                    continue
                gflops = work / r["median_s"] / 1e9
                peaks = samp["machine_peak"]["gflops"], samp["machine_peak_bf16"]["gflops"]
                cells += [f"{r['median_s']:.3f}", f"**{ref[0]['median_s'] / r['median_s']:.2f}**",
                          f"{gflops:.0f} ({100 * gflops / peaks[0]:.0f} / {100 * gflops / peaks[1]:.0f} %)"]
            rows.append(cells)
    from benchmarks.common import markdown_table

    table = markdown_table(["workload", "PyTorch s", "ours f32 s", "PyTorch / ours f32", "f32 GFLOP/s (% f32 / bf16 "
                            "peak)", "ours bf16 s", "PyTorch / ours bf16", "bf16 GFLOP/s (% f32 / bf16 peak)"], rows)
    return "\n".join([f"`{peer['command'].strip()}` (torch {peer['torch_version']}, {peer['threads']} threads, "
                      f"{peer['time']}) against the `sampling_shapes` / `train_step_shapes` rows below, same machine. GFLOP/s are on equal "
                      f"work (the float32 model's XLA FLOP count) against the measured fp32 / bf16-operand matmul "
                      f"peaks.", "",
                      table, ""])


def render(device: str, notes: str = "", results_dir: str = RESULTS_DIR) -> str:
    """Markdown of every ``<name>_<device>.json`` present in ``results_dir``."""
    out = ["## Performance", ""]
    if notes:
        out += [notes.strip(), ""]
    comparison = peer_comparison(device, results_dir)
    if comparison:
        out += ["### Against the PyTorch original (Diffusion Policy's U-Net, same machine)", "", comparison]
    for name, title in SECTIONS:
        path = os.path.join(results_dir, f"{name}_{device}.json")
        if not os.path.exists(path):
            continue
        with open(path) as f:
            res = jsonio.loads(f.read())
        out += [f"### {title}", "", f"`{res['command'].strip()}` on {res['device_description']} "
                f"(jax {res['jax_version']}, {res['time']})", ""]
        if name.startswith("sampling"):
            peak = res["machine_peak"]
            bf16 = res.get("machine_peak_bf16")
            out += [f"Machine peak estimate: {peak['gflops']:.1f} GFLOP/s ({peak['dtype']} {peak['n']}² matmul)"
                    + (f", {bf16['gflops']:.1f} GFLOP/s with bf16 operands (fp32 accumulation)" if bf16 else "")
                    + f". Default `PolicyConfig()` policy: {res['default_policy_params']:,} parameters.", ""]
            out += [f"- {m['size']}/{m['obs']}: {m['params']:,} parameters, "
                    f"{m['flops_per_sample_step'] / 1e6:.2f} MFLOP per sample-step" for m in res["models"]] + [""]
        if name == "tradeoff":
            cheapest = res.get("cheapest_within_3_points")
            out += [res["note"], ""] + ([f"**{cheapest['summary'][0].upper()}{cheapest['summary'][1:]}.**", ""]
                                        if cheapest else [])
        elif res.get("note"):
            out += [res["note"], ""]
        out += [res["table_md"], ""]
        if name == "tradeoff" and res.get("png"):
            out += [f"![Decision latency vs closed-loop success]({res['png']})", ""]
        if name == "delay":
            out += [f"![Success and steps vs inference delay]({name}_{device}.png)", ""]
    return "\n".join(out)


def main(argv=None) -> str:
    p = argparse.ArgumentParser(prog="python -m benchmarks.report", description=__doc__)
    p.add_argument("--device", default=device_kind())
    p.add_argument("--notes", default=None, help="markdown file inserted after the heading")
    p.add_argument("--out", default=os.path.join(RESULTS_DIR, "PERFORMANCE.md"))
    args = p.parse_args(argv)
    notes = open(args.notes).read() if args.notes else ""
    text = render(args.device, notes)
    with open(args.out, "w") as f:
        f.write(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
