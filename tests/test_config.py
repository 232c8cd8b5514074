"""Config validation: every bad value raises ValueError naming its field; derived values; CLI overrides."""

import dataclasses
import math

import pytest

from hipolicy_jax.checkpoint import config_from_dict, config_to_dict
from hipolicy_jax.config import (ChunkConfig, DiffusionConfig, EncoderConfig, EvalConfig, FlowConfig,
                                 InferenceConfig, ModelConfig, PolicyConfig, TrainConfig, replace)


@pytest.mark.parametrize("make,field", [
    (lambda: ChunkConfig(strides=(2, 1)), "chunk.strides"),
    (lambda: ChunkConfig(strides=(1, 1)), "chunk.strides"),
    (lambda: ChunkConfig(strides=(0, 1)), "chunk.strides"),
    (lambda: ChunkConfig(strides=()), "chunk.strides"),
    (lambda: ChunkConfig(obs_horizon=0), "chunk.obs_horizon"),
    (lambda: ChunkConfig(chunk_len=0), "chunk.chunk_len"),
    (lambda: ChunkConfig(action_offset=2), "chunk.action_offset"),
    (lambda: EncoderConfig(obs_type="rgbd"), "encoder.obs_type"),
    (lambda: EncoderConfig(crop_size=100), "encoder.crop_size"),
    (lambda: EncoderConfig(point_dims=4), "encoder.point_dims"),
    (lambda: ModelConfig(size="huge"), "model.size"),
    (lambda: ModelConfig(condition="mid"), "model.condition"),
    (lambda: ModelConfig(down_dims=(60, 128)), "model.down_dims"),
    (lambda: ModelConfig(kernel_size=4), "model.kernel_size"),
    (lambda: DiffusionConfig(prediction_type="v"), "diffusion.prediction_type"),
    (lambda: DiffusionConfig(beta_schedule="cosine"), "diffusion.beta_schedule"),
    (lambda: FlowConfig(time_sampling="logit"), "flow.time_sampling"),
    (lambda: FlowConfig(time_scale=0.0), "flow.time_scale"),
    (lambda: InferenceConfig(num_samples=0), "inference.num_samples"),
    (lambda: InferenceConfig(thresholds=(0.0, -1.0)), "inference.thresholds"),
    (lambda: InferenceConfig(percentiles=(70.0, 10.0)), "inference.percentiles"),
    (lambda: InferenceConfig(percentiles=(0.0, 50.0)), "inference.percentiles"),
    (lambda: InferenceConfig(sampler="heun"), "inference.sampler"),
    (lambda: InferenceConfig(num_steps=0), "inference.num_steps"),
    (lambda: InferenceConfig(calib_windows=0), "inference.calib_windows"),
    (lambda: EvalConfig(episodes=0), "eval.episodes"),
    (lambda: PolicyConfig(objective="score"), "policy.objective"),
    (lambda: TrainConfig(batch_size=0), "train.batch_size"),
    (lambda: TrainConfig(betas=(0.9, 1.0)), "train.betas"),
    (lambda: PolicyConfig(chunk=ChunkConfig(chunk_len=6)), "chunk.chunk_len"),  # 6 % 4 (three U-Net levels)
    (lambda: PolicyConfig(model=ModelConfig(fusion_heads=7)), "model.fusion_heads"),
])
def test_bad_values_name_their_field(make, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        make()


def test_derived_values_for_the_release_windowing():
    c = ChunkConfig()
    assert c.num_freqs == 3 and c.segment_strides == (3, 2, 1) and c.horizon == 24
    assert c.obs_span == 7  # frames 0..6: long [0,3,6], mid [2,4,6], short [4,5,6]
    assert c.action_span == 1 + 7 * 3 + 1  # a[t+1] .. a[t+22]
    assert ModelConfig(size="paper").unet_dims == (256, 512, 1024) and ModelConfig(size="paper").unet_kernel == 5
    assert ModelConfig().downsample_factor == 4


def test_inference_settings_are_not_part_of_the_policy():
    """Thresholds are checked against M where they are used (``calibration.resolve_thresholds``), so one
    ``InferenceConfig`` serves policies of any M; only the sampler settings key a compile."""
    from hipolicy_jax.evaluation.calibration import resolve_thresholds

    inf = InferenceConfig(thresholds=(-math.inf, -6.0, -5.5, math.inf), percentiles=(20.0, 80.0), calib_windows=7)
    assert "sampling" not in {f.name for f in dataclasses.fields(PolicyConfig)}
    assert resolve_thresholds(inf, 3, None) == ((-math.inf, -6.0, -5.5, math.inf), "inference.thresholds")
    assert resolve_thresholds(InferenceConfig(thresholds=(-6.0, -5.5)), 3, None)[0] == (-math.inf, -6.0, -5.5,
                                                                                        math.inf)
    with pytest.raises(ValueError, match=r"inference.thresholds: need M\+1=2"):
        resolve_thresholds(inf, 1, None)
    assert resolve_thresholds(InferenceConfig(), 1, None)[0] == (-math.inf, math.inf)
    with pytest.raises(FileNotFoundError, match="calibration.json"):
        resolve_thresholds(InferenceConfig(), 3, None)
    assert inf.sampler_settings() == InferenceConfig(num_samples=inf.num_samples)


def test_configs_are_frozen_and_replace_takes_dotted_keys():
    cfg = PolicyConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.chunk.strides = (1,)  # type: ignore[misc]
    new = replace(cfg, **{"chunk.strides": (1, 2), "model.fusion": False})
    assert new.chunk.strides == (1, 2) and not new.model.fusion and cfg.chunk.strides == (1, 2, 3)


def test_dict_round_trip():
    cfg = PolicyConfig(chunk=ChunkConfig(strides=(1, 4)), objective="flow", flow=FlowConfig(time_sampling="beta"))
    assert config_from_dict(PolicyConfig, config_to_dict(cfg)) == cfg
    inf = InferenceConfig(thresholds=(-1.0, 0.0, 1.0), percentiles=(30.0,), sampler="ddpm")
    assert config_from_dict(InferenceConfig, config_to_dict(inf)) == inf


def test_a_delay_the_chunk_cannot_carry_fails_at_config_time():
    """`experiments.train --inference.delay 7` with chunk length 8 fails when the config is built, naming the field
    (a decision must be ready before the next one starts: d <= L_c // 2), through the CLI too."""
    import subprocess
    import sys

    from hipolicy_jax.config import InferenceConfig
    from hipolicy_jax.runs.train import RunConfig

    assert RunConfig(inference=InferenceConfig(delay=4)).inference.delay == 4  # L_c 8: up to 4
    with pytest.raises(ValueError, match=r"inference.delay: at most chunk.chunk_len // 2 = 4 .* got 7"):
        RunConfig(inference=InferenceConfig(delay=7))
    out = subprocess.run([sys.executable, "-m", "experiments.train", "--inference.delay", "7", "--dry-run"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "inference.delay: at most chunk.chunk_len // 2 = 4" in out.stderr
    assert "Traceback" not in out.stderr
