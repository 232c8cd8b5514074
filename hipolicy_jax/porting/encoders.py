"""Diffusion Policy's image encoder weights (PyTorch state dict) as ``ResNetAvgPoolEncoder`` parameters.

The torch side is the encoder DP's ``MultiImageObsEncoder`` builds and the HiPolicy release uses: torchvision
``resnet18`` from ``get_resnet`` (``fc = Identity``) with every ``BatchNorm2d`` replaced by ``GroupNorm(C // 16, C)``.
Its state-dict names, relative to the ResNet module (``resnet_torch_shapes`` lists them in torchvision's order)::

    conv1.weight                         (C0, 3, 7, 7)      bn1.weight, bn1.bias                (C0,)
    layer{s+1}.{b}.conv1.weight          (C, C_in, 3, 3)    layer{s+1}.{b}.bn1.weight / .bias   (C,)
    layer{s+1}.{b}.conv2.weight          (C, C, 3, 3)       layer{s+1}.{b}.bn2.weight / .bias   (C,)
    layer{s+1}.0.downsample.0.weight     (C, C_in, 1, 1)    layer{s+1}.0.downsample.1.weight / .bias (C,)

(``downsample`` only where the stride or the width changes: stages 2-4 of ResNet-18.) In a DP / release checkpoint
(the workspace payload's ``state_dicts['model']`` or ``['ema_model']``) they sit under
``obs_encoder.key_model_map.<rgb key>.`` (``head_cam`` in the release); pass that as ``prefix``. The release's
RoboTwin-1 branch also stores its ImageNet statistics as buffers (``obs_encoder.key_transform_map.<key>.2.mean`` /
``.std``): fixed constants, outside the prefix, not parameters.

The flax side is ``models.encoders.ResNetAvgPoolEncoder``'s ``params``: ``stem_conv/kernel`` (7, 7, 3, C0),
``stem_norm/{scale, bias}``, ``stage{s}_block{b}/{conv1, conv2, shortcut}/kernel`` and
``stage{s}_block{b}/{norm1, norm2, shortcut_norm}/{scale, bias}``. Conv kernels go from torch's OIHW to flax's HWIO
(``transpose(2, 3, 1, 0)``); GroupNorm ``weight`` becomes ``scale``.

This module needs numpy only (no jax, flax or torch), so ``scripts/make_torch_encoder_fixtures.py`` loads it by path
in torch's venv and draws the fixture's weights with ``seeded_torch_state``, the recipe the tests redraw.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

RESNET18_CHANNELS = (64, 128, 256, 512)


def _layout(channels: tuple[int, ...], in_channels: int) -> list[tuple[str, tuple[str, ...], tuple[int, ...]]]:
    """``(torch name, flax path, torch shape)`` for every tensor, in torchvision's state-dict order."""
    c0 = channels[0]
    rows = [("conv1.weight", ("stem_conv", "kernel"), (c0, in_channels, 7, 7)),
            ("bn1.weight", ("stem_norm", "scale"), (c0,)),
            ("bn1.bias", ("stem_norm", "bias"), (c0,))]
    c_in = c0
    for s, c in enumerate(channels):
        for b in range(2):
            t, f = f"layer{s + 1}.{b}.", f"stage{s}_block{b}"
            stride = 2 if (s > 0 and b == 0) else 1
            rows += [(t + "conv1.weight", (f, "conv1", "kernel"), (c, c_in, 3, 3)),
                     (t + "bn1.weight", (f, "norm1", "scale"), (c,)),
                     (t + "bn1.bias", (f, "norm1", "bias"), (c,)),
                     (t + "conv2.weight", (f, "conv2", "kernel"), (c, c, 3, 3)),
                     (t + "bn2.weight", (f, "norm2", "scale"), (c,)),
                     (t + "bn2.bias", (f, "norm2", "bias"), (c,))]
            if stride != 1 or c_in != c:  # torchvision's and BasicBlock's shortcut condition
                rows += [(t + "downsample.0.weight", (f, "shortcut", "kernel"), (c, c_in, 1, 1)),
                         (t + "downsample.1.weight", (f, "shortcut_norm", "scale"), (c,)),
                         (t + "downsample.1.bias", (f, "shortcut_norm", "bias"), (c,))]
            c_in = c
    return rows


def resnet_torch_shapes(channels: tuple[int, ...] = RESNET18_CHANNELS,
                        in_channels: int = 3) -> dict[str, tuple[int, ...]]:
    """Torch state-dict name -> shape of DP's GroupNorm ResNet (``fc`` removed), in torchvision's order, names
    relative to the ResNet module. ``channels`` are the stage widths (ResNet-18: ``(64, 128, 256, 512)``)."""
    return {name: shape for name, _, shape in _layout(tuple(channels), in_channels)}


def resnet_params_from_torch(state_dict: Mapping[str, np.ndarray], prefix: str = "",
                             channels: tuple[int, ...] = RESNET18_CHANNELS, in_channels: int = 3) -> dict:
    """``ResNetAvgPoolEncoder(channels)``'s flax ``params`` (nested dicts of float32 arrays) from a torch state dict.

    ``state_dict`` maps torch names to arrays (``{k: v.numpy() for k, v in sd.items()}``); only keys starting with
    ``prefix`` are read and every one of them must be an encoder tensor: a missing key, a mis-shaped one or an
    unexpected one under the prefix (BatchNorm running statistics: the BatchNorms were not replaced; ``fc.*``: fc was
    not removed) raises ``ValueError`` naming the key and the expected shape.
    """
    rows = _layout(tuple(channels), in_channels)
    expected = {prefix + name for name, _, _ in rows}
    unexpected = sorted(k for k in state_dict if k.startswith(prefix) and k not in expected)
    if unexpected:
        raise ValueError(f"state_dict: unexpected keys under prefix {prefix!r} for DP's GroupNorm ResNet with "
                         f"channels={tuple(channels)} (BatchNorm buffers: not replaced by GroupNorm; fc.*: fc not "
                         f"removed): {unexpected[:6]}{' ...' if len(unexpected) > 6 else ''}")
    params: dict = {}
    for name, path, shape in rows:
        key = prefix + name
        if key not in state_dict:
            raise ValueError(f"state_dict[{key!r}]: missing; DP's GroupNorm ResNet with channels={tuple(channels)} "
                             f"expects shape {shape} (torch layout)")
        value = np.asarray(state_dict[key])
        if value.shape != shape:
            raise ValueError(f"state_dict[{key!r}]: expected shape {shape} (torch layout), got {value.shape}")
        if not np.issubdtype(value.dtype, np.floating):
            raise ValueError(f"state_dict[{key!r}]: expected a floating-point array, got dtype {value.dtype}")
        value = value.astype(np.float32)
        if value.ndim == 4:
            value = value.transpose(2, 3, 1, 0)  # OIHW -> HWIO
        node = params
        for part in path[:-1]:
            node = node.setdefault(part, {})
        node[path[-1]] = value
    return params


def seeded_torch_state(shapes: Mapping[str, tuple[int, ...]], seed: int) -> dict[str, np.ndarray]:
    """Deterministic non-trivial weights for a conv / GroupNorm network, by torch name, float32.

    One ``numpy.random.default_rng(seed)`` draws every tensor in the order of ``shapes`` (state-dict order): a conv
    kernel ``(O, I, kh, kw)`` ~ N(0, 2 / (I * kh * kw)) (He: activations stay O(1)); a 2-D or 3-D weight (Linear,
    Conv1d, ConvTranspose1d, attention projections) ~ N(0, 1 / prod(shape[1:])); a CLS token ~ N(0, 1); a GroupNorm
    ``*.weight`` ~ U(0.5, 1.5); a ``*bias`` ~ N(0, 0.2^2). Drawn in float64, then cast. The fixture script writes these into the
    upstream torch module and the tests redraw them from the same names, shapes and seed.
    """
    rng = np.random.default_rng(seed)
    out = {}
    for name, shape in shapes.items():
        if len(shape) == 4:
            value = rng.standard_normal(shape) * np.sqrt(2.0 / (shape[1] * shape[2] * shape[3]))
        elif name.endswith("cls_tokens"):
            value = rng.standard_normal(shape)
        elif len(shape) in (2, 3):  # Linear (O, I), Conv1d (O, I, k), ConvTranspose1d (I, O, k), attention in_proj
            value = rng.standard_normal(shape) * np.sqrt(1.0 / int(np.prod(shape[1:])))
        elif name.endswith(".weight"):
            value = rng.uniform(0.5, 1.5, shape)
        elif name.endswith("bias"):
            value = 0.2 * rng.standard_normal(shape)
        else:
            raise ValueError(f"shapes[{name!r}]: no recipe for shape {tuple(shape)} (conv kernels are 4-D, norm "
                             f"weights / biases end in .weight / .bias)")
        out[name] = value.astype(np.float32)
    return out
