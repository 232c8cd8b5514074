"""Write tests/fixtures/torch/dp_resnet18_gn_encoder.npz with Diffusion Policy's unmodified image encoder.

Made with torch 2.14.1 and torchvision 0.29.1 (CPU) in a scratch venv that is not the project's (the project never
depends on torch), with DP's source tree (``real-stanford/diffusion_policy``, unmodified) on ``sys.path``:

    python3.12 -m venv /work/scratch/torchvenv && /work/scratch/torchvenv/bin/pip install torch torchvision \\
        diffusers einops
    /work/scratch/torchvenv/bin/python scripts/make_torch_encoder_fixtures.py --dp-src /work/scratch/dp_src \\
        tests/fixtures/torch/dp_resnet18_gn_encoder.npz

What it builds, with DP's code only: ``MultiImageObsEncoder(shape_meta, get_resnet('resnet18'), resize_shape=None,
crop_shape=None, random_crop=True, use_group_norm=True, share_rgb_model=False, imagenet_norm=True)`` — the release's
settings — for one rgb key ``head_cam`` (3 x 56 x 56) and one low-dim key ``agent_pos`` (4). ``agent_pos`` sorts
before ``head_cam``, so the output showing the image feature first records that DP puts rgb keys before low-dim keys
whatever their names. 56 px (not 32) leaves layer4 at 2 x 2, so the global average pool averages something, and the
7 -> 4 step of layer4's stride-2 conv exercises odd-size padding. A second encoder with ``crop_shape=(53, 53)`` in
eval mode (``CropRandomizer`` -> torchvision's centre crop, offset ``round(3 / 2) = 2``, not ``3 // 2 = 1``) checks
the crop path.

The 11 M weights are not stored: every encoder tensor is overwritten with ``seeded_torch_state(SEED)`` from
``hipolicy_jax/porting/encoders.py`` (loaded by path; it needs numpy only), which the tests redraw. The images are
``uint8`` from ``default_rng(SEED + 1)``; DP's dataset divides them by 255 and its policy normaliser
(``get_image_range_normalizer``) maps [0, 1] to [-1, 1]: that tensor is the encoder's input and is stored too.

Arrays in the npz (batch ``a``: 3 samples, batch ``b``: 2):

* ``image_u8_{a,b}`` (B, 56, 56, 3) uint8, NHWC as our datasets store images;
* ``image_{a,b}`` (B, 3, 56, 56) float32, the normalised NCHW tensor DP's encoder received;
* ``state_{a,b}`` (B, 4) float32, the (already normalised) low-dim input;
* ``features_{a,b}`` (B, 516) float32, the encoder's output; ``features_crop_a`` (3, 516) with the 53 px crop;
* ``param_names`` (str), ``param_shapes`` (str ``"64,3,7,7"``): the rgb model's state dict, names relative to
  ``prefix``; ``prefix``, ``seed``, ``crop_size``, ``versions``.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys

import numpy as np

SEED = 57
SIZE = 56
STATE_DIM = 4
CROP = 53
RGB_KEY = "head_cam"
LOW_DIM_KEY = "agent_pos"
BATCHES = {"a": 3, "b": 2}
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_porting():
    """``hipolicy_jax/porting/encoders.py`` loaded by path (numpy only: the project's package needs jax)."""
    path = os.path.join(ROOT, "hipolicy_jax", "porting", "encoders.py")
    spec = importlib.util.spec_from_file_location("porting_encoders", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def build(crop_shape, shape_meta, state):
    from diffusion_policy.model.vision.model_getter import get_resnet
    from diffusion_policy.model.vision.multi_image_obs_encoder import MultiImageObsEncoder
    import torch

    enc = MultiImageObsEncoder(shape_meta, get_resnet("resnet18"), resize_shape=None, crop_shape=crop_shape,
                               random_crop=True, use_group_norm=True, share_rgb_model=False, imagenet_norm=True)
    prefix = f"key_model_map.{RGB_KEY}."
    current = {k[len(prefix):]: tuple(v.shape) for k, v in enc.state_dict().items() if k.startswith(prefix)}
    if list(current.items()) != list(state["shapes"].items()):
        raise SystemExit(f"DP's encoder state dict differs from resnet_torch_shapes(): {current}")
    missing, unexpected = enc.load_state_dict(
        {prefix + k: torch.from_numpy(v) for k, v in state["weights"].items()}, strict=False)
    if unexpected or [k for k in missing if k != "_dummy_variable"]:
        raise SystemExit(f"load_state_dict: missing {missing}, unexpected {unexpected}")
    return enc.eval(), prefix


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="the .npz to write")
    parser.add_argument("--dp-src", required=True, help="Diffusion Policy's source tree (holds diffusion_policy/)")
    args = parser.parse_args(argv)
    sys.path.insert(0, os.path.abspath(args.dp_src))

    import torch
    import torchvision
    from diffusion_policy.common.normalize_util import get_image_range_normalizer

    torch.set_num_threads(1)
    porting = load_porting()
    shapes = porting.resnet_torch_shapes()
    state = {"shapes": shapes, "weights": porting.seeded_torch_state(shapes, SEED)}
    shape_meta = {"obs": {RGB_KEY: {"shape": [3, SIZE, SIZE], "type": "rgb"},
                          LOW_DIM_KEY: {"shape": [STATE_DIM], "type": "low_dim"}},
                  "action": {"shape": [2]}}
    enc, prefix = build(None, shape_meta, state)
    enc_crop, _ = build((CROP, CROP), shape_meta, state)
    image_normalizer = get_image_range_normalizer()

    rng = np.random.default_rng(SEED + 1)
    out = {"prefix": np.array(prefix), "seed": np.array(SEED), "crop_size": np.array(CROP),
           "param_names": np.array(list(shapes)),
           "param_shapes": np.array([",".join(map(str, s)) for s in shapes.values()]),
           "versions": np.array(f"torch {torch.__version__}, torchvision {torchvision.__version__}")}
    with torch.no_grad():
        for name, b in BATCHES.items():
            image_u8 = rng.integers(0, 256, (b, SIZE, SIZE, 3), dtype=np.uint8)
            state_in = rng.standard_normal((b, STATE_DIM)).astype(np.float32)
            # DP's dataset: np.moveaxis(img, -1, 1) / 255; its policy normaliser: [0, 1] -> [-1, 1] in float32
            image = image_normalizer.normalize(torch.from_numpy(np.moveaxis(image_u8, -1, 1) / 255))
            obs = {RGB_KEY: image, LOW_DIM_KEY: torch.from_numpy(state_in)}
            out[f"image_u8_{name}"] = image_u8
            out[f"image_{name}"] = image.numpy().astype(np.float32)
            out[f"state_{name}"] = state_in
            out[f"features_{name}"] = enc(obs).numpy()
            if name == "a":
                out["features_crop_a"] = enc_crop(obs).numpy()
    assert out["image_a"].dtype == np.float32 and out["features_a"].shape == (3, 512 + STATE_DIM)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    np.savez_compressed(args.out, **out)
    print(f"wrote {args.out} ({os.path.getsize(args.out) / 1e3:.0f} kB): features_a |max| "
          f"{np.abs(out['features_a']).max():.3f}, mean {out['features_a'][:, :512].mean():.3f}")


if __name__ == "__main__":
    main()
