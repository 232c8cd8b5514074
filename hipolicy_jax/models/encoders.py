"""Observation encoders: proprioceptive state MLP (or the raw state), ResNet-18 image encoders, DP3 point-cloud
encoder.

``ObsEncoder`` turns a hierarchical observation window into HiPolicy's per-frequency condition. Its input arrays
carry leading dims ``(B, M, L_h, ...)`` (batch, frequency in segment order, history frame); every frame of every
frequency goes through the *same* encoder (each distinct time step once, since the frequencies' windows overlap),
and the ``L_h`` frame features of one frequency are flattened into that frequency's condition, exactly as Diffusion
Policy flattens its observation features over time into one global condition. The result is ``(B, M, L_h * F)``.
"""

from __future__ import annotations

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import flax.linen as nn

from hipolicy_jax.config import EncoderConfig

Activation = Literal["mish", "relu"]
_ACTIVATIONS = {"mish": jax.nn.mish, "relu": jax.nn.relu}


def _activation(name: str):
    if name not in _ACTIVATIONS:
        raise ValueError(f"activation: must be one of {sorted(_ACTIVATIONS)}, got {name!r}")
    return _ACTIVATIONS[name]


def gn_groups(channels: int) -> int:
    """GroupNorm group count for a ResNet stage, following robomimic / Diffusion Policy (``channels // 16``).

    Falls back to the largest divisor of ``channels`` not above ``channels // 16`` (at least 1), so that narrow
    CPU-sized trunks still normalise cleanly.
    """
    target = max(1, channels // 16)
    return max(g for g in range(1, target + 1) if channels % g == 0)


class StateEncoder(nn.Module):
    """Per-frame MLP for proprioceptive state: ``(..., D) -> (..., out_dim)``.

    ``Dense(h) [-> LayerNorm] -> act`` for each hidden size, then a final ``Dense(out_dim)`` with no activation
    (DP3's state MLP with ``hidden=(64,)``, ``out_dim=64``, ``activation='relu'``).
    """

    hidden: tuple[int, ...] = (256, 256)
    out_dim: int = 64
    activation: Activation = "mish"
    layer_norm: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = _activation(self.activation)
        for i, h in enumerate(self.hidden):
            x = nn.Dense(h, name=f"dense_{i}")(x)
            if self.layer_norm:
                x = nn.LayerNorm(name=f"norm_{i}")(x)
            x = act(x)
        return nn.Dense(self.out_dim, name="out")(x)


def crop_images(images: jax.Array, crop_size: int, key: jax.Array | None) -> jax.Array:
    """Crop ``(N, H, W, C)`` images to ``(N, crop, crop, C)``.

    With a key, every image gets its own uniformly random offset (Diffusion Policy / robomimic ``CropRandomizer`` in
    training); with ``key=None`` every image is centre-cropped (evaluation), deterministically.
    """
    n, h, w, c = images.shape
    if crop_size == h and crop_size == w:
        return images
    if key is None:
        top = jnp.full((n,), (h - crop_size) // 2, jnp.int32)
        left = jnp.full((n,), (w - crop_size) // 2, jnp.int32)
    else:
        k_top, k_left = jax.random.split(key)
        top = jax.random.randint(k_top, (n,), 0, h - crop_size + 1)
        left = jax.random.randint(k_left, (n,), 0, w - crop_size + 1)

    def one(img, t, l):
        return jax.lax.dynamic_slice(img, (t, l, 0), (crop_size, crop_size, c))

    return jax.vmap(one)(images, top, left)


class SpatialSoftmax(nn.Module):
    """robomimic's spatial soft-argmax: ``(N, H, W, C) -> (N, 2 * num_keypoints)``.

    A 1x1 conv maps the feature map to ``num_keypoints`` heat maps; a softmax over the ``H*W`` positions (temperature
    1) gives each keypoint's expected (x, y) position in [-1, 1].
    """

    num_keypoints: int = 32

    @nn.compact
    def __call__(self, feat: jax.Array) -> jax.Array:
        n, h, w, _ = feat.shape
        heat = nn.Conv(self.num_keypoints, (1, 1), name="keypoints")(feat)  # (N, H, W, K)
        heat = heat.reshape(n, h * w, self.num_keypoints)
        attn = jax.nn.softmax(heat, axis=1)
        pos_y, pos_x = jnp.meshgrid(jnp.linspace(-1.0, 1.0, h), jnp.linspace(-1.0, 1.0, w), indexing="ij")
        ex = jnp.einsum("npk,p->nk", attn, pos_x.reshape(-1))
        ey = jnp.einsum("npk,p->nk", attn, pos_y.reshape(-1))
        return jnp.stack([ex, ey], axis=-1).reshape(n, 2 * self.num_keypoints)


class BasicBlock(nn.Module):
    """ResNet BasicBlock with GroupNorm: two 3x3 convs, projection shortcut when the shape changes.

    ``(N, H, W, C_in) -> (N, H/stride, W/stride, channels)``.
    """

    channels: int
    stride: int = 1

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        groups = gn_groups(self.channels)
        y = nn.Conv(self.channels, (3, 3), strides=self.stride, padding=1, use_bias=False, name="conv1")(x)
        y = nn.relu(nn.GroupNorm(num_groups=groups, epsilon=1e-5, name="norm1")(y))
        y = nn.Conv(self.channels, (3, 3), padding=1, use_bias=False, name="conv2")(y)
        y = nn.GroupNorm(num_groups=groups, epsilon=1e-5, name="norm2")(y)
        if self.stride != 1 or x.shape[-1] != self.channels:
            x = nn.Conv(self.channels, (1, 1), strides=self.stride, use_bias=False, name="shortcut")(x)
            x = nn.GroupNorm(num_groups=groups, epsilon=1e-5, name="shortcut_norm")(x)
        return nn.relu(y + x)


class ImageEncoder(nn.Module):
    """robomimic ``VisualCore`` as used by Diffusion Policy: ResNet-18 trunk with GroupNorm, spatial softmax, Linear.

    Input ``(..., H, W, 3)`` float images in [-1, 1] (NHWC); output ``(..., out_dim)``. The trunk is a 7x7/2 stem
    conv + GroupNorm + ReLU + 3x3/2 max-pool, then one stage of two BasicBlocks per entry of ``channels`` (stride 1
    for the first stage, 2 after), as ResNet-18 with ``channels=(64, 128, 256, 512)``. In training (``train=True``)
    every image is randomly cropped to ``crop_size`` with its own offset, drawn from the ``"crop"`` rng stream; at
    evaluation every image is centre-cropped.
    """

    channels: tuple[int, ...] = (64, 128, 256, 512)
    num_keypoints: int = 32
    out_dim: int = 64
    crop_size: int = 76

    @nn.compact
    def __call__(self, images: jax.Array, train: bool = False) -> jax.Array:
        lead = images.shape[:-3]
        x = images.reshape((-1,) + images.shape[-3:])  # (N, H, W, 3)
        x = crop_images(x, self.crop_size, self.make_rng("crop") if train else None)
        c0 = self.channels[0]
        x = nn.Conv(c0, (7, 7), strides=2, padding=3, use_bias=False, name="stem_conv")(x)
        x = nn.relu(nn.GroupNorm(num_groups=gn_groups(c0), epsilon=1e-5, name="stem_norm")(x))
        x = nn.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
        for s, ch in enumerate(self.channels):
            for b in range(2):
                stride = 2 if (s > 0 and b == 0) else 1
                x = BasicBlock(ch, stride, name=f"stage{s}_block{b}")(x)
        x = SpatialSoftmax(self.num_keypoints, name="spatial_softmax")(x)
        x = nn.Dense(self.out_dim, name="out")(x)
        return x.reshape(lead + (self.out_dim,))


IMAGENET_MEAN = (0.485, 0.456, 0.406)  # torchvision's ImageNet statistics, as Diffusion Policy passes them
IMAGENET_STD = (0.229, 0.224, 0.225)


def dp_centre_crop(images: jax.Array, crop_size: int) -> jax.Array:
    """torchvision's ``center_crop`` (what DP's ``CropRandomizer`` does in eval): ``(N, H, W, C) -> (N, c, c, C)``.

    The offset is ``round((H - c) / 2)`` with Python's rounding (half to even), as torchvision computes it; it differs
    from ``crop_images``' ``(H - c) // 2`` when ``H - c`` is 3, 7, 11, ...
    """
    _, h, w, _ = images.shape
    top, left = int(round((h - crop_size) / 2.0)), int(round((w - crop_size) / 2.0))
    return images[:, top:top + crop_size, left:left + crop_size]


class ResNetAvgPoolEncoder(nn.Module):
    """Diffusion Policy's ``MultiImageObsEncoder`` image path, as the HiPolicy release configures it.

    Input ``(..., H, W, 3)`` float images in [-1, 1] (NHWC; DP's policy normaliser maps the dataset's [0, 1] images to
    [-1, 1] before the encoder); output ``(..., channels[-1])`` (512 for ResNet-18). In DP's order: crop to
    ``crop_size`` (none when it equals H = W; random offsets from the ``"crop"`` rng stream in training, torchvision's
    centre crop at evaluation, as DP's ``CropRandomizer``), then ImageNet ``(x - mean) / std`` per channel — applied
    to the [-1, 1] image, exactly as DP does although the statistics are those of [0, 1] images — then torchvision's
    ResNet-18 with every BatchNorm replaced by ``GroupNorm(C // 16, C)`` (DP's ``replace_bn_with_gn``) and ``fc``
    removed: 7x7/2 stem conv + GroupNorm + ReLU + 3x3/2 max-pool, two BasicBlocks per stage (stride 2 from the second
    stage), global average pool. ``BasicBlock``'s ``gn_groups(C)`` equals ``C // 16`` for every width that
    ``GroupNorm(C // 16, C)`` accepts (``C >= 16``, ``C % (C // 16) == 0``); other widths raise ``ValueError``.
    ``porting.encoders`` maps torchvision's weights onto this module's parameters.
    """

    channels: tuple[int, ...] = (64, 128, 256, 512)
    crop_size: int | None = None  # None: no crop (the release)

    @nn.compact
    def __call__(self, images: jax.Array, train: bool = False) -> jax.Array:
        bad = [c for c in self.channels if c < 16 or c % (c // 16)]
        if bad:
            raise ValueError(f"channels: GroupNorm(C // 16, C) needs C >= 16 and C divisible by C // 16, got "
                             f"{self.channels} (bad: {bad})")
        lead = images.shape[:-3]
        x = images.reshape((-1,) + images.shape[-3:])  # (N, H, W, 3)
        if self.crop_size is not None:
            x = (crop_images(x, self.crop_size, self.make_rng("crop")) if train
                 else dp_centre_crop(x, self.crop_size))
        x = (x - jnp.asarray(IMAGENET_MEAN, jnp.float32)) / jnp.asarray(IMAGENET_STD, jnp.float32)
        c0 = self.channels[0]
        x = nn.Conv(c0, (7, 7), strides=2, padding=3, use_bias=False, name="stem_conv")(x)
        x = nn.relu(nn.GroupNorm(num_groups=c0 // 16, epsilon=1e-5, name="stem_norm")(x))
        x = nn.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
        for s, ch in enumerate(self.channels):
            for b in range(2):
                x = BasicBlock(ch, 2 if (s > 0 and b == 0) else 1, name=f"stage{s}_block{b}")(x)
        x = jnp.mean(x, axis=(1, 2))  # (N, channels[-1]): AdaptiveAvgPool2d(1) + flatten
        return x.reshape(lead + (self.channels[-1],))


class _DenseParams(nn.Module):
    """``nn.Dense``'s parameters (``kernel`` ``(in, features)``, lecun-normal; ``bias`` zeros), created under the
    same names and in the same order, so that they and their initial values equal ``nn.Dense``'s."""

    features: int

    @nn.compact
    def __call__(self, in_features: int) -> tuple[jax.Array, jax.Array]:
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (in_features, self.features), jnp.float32)
        return kernel, self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)


class _LayerNormParams(nn.Module):
    """``nn.LayerNorm``'s parameters (``scale`` ones, ``bias`` zeros) over ``features``."""

    features: int

    @nn.compact
    def __call__(self) -> tuple[jax.Array, jax.Array]:
        return (self.param("scale", nn.initializers.ones_init(), (self.features,), jnp.float32),
                self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32))


def _layer_norm_stats(y: jax.Array, eps: float) -> tuple[jax.Array, jax.Array]:
    """``nn.LayerNorm``'s statistics over the last axis: (mean, 1 / sqrt(var + eps)), the variance as
    E[y²] − E[y]² clipped at 0 (flax's fast variance), each ``(..., 1)``."""
    mean = jnp.mean(y, -1, keepdims=True)
    var = jnp.maximum(jnp.mean(jnp.square(y), -1, keepdims=True) - jnp.square(mean), 0.0)
    return mean, jax.lax.rsqrt(var + eps)


def _normed(y, mean, rstd, scale, shift):
    """The LayerNorm's output, rounded as ``nn.LayerNorm`` rounds it (the ReLU's input)."""
    return (y - mean) * (rstd * scale) + shift


def _rows(v: jax.Array) -> jax.Array:
    """``(..., C) -> (points, C)``."""
    return v.reshape(-1, v.shape[-1])


def _trunk_forward(points, layers, eps):
    """The per-point MLP: (activations of the last layer, every layer's pre-norm output, means, inverse stds)."""
    a, ys, means, rstds = points, [], [], []
    for kernel, bias, scale, shift in layers:
        y = jnp.dot(a, kernel) + bias
        mean, rstd = _layer_norm_stats(y, eps)
        a = jax.nn.relu(_normed(y, mean, rstd, scale, shift))
        ys.append(y)
        means.append(mean)
        rstds.append(rstd)
    return a, ys, means, rstds


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def point_trunk(points: jax.Array, layers, eps: float = 1e-6) -> jax.Array:
    """DP3's PointNet trunk: per point ``Dense -> LayerNorm -> ReLU`` for each ``(kernel, bias, scale, shift)`` of
    ``layers``, then the max over the points. ``(..., P, C) -> (..., layers[-1] width)``.

    Equal to the same network written with ``nn.Dense`` / ``nn.LayerNorm`` / ``jnp.max`` up to float32 rounding,
    gradients included (ties at the max share the gradient, as ``jnp.max``'s do). Its backward pass is written out
    (``_trunk_bwd``): it keeps only each layer's pre-norm output and its two statistics, recomputes the normalised
    activations in the same element-wise pass that uses them, and needs no broadcast copies, which autodiff of the
    modules wrote and read at every layer. With ``host_memory.keep_freed_memory`` the cpu-size HiPolicy train step
    at 512 points and batch 64 takes 382 instead of 1,257 ms (3.3x; ``benchmarks.studies.point_encoder``,
    PERFORMANCE.md), its loss within 6e-6 (relative) of the module version's over 200 steps.
    """
    return jnp.max(_trunk_forward(points, layers, eps)[0], axis=-2)


def _trunk_fwd(points, layers, eps):
    a, ys, means, rstds = _trunk_forward(points, layers, eps)
    pooled = jnp.max(a, axis=-2)
    # where each channel's maximum is, from the very values the max read (a recomputation could round differently)
    hit = a == pooled[..., None, :]
    return pooled, (points, layers, ys, means, rstds, hit)


def _trunk_bwd(eps, residuals, g_pooled):
    del eps
    points, layers, ys, means, rstds, hit = residuals
    count = jnp.sum(hit, axis=-2).astype(g_pooled.dtype)  # ties at the maximum share its gradient, as jnp.max's do
    g_a = jnp.where(hit, (g_pooled / count)[..., None, :], 0.0)
    grads = [None] * len(layers)
    for i in reversed(range(len(layers))):
        kernel, _, scale, shift = layers[i]
        normed = (ys[i] - means[i]) * rstds[i]
        g_z = jnp.where(_normed(ys[i], means[i], rstds[i], scale, shift) > 0, g_a, 0.0)  # the forward's ReLU
        g_normed = g_z * scale
        g_y = rstds[i] * (g_normed - jnp.mean(g_normed, -1, keepdims=True)
                          - normed * jnp.mean(g_normed * normed, -1, keepdims=True))
        if i > 0:  # the layer's input: the previous layer's activations, recomputed
            _, _, s_prev, b_prev = layers[i - 1]
            a_in = jax.nn.relu(_normed(ys[i - 1], means[i - 1], rstds[i - 1], s_prev, b_prev))
        else:
            a_in = points
        # the parameters' gradients sum over every point: as (points, features) matrices, so that the kernel's is
        # one plain matmul (contracting the leading axes in place made XLA copy both operands first)
        g_rows = _rows(g_y)
        grads[i] = (jnp.dot(_rows(a_in).T, g_rows), jnp.sum(g_rows, axis=0), jnp.sum(_rows(g_z * normed), axis=0),
                    jnp.sum(_rows(g_z), axis=0))
        g_a = jnp.dot(g_y, kernel.T)  # at i = 0: the points' gradient (dropped when the points are data)
    return g_a, tuple(grads)


point_trunk.defvjp(_trunk_fwd, _trunk_bwd)


class PointCloudEncoder(nn.Module):
    """DP3's PointNet-style encoder: ``(..., P, C) -> (..., out_dim)``.

    Per point ``Dense(64) -> LayerNorm -> ReLU -> Dense(128) -> LayerNorm -> ReLU -> Dense(256) -> LayerNorm -> ReLU``,
    max-pool over the ``P`` points (``point_trunk``, with its written-out backward pass), then
    ``Dense(out_dim) -> LayerNorm``. The parameters are ``nn.Dense``'s and ``nn.LayerNorm``'s (``dense_i``,
    ``norm_i``, ``out``, ``out_norm``), with their initial values.
    """

    out_dim: int = 64
    widths: tuple[int, ...] = (64, 128, 256)

    @nn.compact
    def __call__(self, points: jax.Array) -> jax.Array:
        layers, fan_in = [], points.shape[-1]
        for i, w in enumerate(self.widths):
            kernel, bias = _DenseParams(w, name=f"dense_{i}")(fan_in)
            scale, shift = _LayerNormParams(w, name=f"norm_{i}")()
            layers.append((kernel, bias, scale, shift))
            fan_in = w
        x = point_trunk(points.astype(jnp.float32), tuple(layers))
        x = nn.Dense(self.out_dim, name="out")(x)
        return nn.LayerNorm(name="out_norm")(x)


class ObsEncoder(nn.Module):
    """Encode a hierarchical observation window into the per-frequency condition ``(B, M, L_h * F)``.

    ``obs`` is a dict of arrays with leading dims ``(B, M, L_h)``:

    * ``state``: ``(B, M, L_h, D)``, always (only the first ``cfg.state_dims`` features are read when set);
    * ``image``: ``(B, M, L_h, image_size, image_size, 3)`` in [-1, 1] when ``cfg.obs_type == "image"``;
    * ``point_cloud``: ``(B, M, L_h, P, point_dims)`` when ``cfg.obs_type == "pointcloud"``.

    Each frame's feature is the state-MLP feature (``state_out``; the normalised state itself with
    ``state_encoder='identity'``, as Diffusion Policy's low-dim configs) concatenated with the image (``image_out``)
    or point-cloud (``point_out``) feature, all produced by one shared set of weights for every frequency and frame;
    ``F`` is the sum. With ``image_encoder='resnet_avgpool'`` the image feature (``image_channels[-1]``, 512 for
    ResNet-18) comes first and the state after it, as Diffusion Policy's ``MultiImageObsEncoder`` orders them: with
    the identity state, ``(B, M, L_h * (512 + D))``. Extra keys are ignored.

    ``frame_offsets`` (``(M, L_h)`` ints, ``data.windowing.obs_offsets``; ``PolicyNet`` passes it) says which time
    step each window position holds. The frequencies' windows overlap (strides 1/2/3 with ``L_h = 3`` cover 6
    distinct steps in 9 positions; every window ends at the current frame), so each distinct step is encoded once and
    its feature reused: 1.5x less encoder work for the defaults, which dominates with images or point clouds. This
    relies on windows built by ``data.windowing`` (equal offsets hold equal frames, also where episode starts are
    edge-padded); the first position holding an offset is the one encoded.

    A missing key, a wrong rank, a wrong trailing size or leading dims that disagree with ``state`` raise
    ``ValueError`` naming the key and the expected shape.
    """

    cfg: EncoderConfig
    frame_offsets: tuple[tuple[int, ...], ...] | None = None


    def _check(self, obs) -> tuple[int, int, int]:
        cfg = self.cfg
        specs = {"state": ("(B, M, L_h, D)", 4, None)}
        if cfg.obs_type == "image":
            specs["image"] = (f"(B, M, L_h, {cfg.image_size}, {cfg.image_size}, 3)", 6,
                              (cfg.image_size, cfg.image_size, 3))
        elif cfg.obs_type == "pointcloud":
            specs["point_cloud"] = (f"(B, M, L_h, P, {cfg.point_dims})", 5, (None, cfg.point_dims))
        lead = None
        for key, (expected, rank, tail) in specs.items():
            if key not in obs:
                raise ValueError(f"obs[{key!r}]: missing; obs_type={cfg.obs_type!r} expects shape {expected}, "
                                 f"got keys {sorted(obs)}")
            shape = tuple(jnp.shape(obs[key]))
            if len(shape) != rank:
                raise ValueError(f"obs[{key!r}]: expected shape {expected} (rank {rank}), got {shape}")
            if tail is not None and any(t is not None and t != s for t, s in zip(tail, shape[-len(tail):])):
                raise ValueError(f"obs[{key!r}]: expected shape {expected}, got {shape}")
            if key == "state" and cfg.state_dims is not None and shape[-1] < cfg.state_dims:
                raise ValueError(f"obs['state']: encoder.state_dims={cfg.state_dims} reads the first "
                                 f"{cfg.state_dims} features, got shape {shape} with D={shape[-1]}")
            if lead is None:
                lead = shape[:3]
            elif shape[:3] != lead:
                raise ValueError(f"obs[{key!r}]: expected shape {expected} with (B, M, L_h) = {lead} as in "
                                 f"obs['state'], got {shape}")
        return lead

    @nn.compact
    def __call__(self, obs, train: bool = False) -> jax.Array:
        b, m, lh = self._check(obs)
        cfg = self.cfg
        first, inverse = distinct_frames(self.frame_offsets, m, lh)
        keys = ("state", {"image": "image", "pointcloud": "point_cloud"}.get(cfg.obs_type))
        # (B, U, ...): one entry per distinct time step
        frames = {k: obs[k].reshape((b, m * lh) + obs[k].shape[3:])[:, first] for k in keys if k is not None}
        state = frames["state"] if cfg.state_dims is None else frames["state"][..., :cfg.state_dims]
        if cfg.state_encoder == "identity":  # Diffusion Policy low-dim: the normalised state itself
            feats = [state.astype(jnp.float32)]
        else:
            feats = [StateEncoder(cfg.state_hidden, cfg.state_out, name="state")(state)]
        if cfg.obs_type == "image" and cfg.image_encoder == "resnet_avgpool":
            crop = cfg.crop_size if cfg.crop_size < cfg.image_size else None
            # Diffusion Policy's MultiImageObsEncoder concatenates the rgb keys' features first, then the low-dim keys
            feats.insert(0, ResNetAvgPoolEncoder(cfg.image_channels, crop, name="image")(frames["image"], train=train))
        elif cfg.obs_type == "image":
            feats.append(ImageEncoder(cfg.image_channels, cfg.num_keypoints, cfg.image_out, cfg.crop_size,
                                      name="image")(frames["image"], train=train))
        elif cfg.obs_type == "pointcloud":
            feats.append(PointCloudEncoder(cfg.point_out, name="point_cloud")(frames["point_cloud"]))
        frame = jnp.concatenate(feats, axis=-1)[:, inverse]  # (B, U, F) -> (B, M*L_h, F)
        return frame.reshape(b, m, lh * frame.shape[-1])


def distinct_frames(frame_offsets, m: int, lh: int) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)`` over the flattened ``(M, L_h)`` window positions: ``first`` (U,) the first position of
    each distinct offset, ``inverse`` (M*L_h,) the distinct offset of each position (identity without offsets)."""
    if frame_offsets is None:
        return np.arange(m * lh), np.arange(m * lh)
    offsets = np.asarray(frame_offsets, np.int64)
    if offsets.shape != (m, lh):
        raise ValueError(f"frame_offsets: expected shape (M, L_h) = {(m, lh)} as the observations, got "
                         f"{offsets.shape}")
    _, first, inverse = np.unique(offsets.reshape(-1), return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)

