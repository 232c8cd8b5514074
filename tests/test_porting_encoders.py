"""Diffusion Policy's image encoder (ResNet-18 + GroupNorm, average pool) run from its PyTorch weights.

``tests/fixtures/torch/dp_resnet18_gn_encoder.npz`` holds the outputs of DP's unmodified ``MultiImageObsEncoder``
(release settings, one rgb key of 3 x 56 x 56, one low-dim key of 4) with weights drawn by
``porting.encoders.seeded_torch_state`` (``scripts/make_torch_encoder_fixtures.py`` says how it was made). The tests
redraw those weights, port them with ``resnet_params_from_torch`` and compare features to 1e-5.
"""

from __future__ import annotations

import functools
import pathlib
import re

import jax
import numpy as np
import pytest

from hipolicy_jax.config import EncoderConfig
from hipolicy_jax.data.normalizer import image_to_float
from hipolicy_jax.models.encoders import ObsEncoder, ResNetAvgPoolEncoder, crop_images
from hipolicy_jax.porting.encoders import (
    RESNET18_CHANNELS,
    resnet_params_from_torch,
    resnet_torch_shapes,
    seeded_torch_state,
)

FIXTURE = pathlib.Path(__file__).parent / "fixtures" / "torch" / "dp_resnet18_gn_encoder.npz"
TOL = 1e-5  # float32; measured max |diff| 2.6e-6 on features of magnitude up to 3.9 (conv summation order)
SIZE, D, FEAT = 56, 4, 512


@pytest.fixture(scope="module")
def fx():
    with np.load(FIXTURE) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def torch_state(fx):
    names = [str(n) for n in fx["param_names"]]
    shapes = {n: tuple(int(v) for v in str(s).split(",")) for n, s in zip(names, fx["param_shapes"])}
    return seeded_torch_state(shapes, int(fx["seed"]))


@pytest.fixture(scope="module")
def params(torch_state):
    return resnet_params_from_torch(torch_state)


@functools.lru_cache(maxsize=None)
def _apply(crop_size):
    return jax.jit(ResNetAvgPoolEncoder(RESNET18_CHANNELS, crop_size).apply)


def encode(params, images_nhwc, crop_size=None) -> np.ndarray:
    return np.asarray(_apply(crop_size)({"params": params}, images_nhwc))


def max_diff(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def resnet_cfg(**changes) -> EncoderConfig:
    base = dict(obs_type="image", image_encoder="resnet_avgpool", state_encoder="identity", image_size=SIZE,
                crop_size=SIZE)
    base.update(changes)
    return EncoderConfig(**base)


# --- the fixture and the weight recipe ---------------------------------------------------------------------------

def test_fixture_names_and_shapes_are_torchvisions_and_the_recipe_is_non_trivial(fx, torch_state):
    # the script checked DP's state dict against resnet_torch_shapes(), in order; the fixture records that list
    assert [str(n) for n in fx["param_names"]] == list(resnet_torch_shapes())
    assert str(fx["prefix"]) == "key_model_map.head_cam."
    shapes = resnet_torch_shapes()
    assert len(shapes) == 3 + 4 * 12 + 3 * 3  # stem, 8 blocks of 6 tensors, 3 shortcuts of 3
    assert sum(int(np.prod(s)) for s in shapes.values()) == 11_176_512  # torchvision resnet18 without fc
    assert shapes["conv1.weight"] == (64, 3, 7, 7)
    assert shapes["layer2.0.downsample.0.weight"] == (128, 64, 1, 1)
    assert "layer1.0.downsample.0.weight" not in shapes  # stride 1, 64 -> 64: identity shortcut
    # the recipe: fan-in scaled kernels, GroupNorm scales in [0.5, 1.5] (not 1), biases N(0, 0.2^2) (not 0)
    w = torch_state["layer3.1.conv2.weight"]
    assert w.dtype == np.float32 and abs(w.std() - np.sqrt(2 / (256 * 9))) < 0.002
    g, b = torch_state["layer4.0.bn2.weight"], torch_state["layer4.0.bn2.bias"]
    assert 0.5 <= g.min() and g.max() <= 1.5 and g.std() > 0.2
    assert abs(b.std() - 0.2) < 0.03
    again = seeded_torch_state(shapes, int(fx["seed"]))
    assert all(np.array_equal(again[k], v) for k, v in torch_state.items())
    assert not np.array_equal(seeded_torch_state(shapes, 1)["conv1.weight"], torch_state["conv1.weight"])
    with pytest.raises(ValueError, match=r"shapes\['x.running_mean'\]: no recipe for shape \(4,\)"):
        seeded_torch_state({"x.running_mean": (4,)}, 0)


def test_dp_input_is_our_image_to_float_within_one_ulp(fx):
    """DP: ``float32(u / 255) * 2 - 1`` (dataset, then normaliser); ours: ``u * (2 / 255) - 1``."""
    for b in ("a", "b"):
        u8, dp = fx[f"image_u8_{b}"], fx[f"image_{b}"]
        np.testing.assert_array_equal(dp, (np.moveaxis(u8, -1, 1) / 255).astype(np.float32) * 2 - 1)
        assert max_diff(image_to_float(u8), np.moveaxis(dp, 1, -1)) <= 2.0 ** -23


# --- features equal DP's -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("batch", ["a", "b"])
def test_features_equal_upstream(fx, params, batch):
    ref = fx[f"features_{batch}"]
    assert ref.shape == (fx[f"image_{batch}"].shape[0], FEAT + D)
    # DP concatenates [rgb feature, low-dim] although 'agent_pos' sorts before 'head_cam'
    np.testing.assert_array_equal(ref[:, FEAT:], fx[f"state_{batch}"])
    ours = encode(params, np.moveaxis(fx[f"image_{batch}"], 1, -1))
    assert ours.shape == (ref.shape[0], FEAT)
    assert max_diff(ours, ref[:, :FEAT]) < TOL
    assert np.abs(ref[:, :FEAT]).max() > 1.0 and ref[:, :FEAT].std() > 0.3  # a comparison of O(1) numbers
    # from the uint8 images through our own [-1, 1] mapping
    assert max_diff(encode(params, image_to_float(fx[f"image_u8_{batch}"])), ref[:, :FEAT]) < TOL


def test_obs_encoder_gives_dps_features_in_dps_order_and_frame_order(fx, params):
    """Batch a's 3 images as one sample's L_h = 3 frames: the condition is DP's ``features.reshape(B, -1)`` over
    the observation steps, each frame ``[image feature, state]``."""
    enc = ObsEncoder(resnet_cfg())
    obs = {"image": image_to_float(fx["image_u8_a"])[None, None], "state": fx["state_a"][None, None]}
    cond = np.asarray(jax.jit(enc.apply)({"params": {"image": params}}, obs))
    assert cond.shape == (1, 1, 3 * (FEAT + D))
    assert max_diff(cond.reshape(3, FEAT + D), fx["features_a"]) < TOL


def test_centre_crop_equals_dps_crop_randomizer_in_eval(fx, params):
    """``crop_shape=(53, 53)``: torchvision's centre crop starts at ``round(3 / 2) = 2``; ``3 // 2 = 1`` is far off."""
    crop = int(fx["crop_size"])
    ref = fx["features_crop_a"][:, :FEAT]
    images = np.moveaxis(fx["image_a"], 1, -1)
    assert max_diff(encode(params, images, crop), ref) < TOL
    assert max_diff(encode(params, images), ref) > 100 * TOL  # the crop mattered
    floor_crop = np.asarray(crop_images(images, crop, None))
    assert max_diff(encode(params, floor_crop), ref) > 100 * TOL
    enc = ObsEncoder(resnet_cfg(crop_size=crop))
    obs = {"image": images[:, None, None], "state": fx["state_a"][:, None, None]}
    cond = np.asarray(jax.jit(enc.apply)({"params": {"image": params}}, obs))
    assert max_diff(cond[:, 0], fx["features_crop_a"]) < TOL


def test_train_crops_are_random_and_no_crop_needs_no_rng(fx, params):
    images = np.moveaxis(fx["image_b"], 1, -1)
    enc = ResNetAvgPoolEncoder(crop_size=53)
    t0, t1 = (enc.apply({"params": params}, images, train=True, rngs={"crop": jax.random.key(k)}) for k in (0, 1))
    assert max_diff(t0, t1) > 100 * TOL
    plain = ResNetAvgPoolEncoder().apply({"params": params}, images, train=True)  # no "crop" stream needed
    assert max_diff(plain, fx["features_b"][:, :FEAT]) < TOL


@pytest.mark.parametrize("mistake", ["kernel_not_transposed", "blocks_swapped"])
def test_a_wrong_mapping_fails_the_comparison_widely(fx, params, mistake):
    wrong = jax.tree_util.tree_map(lambda x: x, params)  # a copy of the nested dicts
    if mistake == "kernel_not_transposed":  # OIHW -> HWOI instead of HWIO: same shape for a 64 -> 64 conv
        k = wrong["stage0_block1"]["conv2"]["kernel"]
        wrong["stage0_block1"]["conv2"] = {"kernel": k.transpose(0, 1, 3, 2)}
    else:  # layer1.0 <-> layer1.1: same shapes
        wrong["stage0_block0"], wrong["stage0_block1"] = params["stage0_block1"], params["stage0_block0"]
    assert jax.tree_util.tree_map(np.shape, wrong) == jax.tree_util.tree_map(np.shape, params)
    images = np.moveaxis(fx["image_a"], 1, -1)
    assert max_diff(encode(params, images), fx["features_a"][:, :FEAT]) < TOL
    assert max_diff(encode(wrong, images), fx["features_a"][:, :FEAT]) > 0.05


# --- the mapping's checks ----------------------------------------------------------------------------------------

def test_prefix_selects_the_encoder_in_a_whole_checkpoint(torch_state, params):
    prefix = "obs_encoder.key_model_map.head_cam."
    whole = {prefix + k: v for k, v in torch_state.items()}
    whole["obs_encoder._dummy_variable"] = np.zeros((0,), np.float32)
    whole["model.final_conv.1.weight"] = np.ones((14, 256, 1), np.float32)
    whole["obs_encoder.key_transform_map.head_cam.2.mean"] = np.zeros((1, 3, 1, 1), np.float32)
    ported = resnet_params_from_torch(whole, prefix=prefix)
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, ported, params))
    # OIHW -> HWIO, GroupNorm weight -> scale
    np.testing.assert_array_equal(ported["stem_conv"]["kernel"][2, 5, 1, 7], torch_state["conv1.weight"][7, 1, 2, 5])
    np.testing.assert_array_equal(ported["stage1_block0"]["shortcut_norm"]["scale"],
                                  torch_state["layer2.0.downsample.1.weight"])


@pytest.mark.parametrize("case", ["missing", "shape", "batchnorm", "fc", "dtype"])
def test_bad_state_dicts_name_the_key_and_the_expected_shape(torch_state, case):
    sd = dict(torch_state)
    if case == "missing":
        del sd["layer3.0.downsample.1.bias"]
        msg = (r"state_dict\['layer3.0.downsample.1.bias'\]: missing; DP's GroupNorm ResNet with channels=\(64, 128, "
               r"256, 512\) expects shape \(256,\) \(torch layout\)")
    elif case == "shape":
        sd["layer1.1.conv2.weight"] = sd["layer1.1.conv2.weight"].transpose(2, 3, 1, 0)  # already HWIO
        msg = (r"state_dict\['layer1.1.conv2.weight'\]: expected shape \(64, 64, 3, 3\) \(torch layout\), "
               r"got \(3, 3, 64, 64\)")
    elif case == "batchnorm":  # a BatchNorm ResNet: running statistics
        sd["bn1.running_mean"] = np.zeros(64, np.float32)
        sd["bn1.num_batches_tracked"] = np.zeros((), np.int64)
        msg = (r"state_dict: unexpected keys under prefix '' .*BatchNorm buffers: not replaced by GroupNorm.*"
               r"\['bn1.num_batches_tracked', 'bn1.running_mean'\]")
    elif case == "fc":
        sd["fc.weight"], sd["fc.bias"] = np.zeros((1000, 512), np.float32), np.zeros(1000, np.float32)
        msg = r"unexpected keys .*fc not removed.*\['fc.bias', 'fc.weight'\]"
    else:
        sd["bn1.bias"] = np.zeros(64, np.int64)
        msg = r"state_dict\['bn1.bias'\]: expected a floating-point array, got dtype int64"
    with pytest.raises(ValueError, match=msg):
        resnet_params_from_torch(sd)


def test_parameter_tree_names_are_stable(params):
    """The flax tree the mapping writes is exactly the module's (names and shapes), inside ObsEncoder under
    ``image``; the names are part of saved checkpoints."""
    cfg = resnet_cfg(image_size=32, crop_size=32)
    obs = {"image": np.zeros((1, 1, 1, 32, 32, 3), np.float32), "state": np.zeros((1, 1, 1, D), np.float32)}
    shapes = jax.eval_shape(ObsEncoder(cfg).init, jax.random.key(0), obs)["params"]
    assert list(shapes) == ["image"]
    assert jax.tree_util.tree_map(lambda s: s.shape, shapes["image"]) == jax.tree_util.tree_map(np.shape, params)
    blocks = [f"stage{s}_block{b}" for s in range(4) for b in range(2)]
    assert sorted(shapes["image"]) == sorted(["stem_conv", "stem_norm"] + blocks)
    assert sorted(shapes["image"]["stage1_block0"]) == ["conv1", "conv2", "norm1", "norm2", "shortcut",
                                                        "shortcut_norm"]
    assert sorted(shapes["image"]["stage0_block0"]) == ["conv1", "conv2", "norm1", "norm2"]
    assert shapes["image"]["stage3_block1"]["norm2"]["scale"].shape == (512,)
    # the default image encoder's tree is untouched
    default = jax.eval_shape(ObsEncoder(EncoderConfig(obs_type="image", image_size=32, crop_size=28,
                                                      image_channels=(8, 16), num_keypoints=4)).init,
                             jax.random.key(0), obs)["params"]
    assert sorted(default) == ["image", "state"]
    assert sorted(default["image"]) == ["out", "spatial_softmax", "stage0_block0", "stage0_block1",
                                        "stage1_block0", "stage1_block1", "stem_conv", "stem_norm"]


def test_obs_encoder_shape_with_the_release_encoder():
    """``(B, M, L_h * (512 + D))`` with the identity state (HiPolicy's M = 3, L_h = 3), and ``512 + state_out``
    with the state MLP."""
    b, m, lh = 2, 3, 3
    obs = {"image": np.zeros((b, m, lh, 40, 40, 3), np.float32), "state": np.zeros((b, m, lh, 7), np.float32)}
    for cfg, feat in [(resnet_cfg(image_size=40, crop_size=36), FEAT + 7),
                      (resnet_cfg(image_size=40, crop_size=40, state_dims=D), FEAT + D),
                      (resnet_cfg(image_size=40, crop_size=40, state_encoder="mlp", state_out=8), FEAT + 8)]:
        enc = ObsEncoder(cfg)
        variables = jax.eval_shape(enc.init, jax.random.key(0), obs)
        out = jax.eval_shape(functools.partial(enc.apply, train=True, rngs={"crop": jax.random.key(1)}),
                             variables, obs)
        assert out.shape == (b, m, lh * feat)


# --- configuration -----------------------------------------------------------------------------------------------

def test_config_defaults_and_messages():
    assert EncoderConfig().image_encoder == "spatial_softmax"
    assert resnet_cfg().image_channels == RESNET18_CHANNELS
    EncoderConfig(image_encoder="resnet_avgpool", image_channels=(16, 40, 72))  # 1, 2 and 4 groups
    with pytest.raises(ValueError, match=re.escape(
            "encoder.image_encoder: must be 'spatial_softmax' or 'resnet_avgpool', got 'avgpool'")):
        EncoderConfig(image_encoder="avgpool")
    for channels in [(8, 16), (64, 56)]:  # 8 // 16 = 0 groups; 56 // 16 = 3 does not divide 56
        with pytest.raises(ValueError, match=re.escape(
                "encoder.image_channels: image_encoder='resnet_avgpool' normalises with GroupNorm(C // 16) as "
                f"Diffusion Policy: every width C must be >= 16 and divisible by C // 16, got {channels}")):
            EncoderConfig(image_encoder="resnet_avgpool", image_channels=channels)
    EncoderConfig(image_channels=(8, 16))  # the spatial-softmax encoder keeps its own group rule
    with pytest.raises(ValueError, match=re.escape(
            "channels: GroupNorm(C // 16, C) needs C >= 16 and C divisible by C // 16, got (64, 56) (bad: [56])")):
        jax.eval_shape(ResNetAvgPoolEncoder((64, 56)).init, jax.random.key(0), np.zeros((1, 32, 32, 3)))
