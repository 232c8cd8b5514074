"""Config validation: every bad value raises ValueError naming its field; derived values; CLI overrides."""

import dataclasses
import math

import pytest

from hipolicy_jax.checkpoint import config_from_dict, config_to_dict
from hipolicy_jax.config import (ChunkConfig, DiffusionConfig, EncoderConfig, ModelConfig, PolicyConfig,
                                 SamplingConfig, TrainConfig, replace)


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
    (lambda: DiffusionConfig(num_inference_steps=10), "diffusion.num_inference_steps"),
    (lambda: DiffusionConfig(sampler="ddim", num_inference_steps=200), "diffusion.num_inference_steps"),
    (lambda: SamplingConfig(num_samples=0), "sampling.num_samples"),
    (lambda: SamplingConfig(thresholds=(0.0, -1.0)), "sampling.thresholds"),
    (lambda: TrainConfig(batch_size=0), "train.batch_size"),
    (lambda: TrainConfig(betas=(0.9, 1.0)), "train.betas"),
    (lambda: PolicyConfig(chunk=ChunkConfig(chunk_len=6)), "chunk.chunk_len"),  # 6 % 4 (three U-Net levels)
    (lambda: PolicyConfig(sampling=SamplingConfig(thresholds=(-1.0, 0.0, 1.0))), "sampling.thresholds"),  # M+1=4
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


def test_single_stride_with_any_thresholds_count_and_valid_thresholds():
    PolicyConfig(chunk=ChunkConfig(strides=(1,)), sampling=SamplingConfig(thresholds=(-math.inf, math.inf)))
    PolicyConfig(sampling=SamplingConfig(thresholds=(-math.inf, -6.0, -5.5, math.inf)))


def test_configs_are_frozen_and_replace_takes_dotted_keys():
    cfg = PolicyConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.chunk.strides = (1,)  # type: ignore[misc]
    new = replace(cfg, **{"chunk.strides": (1, 2), "model.fusion": False})
    assert new.chunk.strides == (1, 2) and not new.model.fusion and cfg.chunk.strides == (1, 2, 3)


def test_dict_round_trip():
    cfg = PolicyConfig(chunk=ChunkConfig(strides=(1, 4)), sampling=SamplingConfig(thresholds=(-1.0, 0.0, 1.0)))
    assert config_from_dict(PolicyConfig, config_to_dict(cfg)) == cfg
