"""``benchmarks.roofline``: the stage programs, their cost analysis, the roofline bound and the hand FLOP count.

Nothing here asserts a timing; the figures live in ``benchmarks/results/roofline_cpu.json``.
"""

import math

import jax
import numpy as np
import pytest

from benchmarks import roofline
from benchmarks.common import ACTION_DIM, STATE_DIM, BenchModel, bench_config
from benchmarks.machine import PEAKS_ENV


def test_roofline_bound_closed_form():
    peaks = {"matmul_f32_gflops": 100.0, "bandwidth_gbs": 10.0}
    assert roofline.roofline_s(2e9, 1e8, peaks) == (pytest.approx(0.02), "compute")  # 20 ms of FLOPs, 10 ms of bytes
    assert roofline.roofline_s(1e9, 1e9, peaks) == (pytest.approx(0.1), "memory")


@pytest.mark.parametrize("strides, frames", [((1,), 3), ((1, 2, 3), 6)])
def test_pointnet_flops_by_hand(strides, frames):
    """DP's window (L_h 3, one stride) holds 3 distinct frames, HiPolicy's (strides 1/2/3) 6 of its 9 positions."""
    cfg = bench_config("cpu", "pointcloud", **{"chunk.strides": strides, "encoder.num_points": 4})
    got = roofline.pointnet_matmul_flops(cfg, batch=2)
    per_point = 3 * 64 + 64 * 128 + 128 * 256  # 41,152 multiply-adds
    points = 2 * frames * 4
    forward = 2 * (points * per_point + 2 * frames * 256 * cfg.encoder.point_out)
    assert got["distinct_frames"] == frames and got["points"] == points
    assert got["forward"] == forward
    assert got["forward_backward"] == 3 * forward - 2 * points * 3 * 64


def test_stages_are_the_train_step():
    """The stage programs compute the real step's pieces: encoder + denoiser gradients sum to the step's gradient
    (the condition's cotangent carried from one to the other), and the update stage is the step's update."""
    model = BenchModel("tiny", "pointcloud", {}, STATE_DIM, ACTION_DIM)
    policy = model.policy(**{"encoder.num_points": 16})
    stages = roofline.Stages(policy, batch_size=4)
    params, obs, action = policy.params, stages.batch["obs"], stages.batch["action"]
    key = jax.random.fold_in(stages.key, 0)  # the step's key at step 0
    k_crop, k_head = jax.random.split(key)
    enc = jax.jit(lambda p, c: jax.vjp(lambda q: policy.net.apply(q, obs, train=True, method=policy.net.encode,
                                                                  rngs={"crop": k_crop}), p)[1](c)[0])
    cond = policy.net.apply(params, obs, train=True, method=policy.net.encode, rngs={"crop": k_crop})
    fn = stages._programs["denoiser forward + backward"][0]
    loss, (g_unet, g_cond) = fn(params, cond, action, k_head)
    grads = jax.tree.map(lambda a, b: a + b, g_unet, enc(params, g_cond))
    state, metrics = stages._programs["train step"][0](stages.holder["step"], stages.batch, stages.key)
    np.testing.assert_allclose(float(metrics["loss"]), float(loss), rtol=1e-5)
    norm = math.sqrt(sum(float(np.sum(np.square(g))) for g in jax.tree.leaves(grads)))
    np.testing.assert_allclose(float(metrics["grad_norm"]), norm, rtol=1e-4)


@pytest.mark.slow  # ~90 s: four tiny rows, every stage compiled
def test_roofline_quick_run(tmp_path, monkeypatch):
    """The smoke grid (tiny, 64 points, batch 8, DP and HiPolicy, point cloud and image): every stage's cost, time
    and bound are finite, XLA counts at least the PointNet's matmuls, and the trace finds the step's operations."""
    monkeypatch.setenv(PEAKS_ENV, "0")
    res = roofline.main(["--quick", "--out-dir", str(tmp_path)])
    rows = res["rows"]
    assert [(r["method"], r["obs"], r["points"], r["batch"]) for r in rows] == [
        ("dp", "pointcloud", 64, 8), ("hipolicy", "pointcloud", 64, 8), ("dp", "image", None, 8),
        ("hipolicy", "image", None, 8)]
    for r in rows:
        assert set(r["stages"]) == set(roofline.STAGES)
        for name, s in r["stages"].items():
            for k in ("median_s", "flops", "bytes", "roofline_s", "x_roofline", "gflops"):
                assert math.isfinite(s[k]) and s[k] > 0, (name, k, s[k])
            assert s["bound"] in ("compute", "memory")
        st = r["stages"]
        # the step does at least what its encoder's and denoiser's gradient programs do (up to XLA's rewrites)
        assert st["train step"]["flops"] >= 0.9 * (st["encoder forward + backward"]["flops"]
                                                   + st["denoiser forward + backward"]["flops"])
        assert st["encoder forward + backward"]["flops"] > st["encoder forward"]["flops"]
        assert r["profile"]["total_op_ms"] > 0 and r["profile"]["top_ops_ms"]
    for r in rows[:2]:  # the hand count is a lower bound of XLA's count of the whole encoder
        hand = r["pointnet_matmul_gflop"]
        assert r["stages"]["encoder forward"]["flops"] / 1e9 >= hand["forward"] * 0.99
        assert r["stages"]["encoder forward + backward"]["flops"] / 1e9 >= hand["forward_backward"] * 0.99
    assert rows[1]["pointnet_matmul_gflop"]["points"] == 2 * rows[0]["pointnet_matmul_gflop"]["points"]


def test_roofline_flags():
    assert roofline.parse_args([]).out_dir is None
    with pytest.raises(SystemExit):
        roofline.parse_args(["--batch", "0"])
