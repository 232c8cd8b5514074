"""Assemble ``benchmarks/results/PERFORMANCE.md`` (linked from docs/performance.md) from the result JSONs.

    python -m benchmarks.report [--device cpu] [--notes benchmarks/results/notes_cpu.md]

Each benchmark's section gives the command it was run with and its markdown table; ``--notes`` (markdown) is
inserted after the heading, for the figures that need prose (the ratios quoted in the summary). A section's JSON
is read from ``benchmarks/results`` (the benchmarks at the top of ``benchmarks``) or, failing that, from
``benchmarks/studies/results`` (the finished studies, ``benchmarks.studies``).
"""

from __future__ import annotations

import argparse
import os

from benchmarks.common import RESULTS_DIR, STUDIES_RESULTS_DIR, device_kind
from hipolicy_jax import jsonio

SECTIONS = (("sampling", "One-call N-sample latency (the paper's sample-times table)"),
            ("optimisation", "Sampler optimisations, before / after (interleaved, one run)"),
            ("convolutions", "Short-sequence U-Net convolutions, before / after (interleaved, one run)"),
            ("train_step", "Train-step throughput"),
            ("point_encoder", "Point-cloud train step: written backward and kept host memory, before / after "
                              "(interleaved, one run)"),
            ("roofline", "The train step against the roofline, stage by stage (point clouds and images)"),
            ("sampling_shapes", "One-call N-sample latency at the PyTorch comparison's shapes (paper size)"),
            ("train_step_shapes", "Train-step throughput at the PyTorch comparison's shapes (paper size)"),
            ("compute_dtype", "Throughput changes, before / after (interleaved, one run)"),
            ("profile", "Where the time goes: profile by model part (jax.profiler trace)"),
            ("precision", "bf16 vs float32: sample statistics of trained runs"),
            ("rollout", "Closed-loop rollout throughput (MJX, policy in the loop)"),
            ("profile_eval", "Evaluation profile: where one closed-loop evaluation's time goes"),
            ("profile_eval_compare_e100", "Compacted rollout vs the vmapped one, 100 episodes (interleaved, one run)"),
            ("profile_eval_compare_e100_hipolicy", "Compacted rollout vs the vmapped one: a cpu-budget HiPolicy run, "
                                                   "100 episodes"),
            ("profile_eval_compare_e20", "Compacted rollout vs the vmapped one, 20 episodes (interleaved, one run)"),
            ("profile_eval_compile", "Rollout compile: cold, its pieces alone, and from the persistent cache"),
            ("profile_eval_compare_drawn", "Single-frequency decisions: sample 0 alone vs all N samples (interleaved, "
                                           "one run)"),
            ("sampling_n1", "N = 1 against the weight-read bound (DP low-dim, paper size; campaigns paused)"),
            ("small_matmul", "The N = 1 bound one kernel at a time: XLA's small-M dot against the read bandwidth"),
            ("tradeoff", "Latency–success trade-off"),
            ("delay", "Asynchronous execution: success under inference delay"),
            ("serving", "Policy serving: in-process, exported, websocket round trip"),
            ("checkpoint_load", "Checked checkpoints: what verifying the checksums costs a load (interleaved, one run)"))


def _path(name: str, device: str, dirs) -> str | None:
    """The first ``<dir>/<name>_<device>.json`` of ``dirs`` that exists (None: none does)."""
    for d in dirs:
        path = os.path.join(d, f"{name}_{device}.json")
        if os.path.exists(path):
            return path
    return None


def _load(dirs, name: str, device: str):
    path = _path(name, device, dirs)
    if path is None:
        return None
    with open(path) as f:
        return jsonio.loads(f.read())


# (our shape, the PyTorch peer's shape) per comparison row; the light fusion is compared with the paper's fusion
PEER_ROWS = (("dp-lowdim", "dp-lowdim"), ("hipolicy-nofusion", "hipolicy-nofusion"), ("hipolicy", "hipolicy"),
             ("hipolicy-lightfusion", "hipolicy"))


def peer_comparison(device: str, results_dir: str = RESULTS_DIR, studies_dir: str = STUDIES_RESULTS_DIR) -> str:
    """The PyTorch comparison table from ``pytorch_peer``, ``sampling --shapes`` and ``train_step --shapes`` JSONs:
    per workload, the PyTorch time, ours in float32 and bfloat16, the ratios, GFLOP/s and % of the measured peaks.
    Empty when a JSON is missing."""
    peer, samp, train = (_load((results_dir, studies_dir), n, device) for n in ("pytorch_peer", "sampling_shapes",
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


def serving_note(res: dict) -> str:
    """The serving benchmark's figures in words, every number from its JSON (``benchmarks.serving``)."""
    paths = {r["path"]: r for r in res["rows"]}
    inproc, exported, ws = (paths[k] for k in ("in-process (jit)", "exported program", "websocket round trip"))
    scaling = {(s["batch"], s["threads"]): s for s in res["batch_scaling"]}
    biggest = max(b for b, t in scaling if t == 1)
    big, one_row = scaling[(biggest, 1)], scaling[(1, 1)]
    one, many, t = res["load_one_client"], res["load"], res["targets"]
    unbatched = next((r for name, r in res["loads"].items() if r["server"]["max_batch"] == 1), None)
    pol, inf = res["policy"], res["policy"]["inference"]
    clients = many["clients"]
    lines = [
        f"Machine: {res['cpu_count']}-core {res['cpu_model']}; 1-minute load average "
        f"{t['load_average'][0][0]:.1f} before the load tests, {t['load_average'][-1][0]:.1f} after the timings. "
        f"Policy: {pol['task']}, strides {'/'.join(map(str, pol['strides']))}, N = {pol['num_samples']}, "
        f"{inf['num_steps']} sampler steps, execution {inf['execution']} ({res['policy_source']}). One observation "
        f"history per request, loopback.",
        "",
        f"- **One decision**: in-process {inproc['median_ms']:.1f} ms (median), the exported program "
        f"{exported['ratio_to_in_process']:.2f}x, the websocket round trip {ws['ratio_to_in_process']:.2f}x "
        f"({ws['median_ms']:.1f} ms, {ws['server_side_median_ms']:.1f} ms of it in the server's decision): serving "
        f"adds {ws['median_ms'] - exported['median_ms']:.0f} ms on loopback.",
        f"- **Batching**: one call of {biggest} rows costs {big['median_ms']:.0f} ms, "
        f"{big['median_ms'] / one_row['median_ms']:.2f}x one row's, so it decides {big['throughput_x_batch1']:.2f}x "
        f"the rows/s of batch 1; the decision is compute-bound on {res['cpu_count']} cores.",
        f"- **Load**: one client {one['requests_per_s']:.2f} requests/s (p50 {one['p50_ms']:.0f} ms); {clients} "
        f"clients {many['requests_per_s']:.1f} requests/s with batching (mean batch {many['mean_batch']:.2f}), "
        f"{t['throughput_ratio']:.2f}x one client (median of {len(t['throughput_ratio_by_round'])} rounds; pooled "
        f"{t['throughput_ratio_pooled']:.2f}x), p50 {many['p50_ms']:.0f} ms, p99 {many['p99_ms']:.0f} ms"
        + (f"; without batching {unbatched['requests_per_s']:.1f} requests/s, p50 {unbatched['p50_ms']:.0f} ms"
           if unbatched else "") + ".",
        f"- Batching buys throughput, not latency, here: the {t['throughput_ratio']:.2f}x is what one batched call "
        f"buys in compute ({t['best_batch_throughput_x']:.2f}x), and {clients} closed-loop clients wait at least "
        f"{t['mean_latency_bound_x_p50']:.2f}x one decision (their p50 is "
        f"{many['p50_ms'] / one['p50_ms']:.2f}x one client's). The benchmark's targets (>= "
        f"{t['throughput_target']}x requests/s, p99 <= {t['p99_target']}x one client's p50) are "
        f"{'met' if t['throughput_met'] and t['p99_met'] else 'not met'} on this machine (p99 / p50 "
        f"{t['p99_over_one_client_p50']:.1f}).",
    ]
    return "\n".join(lines)


def render(device: str, notes: str = "", results_dir: str = RESULTS_DIR,
           studies_dir: str = STUDIES_RESULTS_DIR) -> str:
    """Markdown of every ``<name>_<device>.json`` of ``SECTIONS`` present in ``results_dir`` or ``studies_dir``."""
    out = ["## Performance", ""]
    if notes:
        out += [notes.strip(), ""]
    comparison = peer_comparison(device, results_dir, studies_dir)
    if comparison:
        out += ["### Against the PyTorch original (Diffusion Policy's U-Net, same machine)", "", comparison]
    for name, title in SECTIONS:
        path = _path(name, device, (results_dir, studies_dir))
        if path is None:
            continue
        with open(path) as f:
            res = jsonio.loads(f.read())
        cpu = ((res.get("machine") or {}).get("cpu_model") or "unknown").split(" (")[0]
        out += [f"### {title}", "", f"`{res['command'].strip()}` on {res['device_description']}, {cpu} "
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
        elif name == "serving" and "load_one_client" in res:
            out += [serving_note(res), ""]
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
