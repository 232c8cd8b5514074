"""Smoke tests of the benchmark scripts: each ``main`` runs on a tiny config and writes finite JSON fields.

The figures themselves live in ``benchmarks/results`` and ``benchmarks/studies/results``; nothing here asserts a
timing.
"""

import json
import math
import os

import pytest

from hipolicy_jax import jsonio
from benchmarks import rollout, sampling, tradeoff, train_step
from benchmarks.studies import convolutions, optimisation, small_matmul
from benchmarks.machine import PEAKS_ENV


@pytest.fixture(autouse=True)
def _no_machine_peaks(monkeypatch):
    """The smoke runs skip the machine peaks (2–4 s per JSON; tests/test_machine_info.py checks them)."""
    monkeypatch.setenv(PEAKS_ENV, "0")


def _load(out_dir, name):
    files = list(out_dir.glob(f"{name}_*.json"))
    assert len(files) == 1, files
    text = files[0].read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))  # strict JSON
    return jsonio.loads(text)


def _finite(row, keys):
    for k in keys:
        assert k in row, f"missing field {k!r}"
        assert isinstance(row[k], (int, float)) and math.isfinite(row[k]), f"{k} = {row[k]!r}"


def test_sampling_benchmark(tmp_path):
    sampling.main(["--sizes", "tiny", "--obs", "state", "--ns", "1", "2", "--samplers", "ddim", "--ddim-steps", "2",
                   "--repeats", "2", "--loop-repeats", "1", "--peak-n", "256", "--out-dir", str(tmp_path)])
    res = _load(tmp_path, "sampling")
    _finite(res["machine_peak"], ["gflops"])
    _finite(res, ["default_policy_params"])
    _finite(res["models"][0], ["params", "flops_per_sample_step"])
    modes = {(r["n"], r["mode"]) for r in res["rows"]}
    assert modes == {(1, "vmap"), (2, "vmap"), (2, "loop")}
    for r in res["rows"]:
        _finite(r, ["median_s", "p90_s", "calls", "ratio_to_n1", "gflops", "fraction_of_peak", "mem_peak_mb",
                    "mem_delta_mb"])
        assert r["retraces"] == 0
    _finite(next(r for r in res["rows"] if r["mode"] == "loop"), ["loop_over_vmap"])


@pytest.mark.slow
def test_train_step_benchmark(tmp_path):
    train_step.main(["--sizes", "tiny", "--obs", "state", "pointcloud", "--num-points", "16", "32", "--batch", "8",
                     "--repeats", "2", "--out-dir", str(tmp_path)])
    rows = _load(tmp_path, "train_step")["rows"]
    assert [(r["obs"], r["points"]) for r in rows] == [("state", None), ("pointcloud", 16), ("pointcloud", 32)]
    assert rows[1]["params"] == rows[2]["params"] > rows[0]["params"]  # the point encoder ignores the point count
    for row in rows:
        _finite(row, ["median_s", "p90_s", "steps_per_s", "samples_per_s", "compile_s", "first_step_s",
                      "final_loss"])
        assert row["retraces"] == 0 and row["loss_finite"]


@pytest.mark.slow
def test_checkpoint_load_benchmark(tmp_path):
    from benchmarks.studies import checkpoint_load

    checkpoint_load.main(["--sizes", "tiny", "--rounds", "2", "--out-dir", str(tmp_path)])
    res = _load(tmp_path, "checkpoint_load")
    (row,) = res["rows"]
    _finite(row, ["policy_checked_median_s", "full_unchecked_median_s", "full_checked_median_s",
                  "policy_checksums_median_s", "policy_load_vs_before", "resume_vs_before"])
    assert row["size"] == "tiny" and all(len(v) == 2 for v in row["times_s"].values())
    assert row["policy_load_vs_before"] == pytest.approx(row["policy_checked_median_s"] / row["full_unchecked_median_s"])
    assert "a policy load takes" in res["note"] and res["machine"]


@pytest.mark.slow
def test_rollout_benchmark(tmp_path):
    rollout.main(["--size", "tiny", "--batches", "2", "--num-samples", "2", "--num-steps", "2",
                  "--max-steps", "8", "--repeats", "2", "--out-dir", str(tmp_path)])
    rows = _load(tmp_path, "rollout")["rows"]
    assert [r["episodes"] for r in rows] == [2]
    for r in rows:
        _finite(r, ["median_s", "env_steps_per_s", "replans_per_s", "samples_per_s", "compile_s"])
        assert all(s == 8 * r["episodes"] for s in r["control_steps"])


def test_optimisation_benchmark(tmp_path):
    optimisation.main(["--size", "tiny", "--ns", "2", "--samplers", "ddim", "--ddim-steps", "2", "--rounds", "2",
                       "--variants", "before", "after", "--out-dir", str(tmp_path)])
    (row,) = _load(tmp_path, "optimisation")["rows"]
    _finite(row, ["before_median_s", "after_median_s", "speedup_after", "max_abs_diff"])
    assert row["max_abs_diff"] < 1e-4 and row["retraces"] == 0


@pytest.mark.slow
def test_convolutions_benchmark(tmp_path):
    """Both variants compile and agree (native vs im2col / polyphase) on the tiny U-Net at a short horizon."""
    convolutions.main(["--size", "tiny", "--configs", "DP L_c=8", "--batch", "4", "--num-samples", "2",
                       "--ddim-steps", "2", "--rounds", "2", "--out-dir", str(tmp_path)])
    rows = _load(tmp_path, "convolutions")["rows"]
    assert [r["kind"] for r in rows] == ["train", "sample"]
    for r in rows:
        _finite(r, ["native_median_s", "after_median_s", "speedup", "max_abs_diff"])
        assert r["max_abs_diff"] < 1e-4


def _tiny_run(tmp_path, objective: str) -> str:
    """A 2-step tiny press_button run of ``objective`` on a synthetic demo buffer (random states and actions of the
    task's sizes, shared by the runs), so nothing is collected; → the run dir."""
    import numpy as np

    from hipolicy_jax import envs
    from hipolicy_jax.config import EvalConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig
    from hipolicy_jax.data.replay_buffer import ReplayBuffer
    from hipolicy_jax.runs.train import RunConfig, train

    data = tmp_path / "demos.zarr"
    if not data.exists():
        env, rng = envs.make("press_button"), np.random.default_rng(0)
        ReplayBuffer(data={"state": rng.random((180, env.state_dim), np.float32),
                           "action": rng.random((180, env.action_dim), np.float32)},
                     episode_ends=np.arange(30, 181, 30)).save(data)
    out = tmp_path / objective
    train(RunConfig(task="press_button", out=str(out), data=str(data), episodes=6, val_ratio=0.34,
                    policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2), objective=objective),
                    train=TrainConfig(batch_size=16, num_steps=2, warmup_steps=1, log_every=1, ckpt_every=2),
                    eval=EvalConfig(episodes=1, every=0),
                    inference=InferenceConfig(num_samples=2, num_steps=1, calib_windows=4), progress=False,
                    final_eval=False))
    return str(out)


def _tradeoff_flags(tmp_path, head: str, run: str) -> list[str]:
    """Tiny tradeoff flags: press_button, one 2-step setting per head against a reference at N = 3, 8 windows,
    2 episodes of 8 control steps."""
    return ["--tasks", "press_button", "--heads", head, "--diffusion-settings", "ddim:2", "--diffusion-reference",
            "ddim:2", "--flow-settings", "euler:1", "--flow-reference", "euler:2", "--reference-n", "3", "--windows",
            "8", "--window-batch", "8", "--episodes", "2", "--max-steps", "8", "--repeats", "2", "--row-budget-s", "1",
            "--out-dir", str(tmp_path / "out"), "--runs", f"press_button:{head}:{run}"]


def _tradeoff_row_ok(r: dict, closed_loop: bool):
    _finite(r, ["num_steps", "num_samples", "latency_ms", "latency_p90_ms", "agreement", "spearman",
                "batched_decision_s"])
    assert 0.0 <= r["agreement"] <= 1.0 and -1.0 <= r["spearman"] <= 1.0
    assert r["thresholds"][0] == -math.inf and r["thresholds"][-1] == math.inf
    if closed_loop:
        assert r["closed_loop"] == "run"
        _finite(r, ["success_rate", "mean_steps_all"])
        assert r["mean_steps"] is None or math.isfinite(r["mean_steps"])  # null when no episode succeeded
    else:
        assert r["success_rate"] is None and r["mean_steps"] is None
        assert r["closed_loop"].startswith("not run: batched decision ~") and r["closed_loop"].endswith("> 1e-09 s")


@pytest.mark.slow
def test_tradeoff_benchmark(tmp_path):
    """A tiny diffusion run, N = 2 and N = 3 (the reference setting): latency and open loop measured, the closed
    loops skipped by a tiny --closed-loop-limit-s (null success); a second call resumes every row as is."""
    flags = ["--ns", "2", "3", "--closed-loop-limit-s", "1e-9",
             *_tradeoff_flags(tmp_path, "diffusion", _tiny_run(tmp_path, "diffusion"))]
    tradeoff.main(flags)
    res = _load(tmp_path / "out", "tradeoff")
    rows = {r["num_samples"]: r for r in res["rows"]}
    assert sorted(rows) == [2, 3] and rows[2]["setting"] == "DDIM 2, N=2"
    for r in rows.values():
        assert set(tradeoff.REQUIRED_KEYS) <= set(r) and r["reference"] == "DDIM 2, N=3"
        _tradeoff_row_ok(r, closed_loop=False)
    assert rows[3]["agreement"] == 1.0 and rows[3]["spearman"] == pytest.approx(1.0)  # the reference itself
    assert (tmp_path / "out" / res["png"]).exists() and res["cheapest_within_3_points"] is None

    tradeoff.main(flags)
    assert _load(tmp_path / "out", "tradeoff")["rows"] == res["rows"]  # resumed: nothing re-measured


@pytest.mark.slow
def test_tradeoff_benchmark_closed_loop(tmp_path):
    """Tiny diffusion and flow runs: one setting each with its closed loop run (one rollout compile each)."""
    for head in ("diffusion", "flow"):
        tradeoff.main(["--ns", "2", *_tradeoff_flags(tmp_path, head, _tiny_run(tmp_path, head))])
    rows = {r["head"]: r for r in _load(tmp_path / "out", "tradeoff")["rows"]}
    assert [(rows[h]["setting"], rows[h]["reference"]) for h in ("diffusion", "flow")] == [
        ("DDIM 2, N=2", "DDIM 2, N=3"), ("Euler 1, N=2", "Euler 2, N=3")]
    for r in rows.values():
        _tradeoff_row_ok(r, closed_loop=True)


def test_tradeoff_cheapest_and_spearman():
    import numpy as np

    def row(task, head, sampler, steps, n, latency, success):
        return {"task": task, "head": head, "sampler": sampler, "num_steps": steps, "num_samples": n,
                "setting": f"{sampler} {steps}, N={n}", "latency_ms": latency, "success_rate": success}

    tasks = ["press_button", "latch_door"]
    rows = [row(t, "diffusion", "ddim", 10, 16, 100.0, 0.8) for t in tasks]
    rows += [row(t, "diffusion", "ddpm", 100, 100, 5000.0, 0.9) for t in tasks]
    rows += [row("press_button", "flow", "euler", 1, 4, 5.0, 0.9), row("latch_door", "flow", "euler", 1, 4, 5.0, 0.7)]
    rows += [row(t, "flow", "euler", 2, 4, 10.0, 0.78) for t in tasks]  # within 3 points on both
    rows += [row(t, "flow", "euler", 1, 16, 1.0, None) for t in tasks]  # closed loop not run
    best = tradeoff.cheapest_within(rows, tasks)
    assert (best["head"], best["sampler"], best["num_steps"], best["num_samples"]) == ("flow", "euler", 2, 4)
    assert best["latency_ratio_to_base"] == pytest.approx(0.1) and best["latency_ratio_to_top"] == pytest.approx(0.002)
    assert tradeoff.cheapest_within(rows[2:], tasks) is None  # no DDIM 10, N=16

    a = np.array([3.0, 1.0, 2.0, 2.0, 5.0])
    np.testing.assert_allclose(tradeoff.average_ranks(a), [4.0, 1.0, 2.5, 2.5, 5.0])
    assert tradeoff.spearman(a, a) == pytest.approx(1.0) and tradeoff.spearman(a, -a) == pytest.approx(-1.0)
    assert math.isnan(tradeoff.spearman(a, np.ones(5)))


@pytest.mark.parametrize("module", [sampling, train_step, rollout, optimisation, convolutions, tradeoff, "delay",
                                    "serving", "profile", "studies.checkpoint_load"])
def test_benchmark_flags_parse(module):
    if isinstance(module, str):
        import importlib
        module = importlib.import_module(f"benchmarks.{module}")
    assert module.parse_args([]).out_dir is None


def test_precision_benchmark_needs_checkpoints(capsys):
    from benchmarks.studies import precision

    assert precision.parse_args(["--checkpoints", "a", "b"]).checkpoints == ["a", "b"]
    with pytest.raises(SystemExit):
        precision.parse_args([])
    assert "--checkpoints" in capsys.readouterr().err


# ------------------------------------------------------------------ the optimisations the benchmarks measured
def test_fast_mish_matches_jax_mish():
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hipolicy_jax.models.unet import mish

    x = jnp.linspace(-60.0, 60.0, 20001)
    np.testing.assert_allclose(mish(x), jax.nn.mish(x), rtol=1e-5, atol=5e-6)
    g = jax.vmap(jax.grad(mish))(x)
    np.testing.assert_allclose(g, jax.vmap(jax.grad(jax.nn.mish))(x), rtol=1e-4, atol=1e-5)


def test_precomputed_film_equals_per_step_film():
    """denoise_film with film_condition / film_steps equals denoise; the split FiLM head equals the concatenated
    Dense(mish([step ⊕ cond])) of the same parameters (the tree is unchanged: film/kernel (d+Dc, 2C))."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from benchmarks.common import make_bench_policy
    from hipolicy_jax.models.unet import FiLMHead, FiLMInput

    p = make_bench_policy("tiny", "state")
    net, params = p.net, p.params
    cond = net.apply(params, p.normalizer.normalize_obs(p.obs), method=net.encode)
    x = jax.random.normal(jax.random.key(0), (1, p.cfg.chunk.horizon, net.action_dim))
    for t in (57,):
        ref = net.apply(params, x, jnp.array([t]), cond, method=net.denoise)
        step = jax.tree.map(lambda a: a[0], net.apply(params, jnp.array([t]), method=net.film_steps))
        out = net.apply(params, x, step, net.apply(params, cond, method=net.film_condition), method=net.denoise_film)
        np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)

    film = params["params"]["unet"]["down0_res0"]["film"]
    d = p.cfg.model.unet_step_embed
    step = jax.random.normal(jax.random.key(1), (2, d))
    c = jax.random.normal(jax.random.key(2), (2, 3, film["kernel"].shape[0] - d))
    head = FiLMHead(film["kernel"].shape[1])
    concat = jnp.concatenate([jnp.broadcast_to(step[:, None], (2, 3, d)), c], axis=-1)
    np.testing.assert_allclose(head.apply({"params": film}, FiLMInput(step, c)),
                               head.apply({"params": film}, concat), rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_delay_benchmark(tmp_path):
    """Asynchronous execution rows of a tiny run: synchronous, then d = 1 with both hand-overs; a rerun resumes."""
    from benchmarks import delay
    run = _tiny_run(tmp_path, "diffusion")
    flags = ["--runs", f"press_button:tiny:{run}", "--delays", "0", "1", "--episodes", "2", "--max-steps", "12",
             "--out-dir", str(tmp_path / "out")]
    out = delay.main(flags)
    rows = out["rows"]
    assert [(r["delay"], r["handover"]) for r in rows] == [(0, "sync"), (1, "inpaint"), (1, "naive")]
    for r in rows:
        assert 0.0 <= r["success_rate"] <= 1.0 and len(r["success"]) == 2 and r["mean_decisions"] >= 1
    sync, delayed = rows[0], rows[1]
    assert sync["mean_actions_per_decision"] <= 8 and delayed["mean_actions_per_decision"] <= 7  # L_c − d
    assert os.path.exists(out["png"])
    again = delay.main(flags)
    assert [r["eval_s"] for r in again["rows"]] == [r["eval_s"] for r in rows]  # resumed, not re-run


@pytest.mark.slow
def test_serving_benchmark(tmp_path):
    """The serving benchmark on a tiny run: three single-call paths and a small load test, all replies received."""
    from benchmarks import serving
    run = _tiny_run(tmp_path, "diffusion")
    out = serving.main(["--run", run, "--calls", "2", "--clients", "2", "--requests", "5", "--rounds", "1",
                        "--out-dir", str(tmp_path / "out")])
    assert [r["path"] for r in out["rows"]] == ["in-process (jit)", "exported program", "websocket round trip"]
    for r in out["rows"]:
        _finite(r, ["median_ms", "p90_ms", "ratio_to_in_process"])
    assert out["load"]["replies"] == 10 and out["load"]["failures"] == 0  # 2 clients × 5 requests, one round


def test_report_serving_section_reads_the_json():
    """PERFORMANCE.md's serving section: every figure of its prose from the serving JSON (here the committed one)."""
    from benchmarks import report
    from benchmarks.common import RESULTS_DIR

    path = os.path.join(RESULTS_DIR, "serving_cpu.json")
    if not os.path.exists(path):
        pytest.skip("no committed serving result")
    res = jsonio.load(path)
    note, t = report.serving_note(res), res["targets"]
    assert f"{t['throughput_ratio']:.2f}x one client (median of {len(t['throughput_ratio_by_round'])} rounds" in note
    assert f"{res['load']['requests_per_s']:.1f} requests/s with batching" in note
    assert f"decides {t['best_batch_throughput_x']:.2f}x the rows/s of batch 1" in note
    assert f"compute-bound on {res['cpu_count']} cores" in note and "\n\n- **One decision**" in note
    section = report.render("cpu", results_dir=RESULTS_DIR).split("### Policy serving")[1]
    assert note in section and res["table_md"] in section


def test_pytorch_comparison_shapes():
    """``--shapes``: dp-lowdim is Diffusion Policy's low-dim U-Net to the parameter; the HiPolicy shape predicts
    T = 24 steps of A = 14 with and without fusion (fusion only adds parameters)."""
    import argparse

    import jax
    import jax.numpy as jnp

    from benchmarks.common import SHAPES, bench_config, bench_models
    from hipolicy_jax.models.policy_net import init_policy_params, param_count

    models = bench_models(argparse.Namespace(shapes=["dp-lowdim", "hipolicy", "hipolicy-nofusion"]))
    counts = {}
    for m in models:
        cfg = bench_config("paper", "state", **m.changes)
        obs = {"state": jnp.zeros((1, cfg.chunk.num_freqs, cfg.chunk.obs_horizon, m.state_dim))}
        counts[m.size] = param_count(jax.eval_shape(lambda: init_policy_params(cfg, m.action_dim, obs,
                                                                              jax.random.key(0))))
        assert m.obs == "state" and (m.state_dim, m.action_dim) == SHAPES[m.size][1:]
    assert counts["dp-lowdim"] == 65_783_298
    assert bench_config("paper", "state", **SHAPES["hipolicy"][0]).chunk.horizon == 24
    assert counts["hipolicy"] > counts["hipolicy-nofusion"]
    grid = bench_models(argparse.Namespace(shapes=None, sizes=["tiny"], obs=["state", "image"]))
    assert [(m.size, m.obs) for m in grid] == [("tiny", "state"), ("tiny", "image")]


def test_profile_classifies_ops_by_model_part():
    """The profiler's grouping: module path and opcodes -> (part, pass)."""
    from benchmarks.profile import classify

    fwd = "jit(step)/jvp(PolicyNet.denoise)/unet/down0_res0/"
    bwd = "jit(step)/transpose(jvp(PolicyNet.denoise))/unet/mid_res1/"
    assert classify(fwd + "block0/conv/conv_general_dilated", {"convolution"}) == ("convolution", "forward")
    assert classify(bwd + "block1/norm/reduce_sum", {"reduce", "add"}) == ("GroupNorm", "backward")
    assert classify(fwd + "block0/exp", {"exponential", "multiply"}) == ("Mish", "forward")
    assert classify(fwd + "film/dot_general", {"dot"}) == ("FiLM", "forward")
    assert classify(fwd + "mul", {"multiply", "add"}) == ("FiLM", "forward")  # the per-segment scale and bias
    assert classify(fwd + "fusion/attention/key/dot_general", {"dot"}) == ("fusion attention", "forward")
    assert classify("jit(step)/jvp(PolicyNet.denoise)/unet/up0_upsample/conv_general_dilated",
                    {"convolution"}) == ("up-sampling conv", "forward")
    assert classify(bwd + "block0/conv/rev", {"parameter", "reverse", "transpose", "copy"})[0] == "layout"
    assert classify("jit(step)/mul", {"multiply", "add", "sqrt", "divide"}) == ("optimizer + EMA", "update")
    assert classify("jit(step)/jvp(jit(_normal))/erf_inv", {"multiply"})[0] == "loss + noise"
    assert classify("jit(sample)/vmap()/while/body/mul", {"multiply"}, "sample")[0] == "sampler update + noise"


def test_profile_benchmark(tmp_path):
    """A traced sampler call and train step of the tiny model: the parts add up to the operation total, the
    convolutions and the optimizer are found, and every part is a known one."""
    from benchmarks import profile

    res = profile.main(["--quick", "--out-dir", str(tmp_path)])
    assert _load(tmp_path, "profile")["rows"] == jsonio.loads(jsonio.dumps(res["rows"]))
    by = {r["workload"]: r for r in res["rows"]}
    assert set(by) == {"sample", "train"}
    for r in res["rows"]:
        _finite(r, ["wall_ms", "total_op_ms"])
        assert set(r["parts_ms"]) <= set(profile.PARTS)
        assert math.isclose(sum(r["parts_ms"].values()), r["total_op_ms"], rel_tol=1e-9)
        assert r["parts_ms"].get("convolution", 0) > 0
    assert by["train"]["parts_ms"].get("optimizer + EMA", 0) > 0 and "optimizer + EMA" not in by["sample"]["parts_ms"]
    assert any(k.endswith("(backward)") for k in by["train"]["passes_ms"])


@pytest.mark.slow
def test_compute_dtype_benchmark(tmp_path):
    """The interleaved before / after: three train-step variants with the same loss, two sampler variants whose
    samples differ by bf16 rounding only."""
    from benchmarks.studies import compute_dtype

    res = compute_dtype.main(["--quick", "--out-dir", str(tmp_path)])
    rows = _load(tmp_path, "compute_dtype")["rows"]
    assert [(r["workload"], r["variant"]) for r in rows] == [
        ("train", "where guard"), ("train", "float32"), ("train", "bfloat16"), ("sample", "float32"),
        ("sample", "bfloat16")]
    train = [r for r in res["rows"] if r["workload"] == "train"]
    assert train[0]["loss"] == pytest.approx(train[1]["loss"], rel=1e-5)  # the guard changes no number
    assert train[2]["loss"] == pytest.approx(train[1]["loss"], rel=2e-2)
    diffs = [r["max_abs_diff_to_float32"] for r in res["rows"] if r["workload"] == "sample"]
    assert diffs[0] == 0 and 0 < diffs[1] < 0.1
    for r in rows:
        _finite(r, ["median_s", "speedup"])
        assert len(r["times_s"]) == r["rounds"] == 2


def test_small_matmul_benchmark(tmp_path):
    small_matmul.main(["--rows", "4", "--dtypes", "bfloat16", "--variants", "xla default", "--repeats", "1",
                       "--out-dir", str(tmp_path)])
    res = _load(tmp_path, "small_matmul")
    assert len(res["rows"]) == 2 * len(small_matmul.SHAPES)  # two layouts per weight shape
    for row in res["rows"]:
        _finite(row, ["ms", "weight_gbs", "fraction_of_bandwidth"])
        assert row["weight_mb"] == row["k"] * row["n"] * 2 / 2**20 and row["m"] == 4
    assert res["best"][0]["dtype"] == "bfloat16" and res["bandwidth_gbs"]["xla default"] > 0
