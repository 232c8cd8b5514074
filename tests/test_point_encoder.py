"""DP3's point-cloud encoder with its written-out backward pass (``models.encoders.point_trunk``) against the same
network written with flax's modules and autodiff: parameters, initial values, outputs and every gradient."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.studies.point_encoder import ModulePointCloudEncoder  # the reference: modules and autodiff
from hipolicy_jax.models.encoders import PointCloudEncoder, point_trunk


def _points(shape, seed=0):
    return jax.random.normal(jax.random.key(seed), shape)


def test_same_parameters_and_initial_values():
    points = _points((2, 3, 16, 3))
    new = PointCloudEncoder(32).init(jax.random.key(7), points)
    old = ModulePointCloudEncoder(32).init(jax.random.key(7), points)
    assert jax.tree.structure(new) == jax.tree.structure(old)
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(old)):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def _randomise(params, seed=3):
    """Non-trivial scales and shifts (the initial ones and zeros would hide a wrong LayerNorm gradient)."""
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    return jax.tree.unflatten(tree, [x + 0.3 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


@pytest.mark.parametrize("shape", [(4, 2, 64, 3), (5, 32, 6)])
def test_outputs_and_gradients_equal_autodiff(shape):
    points = _points(shape, seed=1)
    params = _randomise(PointCloudEncoder(16).init(jax.random.key(0), points))
    cot = jax.random.normal(jax.random.key(2), shape[:-2] + (16,))

    def grads(module):
        out, vjp = jax.vjp(lambda p, x: module.apply(p, x), params, points)
        return (out,) + vjp(cot)

    new, old = grads(PointCloudEncoder(16)), grads(ModulePointCloudEncoder(16))
    np.testing.assert_allclose(new[0], old[0], rtol=1e-5, atol=1e-5)  # outputs
    np.testing.assert_allclose(new[2], old[2], rtol=1e-4, atol=1e-5)  # the points' gradient
    for path, a in jax.tree_util.tree_leaves_with_path(new[1]):  # every parameter's gradient
        b = _at(old[1], path)
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-4 * float(jnp.max(jnp.abs(b))),
                                   err_msg=jax.tree_util.keystr(path))


def _at(tree, path):
    for k in path:
        tree = tree[k.key]
    return tree


def test_ties_at_the_maximum_share_the_gradient():
    """Every point of a cloud identical: all tie at every channel's maximum, and ``jnp.max`` splits the gradient
    evenly between them; so does ``point_trunk``'s backward pass."""
    one = _points((3, 1, 3), seed=4)
    points = jnp.repeat(one, 8, axis=1)  # (3, 8, 3): 8 equal points per cloud
    widths = (8, 16)
    keys = jax.random.split(jax.random.key(5), 4 * len(widths))
    layers, fan_in = [], 3
    for i, w in enumerate(widths):
        layers.append((jax.random.normal(keys[4 * i], (fan_in, w)), jax.random.normal(keys[4 * i + 1], (w,)),
                       1.0 + 0.2 * jax.random.normal(keys[4 * i + 2], (w,)), jax.random.normal(keys[4 * i + 3], (w,))))
        fan_in = w
    layers = tuple(layers)

    def reference(points, layers):
        a = points
        for kernel, bias, scale, shift in layers:
            y = a @ kernel + bias
            mean = y.mean(-1, keepdims=True)
            var = jnp.maximum((y * y).mean(-1, keepdims=True) - mean ** 2, 0.0)
            a = jax.nn.relu((y - mean) * (jax.lax.rsqrt(var + 1e-6) * scale) + shift)
        return jnp.max(a, axis=-2)

    cot = jax.random.normal(jax.random.key(6), (3, widths[-1]))
    got = jax.vjp(point_trunk, points, layers)[1](cot)
    want = jax.vjp(reference, points, layers)[1](cot)
    g_points = got[0]
    np.testing.assert_allclose(g_points, jnp.broadcast_to(g_points[:, :1], g_points.shape), rtol=1e-6)  # shared
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_trains_the_same():
    """Ten Adam steps on a regression target from both encoders end at the same parameters (float32 rounding)."""
    import optax

    points = _points((8, 32, 3), seed=8)
    target = jax.random.normal(jax.random.key(9), (8, 8))
    tx = optax.adam(1e-2)

    def run(module):
        params = module.init(jax.random.key(0), points)
        opt = tx.init(params)

        @jax.jit
        def step(params, opt):
            loss, g = jax.value_and_grad(lambda p: jnp.mean((module.apply(p, points) - target) ** 2))(params)
            updates, opt = tx.update(g, opt)
            return optax.apply_updates(params, updates), opt, loss

        losses = []
        for _ in range(10):
            params, opt, loss = step(params, opt)
            losses.append(float(loss))
        return params, losses

    (p_new, l_new), (p_old, l_old) = run(PointCloudEncoder(8)), run(ModulePointCloudEncoder(8))
    np.testing.assert_allclose(l_new, l_old, rtol=1e-4)
    assert l_new[-1] < 0.8 * l_new[0]  # it learns
    for a, b in zip(jax.tree.leaves(p_new), jax.tree.leaves(p_old)):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4)


@pytest.mark.slow  # the smoke run of the before / after study: four variants compiled twice, ~40 s
def test_point_encoder_study_quick(tmp_path, monkeypatch):
    from benchmarks.machine import PEAKS_ENV
    from benchmarks.studies import point_encoder

    monkeypatch.setenv(PEAKS_ENV, "0")
    res = point_encoder.main(["--quick", "--out-dir", str(tmp_path)])
    assert [(r["method"], r["points"]) for r in res["rows"]] == [("dp", 32), ("hipolicy", 32)]
    for r in res["rows"]:
        assert list(r["variants"]) == [point_encoder.label(*v) for v in point_encoder.VARIANTS]
        for v in r["variants"].values():
            assert v["median_s"] > 0 and math.isfinite(v["last_loss"]) and v["calls"] == 1
    traj = res["trajectory"]
    assert traj["steps"] == 3 and len(traj["loss_before"]) == len(traj["loss_after"]) == 3
    assert traj["max_rel_diff"] < 1e-4  # the same training, to float32 rounding
    assert (tmp_path / "point_encoder_cpu.json").exists()
