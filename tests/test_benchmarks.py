"""Smoke tests of the benchmark scripts: each ``main`` runs on a tiny config and writes finite JSON fields.

The figures themselves live in ``benchmarks/results``; nothing here asserts a timing.
"""

import json
import math

import pytest

from benchmarks import convolutions, optimisation, rollout, sampling, train_step


def _load(out_dir, name):
    files = list(out_dir.glob(f"{name}_*.json"))
    assert len(files) == 1, files
    return json.loads(files[0].read_text())


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


def test_convolutions_benchmark(tmp_path):
    """Both variants compile and agree (native vs im2col / polyphase) on the tiny U-Net at a short horizon."""
    convolutions.main(["--size", "tiny", "--configs", "DP L_c=8", "--batch", "4", "--num-samples", "2",
                       "--ddim-steps", "2", "--rounds", "2", "--out-dir", str(tmp_path)])
    rows = _load(tmp_path, "convolutions")["rows"]
    assert [r["kind"] for r in rows] == ["train", "sample"]
    for r in rows:
        _finite(r, ["native_median_s", "after_median_s", "speedup", "max_abs_diff"])
        assert r["max_abs_diff"] < 1e-4


@pytest.mark.parametrize("module", [sampling, train_step, rollout, optimisation, convolutions])
def test_benchmark_flags_parse(module):
    assert module.parse_args([]).out_dir is None


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
