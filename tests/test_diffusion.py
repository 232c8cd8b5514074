"""Diffusion schedules and reverse steps against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax import diffusion
from hipolicy_jax.config import DiffusionConfig


def test_squaredcos_betas_match_formula():
    cfg = DiffusionConfig()
    betas = diffusion.make_betas(cfg)
    f = lambda t: np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2  # noqa: E731
    assert betas.shape == (100,)
    np.testing.assert_allclose(betas[0], 1 - f(0.01) / f(0.0), rtol=1e-12)
    assert betas[-1] == pytest.approx(0.999)  # capped
    assert np.all(np.diff(betas) > 0)
    ab = diffusion.alphas_cumprod(cfg)
    assert ab[0] > 0.999 and ab[-1] < 1e-3


def test_linear_schedule_endpoints():
    betas = diffusion.make_betas(DiffusionConfig(beta_schedule="linear", num_train_steps=10, num_inference_steps=10))
    np.testing.assert_allclose(betas[[0, -1]], [1e-4, 0.02])


@pytest.mark.parametrize("sampler,steps", [("ddpm", 100), ("ddim", 10), ("ddim", 100)])
def test_table_timesteps_and_final_step_is_clean(sampler, steps):
    tab = diffusion.reverse_table(DiffusionConfig(), steps, sampler)
    t = np.asarray(tab.timesteps)
    assert t.shape == (steps,) and t[-1] == 0 and np.all(np.diff(t) < 0)
    if sampler == "ddim" and steps == 10:
        np.testing.assert_array_equal(t, np.arange(90, -1, -10))
    # At the last step ᾱ_prev = 1: x_prev = x0 exactly, no noise.
    assert float(tab.sigma[-1]) == 0.0
    np.testing.assert_allclose(float(tab.c_x0[-1]), 1.0, rtol=1e-5)
    assert abs(float(tab.c_xt[-1])) < 1e-6 and abs(float(tab.c_eps[-1])) < 1e-6


def test_ddpm_table_rejects_fewer_steps():
    with pytest.raises(ValueError, match="num_inference_steps"):
        diffusion.reverse_table(DiffusionConfig(), 10, "ddpm")


def test_config_requires_ddim_for_few_steps():
    with pytest.raises(ValueError, match="diffusion.num_inference_steps"):
        DiffusionConfig(num_inference_steps=10)
    DiffusionConfig(sampler="ddim", num_inference_steps=10)


def _run_chain(cfg, table, x, x0_fn, key):
    def body(x, inp):
        row, k = inp
        x0 = x0_fn(x, row)
        if cfg.prediction_type == "epsilon":
            out = (x - row.sqrt_ab * x0) / row.sqrt_1m_ab
        else:
            out = x0
        return diffusion.reverse_step(cfg, row, x, out, jax.random.normal(k, x.shape)), None

    keys = jax.random.split(key, table.timesteps.shape[0])
    return jax.lax.scan(body, x, (table, keys))[0]


@pytest.mark.parametrize("prediction", ["epsilon", "sample"])
@pytest.mark.parametrize("sampler,steps", [("ddpm", 100), ("ddim", 10)])
def test_oracle_denoiser_recovers_point_mass(prediction, sampler, steps):
    cfg = DiffusionConfig(prediction_type=prediction, sampler=sampler, num_inference_steps=steps)
    c = jnp.array([0.3, -0.7, 0.9])
    x = jax.random.normal(jax.random.key(0), (64, 3))
    out = _run_chain(cfg, diffusion.reverse_table(cfg), x, lambda x, row: jnp.broadcast_to(c, x.shape),
                     jax.random.key(1))
    np.testing.assert_allclose(np.asarray(out), np.broadcast_to(np.asarray(c), (64, 3)), atol=1e-5)


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_oracle_denoiser_reproduces_gaussian_variance(sampler):
    """Data x0 ~ N(0, s²): the Bayes-optimal E[x0|x_t] = sqrt(ᾱ)s²/(ᾱs²+1-ᾱ)·x_t; fine chains end at std s.

    (With 100 steps both land ~4% low — discretisation and the fixed-small variance — so use K = 1000.)
    """
    s = 0.4
    cfg = DiffusionConfig(prediction_type="sample", clip_sample=False, sampler=sampler, num_train_steps=1000,
                          num_inference_steps=1000)

    def x0_fn(x, row):
        ab = row.sqrt_ab ** 2
        return row.sqrt_ab * s ** 2 / (ab * s ** 2 + 1 - ab) * x

    x = jax.random.normal(jax.random.key(0), (20000, 1))
    out = np.asarray(_run_chain(cfg, diffusion.reverse_table(cfg), x, x0_fn, jax.random.key(1)))
    assert out.std() == pytest.approx(s, rel=0.015)
    assert abs(out.mean()) < 0.02


def test_add_noise_marginal_variance():
    cfg = DiffusionConfig()
    ab = diffusion.alphas_cumprod(cfg)
    x0 = jnp.full((4000, 1, 1), 0.5)
    noise = jax.random.normal(jax.random.key(0), x0.shape)
    t = jnp.full((4000,), 50)
    xt = np.asarray(diffusion.add_noise(cfg, x0, noise, t))
    assert xt.mean() == pytest.approx(np.sqrt(ab[50]) * 0.5, abs=0.03)
    assert xt.std() == pytest.approx(np.sqrt(1 - ab[50]), rel=0.05)
