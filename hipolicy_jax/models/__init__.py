"""Networks: observation encoders, the conditional 1D U-Net denoiser and the combined ``PolicyNet``."""

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
