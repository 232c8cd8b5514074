"""Diffusion Policy's / the HiPolicy release's ``ConditionalUnet1D`` state dict -> our ``ConditionalUnet1D`` params.

Input: ``{torch name: np.ndarray}`` (e.g. ``model.down_modules.0.0.blocks.0.block.0.weight``) and a prefix
(``model.`` for a policy's state dict, ``""`` for the U-Net's own). Output: the parameter tree of
``models.unet.ConditionalUnet1D`` (float32 numpy). Layouts:

* ``Conv1d`` weight ``(O, I, k)`` -> kernel ``(k, I, O)`` (both cross-correlate); ``Linear`` ``(O, I)`` -> ``(I, O)``;
  GroupNorm ``weight`` -> ``scale``.
* ``ConvTranspose1d(C, C, 4, 2, 1)`` weight ``(I, O, 4)`` -> ``Upsample1d`` kernel ``(4, I, O)`` with its taps
  reversed: torch's ``y[2i] = x[i]·w1 + x[i-1]·w3`` is our ``x[i-1]·w0 + x[i]·w2``.
* FiLM ``cond_encoder.1`` (``cond_predict_scale=True``: ``(2C, d + Dc)``, scale rows then bias rows, as our
  ``film``). Diffusion Policy's ``cond_predict_scale=False`` adds the embedding as a bias only; it maps exactly onto
  scale-and-bias FiLM with the scale rows' weights 0 and bias 1.
* The release's fusion (``global_feature_extractor``): ``cls_tokens (1, 1, D)``, ``nn.MultiheadAttention``'s
  ``in_proj_weight (3D, D)`` (query, key, value rows), ``in_proj_bias`` and ``out_proj``. For
  ``fusion_kind='release'`` (the function the release computes) only the value and output projections matter. For
  ``fusion_kind='attention'`` every projection is mapped, with the token's features reordered: the release flattens
  a segment ``(C, L)`` channels first, ours ``(L, C)`` time first, so feature ``l*C + c`` of ours is the release's
  ``c*L + l``.

Every expected name must be present with the expected shape and every name under the prefix must be used: a
``ValueError`` names the first that is not.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import numpy as np

FusionKind = str  # "attention" | "release"


class _Reader:
    """Takes tensors out of a state dict by name, checking shapes; remembers what it took."""

    def __init__(self, state: Mapping[str, np.ndarray], prefix: str, what: str):
        self.state, self.prefix, self.what, self.used = state, prefix, what, set()

    def has(self, name: str) -> bool:
        return self.prefix + name in self.state

    def get(self, name: str, shape: tuple[int | None, ...] | None = None) -> np.ndarray:
        key = self.prefix + name
        if key not in self.state:
            near = sorted(k for k in self.state if k.startswith(key.rsplit(".", 1)[0]))[:4]
            raise ValueError(f"{self.what}: state dict has no {key!r}" + (f" (near: {near})" if near else ""))
        x = np.asarray(self.state[key], dtype=np.float32)
        if shape is not None and (x.ndim != len(shape) or any(e is not None and e != s for e, s in zip(shape, x.shape))):
            want = "(" + ", ".join("?" if e is None else str(e) for e in shape) + ")"
            raise ValueError(f"{self.what}: {key!r} has shape {x.shape}, expected {want}")
        self.used.add(key)
        return x

    def unused(self) -> list[str]:
        return sorted(k for k in self.state if k.startswith(self.prefix) and k not in self.used)


def _conv(r: _Reader, name: str, out_ch: int | None = None, in_ch: int | None = None, k: int | None = None) -> dict:
    w = r.get(f"{name}.weight", (out_ch, in_ch, k))
    return {"kernel": np.ascontiguousarray(w.transpose(2, 1, 0)), "bias": r.get(f"{name}.bias", (w.shape[0],))}


def _linear(r: _Reader, name: str, out_f: int | None = None, in_f: int | None = None) -> dict:
    w = r.get(f"{name}.weight", (out_f, in_f))
    return {"kernel": np.ascontiguousarray(w.T), "bias": r.get(f"{name}.bias", (w.shape[0],))}


def _block(r: _Reader, name: str, out_ch: int, in_ch: int | None = None) -> dict:
    """``Conv1dBlock``: ``block.0`` Conv1d, ``block.1`` GroupNorm (``block.2`` Mish has no parameters)."""
    conv = _conv(r, f"{name}.block.0", out_ch, in_ch)
    return {"conv": conv, "norm": {"scale": r.get(f"{name}.block.1.weight", (out_ch,)),
                                   "bias": r.get(f"{name}.block.1.bias", (out_ch,))}}


def _token_perm(channels: int, length: int) -> np.ndarray:
    """``perm[l*C + c] = c*L + l``: our (L, C) token feature index -> the release's (C, L) one."""
    l, c = np.meshgrid(np.arange(length), np.arange(channels), indexing="ij")
    return (c * length + l).reshape(-1)


def _fusion(r: _Reader, name: str, channels: int, length: int, heads: int, kind: FusionKind) -> dict:
    d = channels * length
    if d % heads:
        raise ValueError(f"{r.what}: {name} tokens are {d} wide, not divisible by fusion_heads={heads}")
    hd = d // heads
    cls = r.get(f"{name}.cls_tokens", (1, 1, d))
    w_in = r.get(f"{name}.cross_attention.in_proj_weight", (3 * d, d))
    b_in = r.get(f"{name}.cross_attention.in_proj_bias", (3 * d,))
    w_out = r.get(f"{name}.cross_attention.out_proj.weight", (d, d))
    b_out = r.get(f"{name}.cross_attention.out_proj.bias", (d,))

    def proj(i: int, perm: np.ndarray) -> dict:  # torch (out, in) rows of q / k / v -> DenseGeneral (D, H, hd)
        w, b = w_in[i * d:(i + 1) * d], b_in[i * d:(i + 1) * d]
        return {"kernel": np.ascontiguousarray(w.T[perm].reshape(d, heads, hd)), "bias": b.reshape(heads, hd)}

    if kind == "release":  # input and output stay in the release's (C, L) order (SegmentFusion reshapes so)
        ident = np.arange(d)
        return {"cls": cls, "attention": {"value": proj(2, ident), "out": {
            "kernel": np.ascontiguousarray(w_out.T.reshape(heads, hd, d)), "bias": b_out}}}
    perm = _token_perm(channels, length)
    return {"cls": cls[..., perm], "attention": {
        "query": proj(0, perm), "key": proj(1, perm), "value": proj(2, perm),
        "out": {"kernel": np.ascontiguousarray(w_out.T[:, perm].reshape(heads, hd, d)), "bias": b_out[perm]}}}


def _res_block(r: _Reader, name: str, in_ch: int, out_ch: int, cond_dim: int, fusion: dict | None) -> dict:
    """One ``ConditionalResidualBlock1D``; ``fusion``: ``{length, heads, kind}`` for the release's fusion blocks."""
    wide = 2 if fusion is not None else 1
    p = {"block0": _block(r, f"{name}.blocks.0", wide * out_ch, wide * in_ch),
         "block1": _block(r, f"{name}.blocks.1", out_ch, wide * out_ch)}
    w = r.get(f"{name}.cond_encoder.1.weight", (None, cond_dim))
    b = r.get(f"{name}.cond_encoder.1.bias", (w.shape[0],))
    if w.shape[0] == 2 * out_ch:  # cond_predict_scale=True: [scale; bias] rows
        p["film"] = {"kernel": np.ascontiguousarray(w.T), "bias": b}
    elif w.shape[0] == out_ch:  # bias-only FiLM: scale fixed at 1
        if fusion is not None:  # the release skips FiLM entirely in this case; no checkpoint of it is known
            raise ValueError(f"{r.what}: {name} has a bias-only FiLM (cond_predict_scale=False) in a fusion block; "
                             f"the release uses cond_predict_scale=True")
        p["film"] = {"kernel": np.concatenate([np.zeros_like(w.T), w.T], axis=1),
                     "bias": np.concatenate([np.ones_like(b), b])}
    else:
        raise ValueError(f"{r.what}: {r.prefix}{name}.cond_encoder.1.weight has shape {w.shape}, expected "
                         f"({2 * out_ch} or {out_ch}, {cond_dim})")
    if r.has(f"{name}.residual_conv.weight"):
        p["residual"] = _conv(r, f"{name}.residual_conv", out_ch, in_ch, 1)
    elif in_ch != out_ch:
        raise ValueError(f"{r.what}: state dict has no {r.prefix}{name}.residual_conv.weight ({in_ch} -> {out_ch} "
                         f"channels needs one)")
    if fusion is not None:
        p["fusion"] = _fusion(r, f"{name}.global_feature_extractor", in_ch, fusion["length"], fusion["heads"],
                              fusion["kind"])
    return p


def unet_shape(state: Mapping[str, np.ndarray], prefix: str = "model.") -> dict:
    """What a state dict's U-Net is: ``{down_dims, kernel_size, step_embed_dim, action_dim, cond_dim,
    hierarchical, local_cond}`` read off its tensor shapes (``cond_dim`` = the FiLM input minus the step embedding:
    Diffusion Policy's ``global_cond_dim``; for the release, one stride's condition)."""
    r = _Reader(state, prefix, "unet")
    levels = sorted({int(m.group(1)) for k in state if (m := re.match(re.escape(prefix) + r"down_modules\.(\d+)\.", k))})
    if not levels:
        raise ValueError(f"unet: no {prefix}down_modules.* in the state dict; is the prefix right? "
                         f"(first keys: {sorted(state)[:5]})")
    dims = [int(r.get(f"down_modules.{i}.1.blocks.1.block.0.weight").shape[0]) for i in levels]
    first = r.get("down_modules.0.0.blocks.0.block.0.weight")
    hier = r.has("down_modules.0.0.global_feature_extractor.cls_tokens")
    step = int(r.get("diffusion_step_encoder.3.weight").shape[0])
    film_in = int(r.get("down_modules.0.0.cond_encoder.1.weight").shape[1])
    return {"down_dims": tuple(dims), "kernel_size": int(first.shape[2]), "step_embed_dim": step,
            "action_dim": int(first.shape[1]) // (2 if hier else 1), "cond_dim": film_in - step,
            "hierarchical": hier, "local_cond": r.has("local_cond_encoder.0.blocks.0.block.0.weight")}


def unet_params(state: Mapping[str, np.ndarray], prefix: str = "model.", *, chunk_len: int = 8,
                fusion_heads: int = 8, fusion_kind: FusionKind = "release") -> dict:
    """Our ``ConditionalUnet1D`` parameter tree from a Diffusion Policy or release U-Net state dict.

    ``chunk_len`` (L_c) and ``fusion_heads`` only matter for the release's fusion (its tokens are ``C * L_c`` wide);
    ``fusion_kind`` says which of our fusions the weights are mapped for (``'release'``: the release's function).
    Raises ``ValueError`` naming the missing or mis-shaped tensor, or the first tensor left unused.
    """
    shape = unet_shape(state, prefix)
    if shape["local_cond"]:
        raise ValueError(f"unet: {prefix}local_cond_encoder.* is present (obs_as_local_cond=True); only "
                         f"obs_as_global_cond=True policies are supported")
    r = _Reader(state, prefix, "unet")
    dims, d = shape["down_dims"], shape["step_embed_dim"]
    a, cond = shape["action_dim"], d + shape["cond_dim"]
    p = {"step_dense0": _linear(r, "diffusion_step_encoder.1", 4 * d, d),
         "step_dense1": _linear(r, "diffusion_step_encoder.3", d, 4 * d)}
    chans = (a,) + dims
    for i, ch in enumerate(dims):
        fuse = ({"length": chunk_len // 2 ** i, "heads": fusion_heads, "kind": fusion_kind}
                if shape["hierarchical"] and i == 0 else None)
        p[f"down{i}_res0"] = _res_block(r, f"down_modules.{i}.0", chans[i], ch, cond, fuse)
        p[f"down{i}_res1"] = _res_block(r, f"down_modules.{i}.1", ch, ch, cond, fuse)
        if i < len(dims) - 1:
            p[f"down{i}_downsample"] = _conv(r, f"down_modules.{i}.2.conv", ch, ch, 3)
    p["mid_res0"] = _res_block(r, "mid_modules.0", dims[-1], dims[-1], cond, None)
    p["mid_res1"] = _res_block(r, "mid_modules.1", dims[-1], dims[-1], cond, None)
    for j, ch in enumerate(reversed(dims[:-1])):
        wide = dims[len(dims) - 1 - j]
        p[f"up{j}_res0"] = _res_block(r, f"up_modules.{j}.0", 2 * wide, ch, cond, None)
        p[f"up{j}_res1"] = _res_block(r, f"up_modules.{j}.1", ch, ch, cond, None)
        w = r.get(f"up_modules.{j}.2.conv.weight", (ch, ch, 4))  # ConvTranspose1d: (in, out, k)
        p[f"up{j}_upsample"] = {"kernel": np.ascontiguousarray(w[:, :, ::-1].transpose(2, 0, 1)),
                                "bias": r.get(f"up_modules.{j}.2.conv.bias", (ch,))}
    p["final_block"] = _block(r, "final_conv.0", dims[0], dims[0])
    p["final_conv"] = _conv(r, "final_conv.1", a, dims[0], 1)
    left = r.unused()
    if left:
        raise ValueError(f"unet: {len(left)} tensors of the state dict were not mapped, e.g. {left[:3]}; is it a "
                         f"ConditionalUnet1D of Diffusion Policy or the HiPolicy release?")
    return p


__all__ = ["unet_params", "unet_shape"]
