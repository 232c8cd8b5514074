"""Networks, the encoder and denoiser stages of the flow: observation windows -> condition -> denoised chunk.

    data (windows, ``data.windowing``) -> **encoders** (``ObsEncoder``) -> **denoiser** (``ConditionalUnet1D``)
    -> generative head (``heads``: what the denoiser's output means) -> sampling (``hipolicy_jax.sampling``)

* ``encoders``: ``ObsEncoder`` turns a window ``{key: (B, M, L_h, ...)}`` into the per-frequency condition
  ``(B, M, L_h * F)`` from one shared per-frame encoder: ``StateEncoder`` (an MLP, or the raw state with
  ``state_encoder='identity'``) plus ``ImageEncoder`` (robomimic's ResNet-18 with spatial softmax),
  ``ResNetAvgPoolEncoder`` (Diffusion Policy's ResNet-18 with average pooling) or ``PointCloudEncoder`` (DP3's);
  ``SpatialSoftmax`` and ``crop_images`` are their pieces.
* ``unet``: ``ConditionalUnet1D``, Diffusion Policy's conditional 1D U-Net with HiPolicy's hierarchical FiLM and
  global fusion (``SegmentFusion``, or the release's constant ``ReleaseFusionAttention``), built from
  ``ConditionalResidualBlock1D``, ``Conv1dBlock`` and ``StepEncoder``; ``(B, M*L_c, A)`` noisy chunk, time,
  ``(B, M, Dc)`` condition -> ``(B, M*L_c, A)``.
* ``policy_net``: ``PolicyNet`` (encoder + U-Net from a ``PolicyConfig``, with the methods the sampler calls:
  ``encode``, ``denoise``, ``film_condition`` / ``film_steps`` / ``denoise_film``), ``init_policy_params``,
  ``init_variables`` and ``param_count``.

Public names re-exported here: ``ObsEncoder``, ``StateEncoder``, ``ImageEncoder``, ``ResNetAvgPoolEncoder``,
``PointCloudEncoder``, ``SpatialSoftmax``, ``crop_images``; ``ConditionalUnet1D``, ``ConditionalResidualBlock1D``,
``Conv1dBlock``, ``SegmentFusion``, ``ReleaseFusionAttention``, ``StepEncoder``; ``PolicyNet``,
``init_policy_params``, ``init_variables``, ``param_count``. Other names come from their module (``unet.conv1d``,
``unet.mish``, ``unet.lowp_kernels``, ...). Within ``hipolicy_jax`` this package imports only ``config`` and
``data.windowing``.
"""

from hipolicy_jax.models.encoders import (
    ImageEncoder,
    ObsEncoder,
    PointCloudEncoder,
    ResNetAvgPoolEncoder,
    SpatialSoftmax,
    StateEncoder,
    crop_images,
)
from hipolicy_jax.models.policy_net import PolicyNet, init_policy_params, init_variables, param_count
from hipolicy_jax.models.unet import (
    ConditionalResidualBlock1D,
    ConditionalUnet1D,
    Conv1dBlock,
    ReleaseFusionAttention,
    SegmentFusion,
    StepEncoder,
)

__all__ = [
    "ConditionalResidualBlock1D",
    "ConditionalUnet1D",
    "Conv1dBlock",
    "ImageEncoder",
    "ObsEncoder",
    "PointCloudEncoder",
    "PolicyNet",
    "ReleaseFusionAttention",
    "ResNetAvgPoolEncoder",
    "SegmentFusion",
    "StepEncoder",
    "SpatialSoftmax",
    "StateEncoder",
    "crop_images",
    "init_policy_params",
    "init_variables",
    "param_count",
]
