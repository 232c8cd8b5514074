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
            ("rollout", "Closed-loop rollout throughput (MJX, policy in the loop)"),
            ("tradeoff", "Latency–success trade-off"),
            ("delay", "Asynchronous execution: success under inference delay"),
            ("serving", "Policy serving: in-process, exported, websocket round trip"))


def render(device: str, notes: str = "", results_dir: str = RESULTS_DIR) -> str:
    """Markdown of every ``<name>_<device>.json`` present in ``results_dir``."""
    out = ["## Performance", ""]
    if notes:
        out += [notes.strip(), ""]
    for name, title in SECTIONS:
        path = os.path.join(results_dir, f"{name}_{device}.json")
        if not os.path.exists(path):
            continue
        with open(path) as f:
            res = jsonio.loads(f.read())
        out += [f"### {title}", "", f"`{res['command'].strip()}` on {res['device_description']} "
                f"(jax {res['jax_version']}, {res['time']})", ""]
        if name == "sampling":
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
