"""The diffusion head: schedules and reverse steps against closed forms and against diffusers' update rules."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax.config import DiffusionConfig, InferenceConfig
from hipolicy_jax.heads import diffusion


def test_squaredcos_betas_match_formula():
    cfg = DiffusionConfig()
    betas = diffusion.make_betas(cfg)
    f = lambda t: np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2  # noqa: E731
    assert betas.shape == (100,)
    assert betas[0] == np.float32(1 - f(0.01) / f(0.0))  # rounded to float32, as diffusers stores it
    assert betas[-1] == pytest.approx(0.999)  # capped
    assert np.all(np.diff(betas) > 0)
    ab = diffusion.alphas_cumprod(cfg)
    assert ab[0] > 0.999 and ab[-1] < 1e-3


def test_linear_schedule_endpoints():
    betas = diffusion.make_betas(DiffusionConfig(beta_schedule="linear", num_train_steps=10))
    np.testing.assert_allclose(betas[[0, -1]], [1e-4, 0.02])


@pytest.mark.parametrize("sampler,steps", [("ddpm", 100), ("ddim", 10), ("ddim", 100), ("ddim-clipped", 10)])
def test_table_timesteps_and_final_step_is_clean(sampler, steps):
    tab = diffusion.reverse_table(DiffusionConfig(), sampler, steps)
    t = np.asarray(tab.time)
    assert t.shape == (steps,) and t[-1] == 0 and np.all(np.diff(t) < 0)
    if sampler == "ddim" and steps == 10:
        np.testing.assert_array_equal(t, np.arange(90, -1, -10))
    # At the last step ᾱ_prev = 1: x_prev = x0 exactly, no noise.
    assert float(tab.sigma[-1]) == 0.0
    # 1 in exact arithmetic; diffusers' float32 ᾱ_0 makes DDPM's last step β_0/(1-ᾱ_0) = 1 + 1.4e-5, which a ported
    # Diffusion Policy checkpoint was sampled with (tests/test_porting.py), so the table keeps it
    np.testing.assert_allclose(float(tab.c_x0[-1]), 1.0, rtol=1e-5 if sampler != "ddpm" else 2e-5)
    assert abs(float(tab.c_xt[-1])) < 1e-6 and abs(float(tab.c_eps[-1])) < 1e-6 and abs(float(tab.c_eps_c[-1])) < 1e-6


def test_sampler_resolution_and_its_errors():
    cfg = DiffusionConfig()
    assert diffusion.resolve_sampler(cfg, InferenceConfig()) == ("ddim", 10)  # auto
    assert diffusion.resolve_sampler(cfg, InferenceConfig(sampler="ddpm")) == ("ddpm", 100)
    assert diffusion.resolve_sampler(cfg, InferenceConfig(sampler="ddim", num_steps=4)) == ("ddim", 4)
    with pytest.raises(ValueError, match=r"inference.num_steps: DDPM denoises through all 100"):
        diffusion.resolve_sampler(cfg, InferenceConfig(sampler="ddpm", num_steps=10))
    with pytest.raises(ValueError, match=r"inference.num_steps: DDIM takes 1 to 100"):
        diffusion.resolve_sampler(cfg, InferenceConfig(sampler="ddim", num_steps=200))
    with pytest.raises(ValueError, match=r"inference.sampler: the diffusion head samples with .*'euler'"):
        diffusion.resolve_sampler(cfg, InferenceConfig(sampler="euler"))
    with pytest.raises(ValueError, match="inference.num_steps"):
        diffusion.reverse_table(cfg, "ddpm", 10)


def _diffusers_ddim_step(ab: np.ndarray, t: int, prev: int, eps_model: np.ndarray, x_t: np.ndarray, prediction: str,
                         clip: bool, use_clipped_model_output: bool) -> np.ndarray:
    """diffusers' ``DDIMScheduler.step`` (η = 0, set_alpha_to_one) written out in NumPy, float64."""
    a_t = ab[t]
    a_prev = ab[prev] if prev >= 0 else 1.0
    if prediction == "epsilon":
        x0 = (x_t - np.sqrt(1 - a_t) * eps_model) / np.sqrt(a_t)
        eps = eps_model
    else:
        x0 = eps_model
        eps = (x_t - np.sqrt(a_t) * x0) / np.sqrt(1 - a_t)
    if clip:
        x0 = np.clip(x0, -1.0, 1.0)
    if use_clipped_model_output:
        eps = (x_t - np.sqrt(a_t) * x0) / np.sqrt(1 - a_t)
    return np.sqrt(a_prev) * x0 + np.sqrt(1 - a_prev) * eps


@pytest.mark.parametrize("prediction", ["epsilon", "sample"])
@pytest.mark.parametrize("sampler", ["ddim", "ddim-clipped"])
def test_ddim_step_matches_diffusers(prediction, sampler):
    """Fixed model output, x_t and t: our DDIM update equals diffusers' to 1e-5 (default
    ``use_clipped_model_output=False`` for 'ddim', True for 'ddim-clipped'), with the clip active."""
    cfg = DiffusionConfig(prediction_type=prediction)
    ab = diffusion.alphas_cumprod(cfg)
    tab = diffusion.reverse_table(cfg, sampler, 10)
    rng = np.random.default_rng(0)
    x_t = 2.0 * rng.standard_normal((4, 24, 3))  # large enough that the predicted clean sample gets clipped
    out = 1.5 * rng.standard_normal((4, 24, 3))
    steps = np.asarray(tab.time)
    for i, t in enumerate(steps):
        row = jax.tree.map(lambda a: a[i], tab)
        ours = np.asarray(diffusion.reverse_step(cfg, row, jnp.asarray(x_t, jnp.float32), jnp.asarray(out, jnp.float32),
                                                 None))
        ref = _diffusers_ddim_step(ab, int(t), int(t) - 10, out, x_t, prediction, True, sampler == "ddim-clipped")
        np.testing.assert_allclose(ours, ref, atol=1e-5, rtol=1e-5)
    # the two forms differ where the clip is active (here by far more than the tolerance)
    row = jax.tree.map(lambda a: a[0], tab)
    a = _diffusers_ddim_step(ab, int(steps[0]), int(steps[0]) - 10, out, x_t, prediction, True, False)
    b = _diffusers_ddim_step(ab, int(steps[0]), int(steps[0]) - 10, out, x_t, prediction, True, True)
    assert np.abs(a - b).max() > 0.1


def test_ddpm_step_matches_diffusers_posterior_mean():
    """DDPM with the noise term zeroed is diffusers' posterior mean of the clipped clean sample."""
    cfg = DiffusionConfig()
    ab = diffusion.alphas_cumprod(cfg)
    tab = diffusion.reverse_table(cfg, "ddpm", 100)
    rng = np.random.default_rng(1)
    x_t, eps = rng.standard_normal((2, 8, 2)), rng.standard_normal((2, 8, 2))
    for i in (0, 50, 98, 99):
        t = int(tab.time[i])
        a_t, a_prev = ab[t], (ab[t - 1] if t > 0 else 1.0)
        beta = 1 - a_t / a_prev
        x0 = np.clip((x_t - np.sqrt(1 - a_t) * eps) / np.sqrt(a_t), -1, 1)
        ref = (np.sqrt(a_prev) * beta / (1 - a_t)) * x0 + (np.sqrt(1 - beta) * (1 - a_prev) / (1 - a_t)) * x_t
        row = jax.tree.map(lambda a: a[i], tab)
        ours = diffusion.reverse_step(cfg, row, jnp.asarray(x_t, jnp.float32), jnp.asarray(eps, jnp.float32),
                                      jnp.zeros(x_t.shape, jnp.float32))
        np.testing.assert_allclose(np.asarray(ours), ref, atol=1e-5, rtol=1e-5)


def _run_chain(cfg, table, x, x0_fn, key):
    def body(x, inp):
        row, k = inp
        x0 = x0_fn(x, row)
        if cfg.prediction_type == "epsilon":
            out = (x - row.sqrt_ab * x0) / row.sqrt_1m_ab
        else:
            out = x0
        return diffusion.reverse_step(cfg, row, x, out, jax.random.normal(k, x.shape)), None

    keys = jax.random.split(key, table.time.shape[0])
    return jax.lax.scan(body, x, (table, keys))[0]


@pytest.mark.parametrize("prediction", ["epsilon", "sample"])
@pytest.mark.parametrize("sampler,steps", [("ddpm", 100), ("ddim", 10)])
def test_oracle_denoiser_recovers_point_mass(prediction, sampler, steps):
    cfg = DiffusionConfig(prediction_type=prediction)
    c = jnp.array([0.3, -0.7, 0.9])
    x = jax.random.normal(jax.random.key(0), (64, 3))
    out = _run_chain(cfg, diffusion.reverse_table(cfg, sampler, steps), x, lambda x, row: jnp.broadcast_to(c, x.shape),
                     jax.random.key(1))
    # DDPM's last step scales x0 by diffusers' float32 β_0/(1-ᾱ_0) = 1 + 1.4e-5 (see above)
    np.testing.assert_allclose(np.asarray(out), np.broadcast_to(np.asarray(c), (64, 3)),
                               atol=1e-5 if sampler != "ddpm" else 2e-5)


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_oracle_denoiser_reproduces_gaussian_variance(sampler):
    """Data x0 ~ N(0, s²): the Bayes-optimal E[x0|x_t] = sqrt(ᾱ)s²/(ᾱs²+1-ᾱ)·x_t; fine chains end at std s.

    (With 100 steps both land ~4% low — discretisation and the fixed-small variance — so use K = 1000.)
    """
    s = 0.4
    cfg = DiffusionConfig(prediction_type="sample", clip_sample=False, num_train_steps=1000)

    def x0_fn(x, row):
        ab = row.sqrt_ab ** 2
        return row.sqrt_ab * s ** 2 / (ab * s ** 2 + 1 - ab) * x

    x = jax.random.normal(jax.random.key(0), (20000, 1))
    out = np.asarray(_run_chain(cfg, diffusion.reverse_table(cfg, sampler, 1000), x, x0_fn, jax.random.key(1)))
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
