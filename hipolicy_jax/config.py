"""Frozen configuration dataclasses for hipolicy_jax.

Every config is immutable and validates itself in ``__post_init__``: a bad value raises ``ValueError`` naming the
field and what was expected. Derived quantities are properties, never written back. The top-level ``Config`` is what
``tyro`` exposes on the command line (``--chunk.strides 1 2 4``, ``--model.size paper``, ...).

Frequency layout
----------------
``ChunkConfig.strides`` is strictly ascending (1, 2, 3): stride 1 is the highest frequency (the control rate).
The action chunk the model predicts concatenates one ``chunk_len`` segment per stride along time, from the lowest
to the highest frequency, i.e. in *descending* stride order (``segment_strides`` = (3, 2, 1)), as the reference
release does. Every per-frequency axis in the code base (observation windows, conditions, FiLM parameters) uses
this segment order. With a single stride the model is exactly a single-frequency Diffusion Policy.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

ObsType = Literal["state", "image", "pointcloud"]
ConditionMode = Literal["hier", "low", "high"]
PredictionType = Literal["epsilon", "sample"]
Objective = Literal["diffusion", "flow"]
ModelSize = Literal["cpu", "paper", "tiny"]
ActionKind = Literal["absolute", "delta"]
ACTION_KINDS: tuple[str, ...] = ("absolute", "delta")


def _require(cond: bool, field: str, msg: str) -> None:
    if not cond:
        raise ValueError(f"{field}: {msg}")


def check_action_kinds(kinds, field: str, action_dim: int | None = None) -> tuple[str, ...]:
    """``kinds`` as a tuple of ``ACTION_KINDS`` strings, one per action dimension (``action_dim`` of them when
    given); anything else raises a one-line ``ValueError`` naming ``field`` and what was expected."""
    expected = "a sequence of 'absolute' / 'delta', one per action dimension"
    _require(kinds is not None and not isinstance(kinds, str), field, f"expected {expected}, got {kinds!r}")
    kinds = tuple(kinds)
    bad = [k for k in kinds if k not in ACTION_KINDS]
    _require(not bad, field,
             f"each kind must be 'absolute' or 'delta', got {', '.join(map(repr, bad))} in {list(kinds)}")
    _require(len(kinds) >= 1, field, f"expected {expected}, got none")
    _require(action_dim is None or len(kinds) == action_dim, field,
             f"expected {action_dim} kinds (one per action dimension), got {len(kinds)}: {list(kinds)}")
    return kinds


@dataclasses.dataclass(frozen=True)
class ChunkConfig:
    """Multi-frequency observation windows and action chunks.

    For a current index t and stride s: observation frames o[t-(L_h-1)s], ..., o[t-s], o[t] and action frames
    a[t+δ], a[t+δ+s], ..., a[t+δ+(L_c-1)s] with δ = ``action_offset``.

    ``action_kinds`` says, per action dimension, what an action is: ``'absolute'`` (a target: a stride-s segment
    samples every s-th recorded action) or ``'delta'`` (a displacement from where the robot is: a stride-s
    segment's action i is the SUM of the s recorded deltas of its block, so it carries the block's motion;
    ``data.windowing.segment_actions``). It changes what the network predicts, so it is part of the trained policy.
    None (the default, and every run trained before it existed): not declared here; the policy's actions are all
    absolute, and training (``runs.train``) takes the demo buffer's kinds instead, storing them here when any is a
    delta.
    """

    strides: tuple[int, ...] = (1, 2, 3)
    obs_horizon: int = 3  # L_h
    chunk_len: int = 8  # L_c
    # δ: the chunk's first action is for frame t+δ. The release predicts from the step after the current frame (1).
    # Diffusion Policy predicts from the first observed frame, δ = -(L_h-1) (its horizon covers the observed steps
    # too); the actions before the current frame are predicted and never executed. δ < 0 needs a single stride.
    action_offset: int = 1
    # Actions executed per decision, from the first action for a frame >= t (Diffusion Policy's n_action_steps).
    # None: all of them, L_c - max(0, -δ), what HiPolicy and our defaults do.
    exec_len: int | None = None
    # Per action dimension 'absolute' or 'delta' (the class docstring); None: every dimension absolute / the
    # buffer's kinds at training.
    action_kinds: tuple[ActionKind, ...] | None = None

    def __post_init__(self):
        if self.action_kinds is not None:
            object.__setattr__(self, "action_kinds", check_action_kinds(self.action_kinds, "chunk.action_kinds"))
        s = tuple(self.strides)
        _require(len(s) >= 1, "chunk.strides", "needs at least one stride")
        _require(all(isinstance(x, int) and x >= 1 for x in s), "chunk.strides",
                 f"must be positive integers, got {s}")
        _require(all(a < b for a, b in zip(s, s[1:])), "chunk.strides", f"must be strictly ascending, got {s}")
        _require(self.obs_horizon >= 1, "chunk.obs_horizon", f"(L_h) must be >= 1, got {self.obs_horizon}")
        _require(self.chunk_len >= 1, "chunk.chunk_len", f"(L_c) must be >= 1, got {self.chunk_len}")
        _require(-(self.obs_horizon - 1) <= self.action_offset <= 1, "chunk.action_offset",
                 f"must be in [-(obs_horizon-1), 1] = [{-(self.obs_horizon - 1)}, 1], got {self.action_offset}")
        _require(self.action_offset >= 0 or len(s) == 1, "chunk.action_offset",
                 f"a negative offset (actions for observed frames, Diffusion Policy's layout) needs a single stride, "
                 f"got {self.action_offset} with strides {s}")
        _require(self.action_offset > -self.chunk_len, "chunk.action_offset",
                 f"leaves no action for the current frame: chunk_len={self.chunk_len}, got {self.action_offset}")
        _require(self.exec_len is None or 1 <= self.exec_len <= self.chunk_len - max(0, -self.action_offset),
                 "chunk.exec_len", f"must be None or in [1, chunk_len - max(0, -action_offset)] = "
                 f"[1, {self.chunk_len - max(0, -self.action_offset)}], got {self.exec_len}")
        object.__setattr__(self, "strides", s)

    @property
    def num_freqs(self) -> int:
        """M, the number of frequencies."""
        return len(self.strides)

    @property
    def segment_strides(self) -> tuple[int, ...]:
        """Strides in chunk-segment order: lowest frequency (largest stride) first."""
        return tuple(sorted(self.strides, reverse=True))

    @property
    def horizon(self) -> int:
        """Length of the concatenated chunk, M·L_c."""
        return self.num_freqs * self.chunk_len

    @property
    def obs_span(self) -> int:
        """Base-rate frames of history needed to serve every stride: (L_h-1)·max(s) + 1."""
        return (self.obs_horizon - 1) * max(self.strides) + 1

    @property
    def exec_start(self) -> int:
        """Index in a segment of the first executed action: the first for a frame >= t, max(0, -δ)."""
        return max(0, -self.action_offset)

    @property
    def exec_steps(self) -> int:
        """Actions executed per decision (at most; AAC may stop earlier): ``exec_len`` or L_c - ``exec_start``."""
        return self.exec_len if self.exec_len is not None else self.chunk_len - self.exec_start

    @property
    def action_span(self) -> int:
        """Base-rate action steps covered by the longest chunk: δ + (L_c-1)·max(s) + 1."""
        return self.action_offset + (self.chunk_len - 1) * max(self.strides) + 1

    def kinds(self, action_dim: int) -> tuple[str, ...]:
        """The ``action_dim`` kinds of the policy's actions: ``action_kinds`` (checked against ``action_dim``), or
        every dimension ``'absolute'`` when None."""
        if self.action_kinds is None:
            return ("absolute",) * action_dim
        return check_action_kinds(self.action_kinds, "chunk.action_kinds", action_dim)

    @property
    def has_delta(self) -> bool:
        """Whether any action dimension is a delta (segments then hold summed deltas, per-segment statistics)."""
        return self.action_kinds is not None and "delta" in self.action_kinds


# Named U-Net sizes: (down_dims, kernel_size, step_embed_dim).
MODEL_SIZES: dict[str, tuple[tuple[int, ...], int, int]] = {
    "paper": ((256, 512, 1024), 5, 128),
    "cpu": ((64, 128, 256), 5, 64),
    "tiny": ((16, 32), 3, 16),
}


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
    """Observation encoders. ``obs_type`` picks state-only, image (+state) or point cloud (+state)."""

    obs_type: ObsType = "state"
    state_encoder: Literal["mlp", "identity"] = "mlp"  # identity: the raw (normalised) state window is the
    # condition, as Diffusion Policy's low-dim configs
    state_hidden: tuple[int, ...] = (256, 256)  # low-dim MLP hidden sizes
    state_out: int = 64  # per-frame feature size of the state MLP
    # read only the first state_dims features of state (None: all). The MJX tasks' first 4 are proprioception (TCP
    # xyz, gripper opening), the rest object poses: vision policies use 4 and see objects only through the camera
    state_dims: int | None = None
    # image encoder (ResNet-18 style trunk with GroupNorm, spatial softmax)
    image_size: int = 84  # input H = W
    crop_size: int = 76  # random crop in training, centre crop at evaluation
    image_channels: tuple[int, ...] = (64, 128, 256, 512)  # ResNet stage widths; "cpu" configs use smaller
    num_keypoints: int = 32
    image_out: int = 64
    # The image encoder's head. 'spatial_softmax': robomimic's VisualCore, as Diffusion Policy's hybrid configs
    # (the trunk above, spatial soft-argmax, Linear(image_out)). 'resnet_avgpool': what DP's MultiImageObsEncoder
    # builds and the HiPolicy release uses: torchvision ResNet-18 with every BatchNorm replaced by GroupNorm(C // 16),
    # fc removed (the image_channels[-1] = 512-D global average pool; num_keypoints and image_out unused), ImageNet
    # mean/std applied to the [-1, 1] image as DP does, image feature before the state (DP: rgb keys, then low-dim
    # keys). ImageNet normalisation belongs to the kind, not a flag: the release and every DP config that builds
    # this encoder set imagenet_norm=True. Release values with it: image_channels (64, 128, 256, 512), crop_size =
    # image_size (no crop), state_encoder 'identity'. Default 'spatial_softmax': our trained runs use it.
    image_encoder: Literal["spatial_softmax", "resnet_avgpool"] = "spatial_softmax"
    # point-cloud encoder (DP3)
    num_points: int = 512
    point_sampling: Literal["random", "fps"] = "random"  # down-sampling of the camera's points; DP3: fps
    point_dims: int = 3  # 3 = xyz, 6 = xyz+rgb
    point_out: int = 64

    def __post_init__(self):
        _require(self.obs_type in ("state", "image", "pointcloud"), "encoder.obs_type",
                 f"must be 'state', 'image' or 'pointcloud', got {self.obs_type!r}")
        _require(0 < self.crop_size <= self.image_size, "encoder.crop_size",
                 f"must be in (0, image_size={self.image_size}], got {self.crop_size}")
        _require(self.point_dims in (3, 6), "encoder.point_dims",
                 f"must be 3 (xyz) or 6 (xyz+rgb), got {self.point_dims}")
        _require(self.point_sampling in ("random", "fps"), "encoder.point_sampling",
                 f"must be 'random' or 'fps' (farthest-point), got {self.point_sampling!r}")
        _require(self.state_encoder in ("mlp", "identity"), "encoder.state_encoder",
                 f"must be 'mlp' or 'identity', got {self.state_encoder!r}")
        _require(self.num_points >= 1, "encoder.num_points", f"must be >= 1, got {self.num_points}")
        _require(self.state_dims is None or self.state_dims >= 1, "encoder.state_dims",
                 f"must be None (all) or >= 1, got {self.state_dims}")
        _require(len(self.image_channels) >= 1, "encoder.image_channels", "needs at least one stage")
        _require(self.image_encoder in ("spatial_softmax", "resnet_avgpool"), "encoder.image_encoder",
                 f"must be 'spatial_softmax' or 'resnet_avgpool', got {self.image_encoder!r}")
        _require(self.image_encoder != "resnet_avgpool"
                 or all(c >= 16 and c % (c // 16) == 0 for c in self.image_channels), "encoder.image_channels",
                 f"image_encoder='resnet_avgpool' normalises with GroupNorm(C // 16) as Diffusion Policy: every "
                 f"width C must be >= 16 and divisible by C // 16, got {self.image_channels}")
        _require(self.num_keypoints >= 1, "encoder.num_keypoints", f"must be >= 1, got {self.num_keypoints}")

    @property
    def obs_keys(self) -> tuple[str, ...]:
        """Observation keys the policy reads: state always, plus the image or point cloud."""
        return {"state": ("state",), "image": ("state", "image"), "pointcloud": ("state", "point_cloud")}[self.obs_type]


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Conditional 1D U-Net denoiser (Diffusion Policy semantics) with HiPolicy's hierarchical FiLM and fusion.

    ``down_dims`` / ``kernel_size`` / ``step_embed_dim`` left as None take the values of the named ``size``.
    """

    size: ModelSize = "cpu"
    down_dims: tuple[int, ...] | None = None
    kernel_size: int | None = None
    step_embed_dim: int | None = None
    n_groups: int = 8
    condition: ConditionMode = "hier"  # hier: each segment its own frequency's obs; low / high: all segments one
    fusion: bool = True  # CLS-token attention across frequency segments (inactive when M = 1)
    fusion_heads: int = 8
    # None: the paper's fusion (attention over full L_c·C-wide segment tokens). An int: the lighter variant that
    # projects each segment token to this width before the attention (a model change with fewer parameters).
    fusion_token_dim: int | None = None
    # What the fusion computes. 'attention' (default): CLS-token attention over each sample's segment tokens, as the
    # paper describes. 'release': the HiPolicy release's function, which is a learned constant: its
    # nn.MultiheadAttention (batch_first=False) fed (B, M+1, D) attends along the batch, so the CLS output is
    # out_proj(v_proj(cls)) for every input. Kept to run the release's weights exactly (experiments.import_checkpoint)
    # and to measure, in the ablation, what real attention adds over that constant; not the default, because a
    # constant cannot fuse anything.
    fusion_kind: Literal["attention", "release"] = "attention"
    # Operand dtype of the U-Net's convolutions and fusion attention (float32 accumulation, parameters, norms):
    # 'bfloat16' runs them as bf16 matmuls (BF16 dot-product / AMX instructions where the CPU has them).
    compute_dtype: Literal["float32", "bfloat16"] = "float32"

    def __post_init__(self):
        _require(self.compute_dtype in ("float32", "bfloat16"), "model.compute_dtype",
                 f"must be 'float32' or 'bfloat16', got {self.compute_dtype!r}")
        _require(self.size in MODEL_SIZES, "model.size", f"must be one of {sorted(MODEL_SIZES)}, got {self.size!r}")
        _require(self.condition in ("hier", "low", "high"), "model.condition",
                 f"must be 'hier', 'low' or 'high', got {self.condition!r}")
        dims = self.unet_dims
        _require(len(dims) >= 1 and all(d >= 1 for d in dims), "model.down_dims", f"must be positive, got {dims}")
        _require(all(d % self.n_groups == 0 for d in dims), "model.down_dims",
                 f"every width must be divisible by n_groups={self.n_groups}, got {dims}")
        _require(self.unet_kernel % 2 == 1, "model.kernel_size", f"must be odd, got {self.unet_kernel}")
        _require(self.unet_step_embed % 2 == 0, "model.step_embed_dim", f"must be even, got {self.unet_step_embed}")
        _require(self.fusion_heads >= 1, "model.fusion_heads", f"must be >= 1, got {self.fusion_heads}")
        _require(self.fusion_token_dim is None or self.fusion_token_dim >= 1, "model.fusion_token_dim",
                 f"must be None or >= 1, got {self.fusion_token_dim}")
        _require(self.fusion_kind in ("attention", "release"), "model.fusion_kind",
                 f"must be 'attention' or 'release', got {self.fusion_kind!r}")
        _require(self.fusion_kind == "attention" or self.fusion_token_dim is None, "model.fusion_token_dim",
                 f"the release's fusion (model.fusion_kind='release') has full-width tokens; pass None, got "
                 f"{self.fusion_token_dim}")

    @property
    def unet_dims(self) -> tuple[int, ...]:
        return tuple(self.down_dims) if self.down_dims is not None else MODEL_SIZES[self.size][0]

    @property
    def unet_kernel(self) -> int:
        return self.kernel_size if self.kernel_size is not None else MODEL_SIZES[self.size][1]

    @property
    def unet_step_embed(self) -> int:
        return self.step_embed_dim if self.step_embed_dim is not None else MODEL_SIZES[self.size][2]

    @property
    def downsample_factor(self) -> int:
        """Total temporal down-sampling of the U-Net: 2^(levels-1) (the last level does not down-sample)."""
        return 2 ** (len(self.unet_dims) - 1)


@dataclasses.dataclass(frozen=True)
class DiffusionConfig:
    """The diffusion head's training objective: DDPM noise schedule and prediction type (Diffusion Policy defaults).

    How a trained diffusion head is sampled (DDPM, DDIM, number of steps) is an inference setting
    (``InferenceConfig``), not part of the trained policy.
    """

    num_train_steps: int = 100
    beta_schedule: Literal["squaredcos_cap_v2", "linear"] = "squaredcos_cap_v2"
    beta_start: float = 1e-4  # linear schedule only
    beta_end: float = 0.02  # linear schedule only
    prediction_type: PredictionType = "epsilon"  # DP: epsilon; DP3: sample
    clip_sample: bool = True
    clip_range: float = 1.0

    def __post_init__(self):
        _require(self.num_train_steps >= 1, "diffusion.num_train_steps", f"must be >= 1, got {self.num_train_steps}")
        _require(self.prediction_type in ("epsilon", "sample"), "diffusion.prediction_type",
                 f"must be 'epsilon' or 'sample', got {self.prediction_type!r}")
        _require(self.beta_schedule in ("squaredcos_cap_v2", "linear"), "diffusion.beta_schedule",
                 f"must be 'squaredcos_cap_v2' or 'linear', got {self.beta_schedule!r}")
        _require(self.clip_range > 0, "diffusion.clip_range", f"must be > 0, got {self.clip_range}")


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    """The flow-matching head's training objective (conditional flow matching, linear / OT path, as openpi).

    ``x_τ = τ·ε + (1−τ)·a`` with τ = 1 pure noise and τ = 0 the action chunk; the network predicts the velocity
    ``ε − a`` from ``x_τ`` and the time input ``τ·time_scale`` (so the sinusoidal step embedding sees the same range
    as the diffusion head's integer timesteps). Training draws τ uniformly, or from openpi's ``Beta(1.5, 1)``
    (more weight on noisy times) with ``time_sampling='beta'``.
    """

    time_sampling: Literal["uniform", "beta"] = "uniform"
    time_scale: float = 100.0
    clip_sample: bool = True  # clip the final sample to [-clip_range, clip_range] (the normalised action range)
    clip_range: float = 1.0

    def __post_init__(self):
        _require(self.time_sampling in ("uniform", "beta"), "flow.time_sampling",
                 f"must be 'uniform' or 'beta', got {self.time_sampling!r}")
        _require(self.time_scale > 0, "flow.time_scale", f"must be > 0, got {self.time_scale}")
        _require(self.clip_range > 0, "flow.clip_range", f"must be > 0, got {self.clip_range}")


ExecutionKind = Literal["chunk", "aac", "te"]
HandoverKind = Literal["naive", "inpaint"]
SemanticsKind = Literal["rate", "waypoint"]


@dataclasses.dataclass(frozen=True)
class InferenceConfig:
    """How a trained policy is run: the one home of every inference setting.

    Used by training's periodic evaluation, ``experiments.evaluate`` / ``calibrate``, the paper budgets and the
    benchmarks. It is not part of a trained run's identity (changing it never blocks resume or reuse of a run);
    ``experiments.train`` stores the one it used beside the run (``inference.json``), where ``evaluate`` and
    ``calibrate`` take their defaults from.

    - ``num_samples``: N chunks drawn per decision for the action entropy (N = 1: no entropy, highest frequency).
    - ``sampler`` / ``num_steps``: how the generative head integrates. Diffusion: ``ddpm`` (every train step),
      ``ddim`` (diffusers' default DDIM, η = 0) or ``ddim-clipped`` (DDIM with ε recomputed from the clipped clean
      sample, diffusers' ``use_clipped_model_output=True``); flow: ``euler``. ``auto`` is ``ddim`` for diffusion and
      ``euler`` for flow; ``num_steps`` None is every train step for DDPM and 10 otherwise.
    - ``thresholds``: M+1 ascending (or the M−1 inner) entropy thresholds; None: the run's calibration, taken at
      ``percentiles`` (M−1 values in (0, 100); None: 10 / 70 for M = 3 as the paper, evenly spaced otherwise) of
      the action entropies of ``calib_windows`` held-out demo windows.
    - ``entropy_guided``: False always executes the highest frequency (stride 1).
    - ``execution``: how a decision's samples are executed (``evaluation.execution``): ``chunk`` runs the L_c
      actions of the selected frequency; ``aac`` (adaptive action chunking) the first k of them, k from the
      entropy curve of the N samples; ``te`` (ACT's temporal ensembling) decides at every control step and executes
      the exp(−te_decay·i)-weighted mean of the stored chunks' predictions for that step.
    - ``delay``: asynchronous execution under an inference delay of d control steps (``chunk`` execution only,
      d ≤ L_c/2): the next decision starts d steps before the current chunk is used up, from the observation at
      that time, while the robot executes the old chunk's last d actions; the new chunk then runs from its action
      d. 0 is synchronous execution. ``handover`` says how the new chunk meets the d committed actions: ``naive``
      switches to it as sampled; ``inpaint`` guides its first d actions (at every frequency) to the committed ones
      inside the one sampler, and the entropy is read over the free actions only.
    - ``semantics``: what executing one action means (``evaluation.rollout``). ``rate``: one action per control
      step, so a stride-s chunk covers s steps of demonstration time per control step. ``waypoint`` (the HiPolicy
      release's): each action is a target the low-level controller is given until the hand is within
      ``waypoint_tolerance`` metres of it, or for at most ``waypoint_steps`` × the decision's stride control steps
      (None: the environment's own, measured on its experts: MJX tasks 5 mm and 3, Meta-World 4 cm and 5, whose hand
      trails its target by 3 cm in motion);
      the policy observes once per action (its history holds one frame per action, not per control step), and the
      next action starts from where the robot is. Evaluations count decisions, actions and control steps (physical
      time) under both.
    - ``controller_speed``: a speed limit (m/s) of the MJX tasks' low-level controller: the hand's set-point moves
      towards each target at most ``controller_speed`` · control_dt a control step (a straight-line planner, as a
      robot's trajectory planner bounds joint speeds). None: the position servo is given the target at once (it
      reaches a stride-3 target within one 0.1 s step; docs/execution.md).
    """

    num_samples: int = 16
    sampler: Literal["auto", "ddpm", "ddim", "ddim-clipped", "euler"] = "auto"
    num_steps: int | None = None
    thresholds: tuple[float, ...] | None = None
    percentiles: tuple[float, ...] | None = None
    calib_windows: int = 128
    entropy_guided: bool = True
    execution: ExecutionKind = "chunk"
    te_decay: float = 0.01  # temporal ensembling's m (ACT): weight exp(-m·i), i = 0 for the oldest prediction
    entropy_eps: float = 1e-6
    delay: int = 0  # inference delay d in control steps (asynchronous execution); 0 = synchronous
    handover: HandoverKind = "naive"  # how a delayed decision's chunk meets the committed actions
    semantics: SemanticsKind = "rate"  # one action per control step | each action a target reached (waypoint)
    waypoint_tolerance: float | None = None  # m: the hand is at a waypoint within this distance; None: the env's
    waypoint_steps: int | None = None  # control steps a waypoint may take per unit of stride; None: the env's
    controller_speed: float | None = None  # m/s limit of the MJX hand's set-point; None: no limit

    def __post_init__(self):
        _require(self.num_samples >= 1, "inference.num_samples", f"(N) must be >= 1, got {self.num_samples}")
        _require(self.sampler in ("auto", "ddpm", "ddim", "ddim-clipped", "euler"), "inference.sampler",
                 f"must be 'auto', 'ddpm', 'ddim', 'ddim-clipped' or 'euler', got {self.sampler!r}")
        _require(self.num_steps is None or self.num_steps >= 1, "inference.num_steps",
                 f"must be None (the sampler's default) or >= 1, got {self.num_steps}")
        if self.thresholds is not None:
            t = tuple(float(x) for x in self.thresholds)
            _require(all(a < b for a, b in zip(t, t[1:])), "inference.thresholds",
                     f"must be strictly ascending, got {t}")
            object.__setattr__(self, "thresholds", t)
        if self.percentiles is not None:
            p = tuple(float(x) for x in self.percentiles)
            _require(all(0 < x < 100 for x in p) and all(a < b for a, b in zip(p, p[1:])), "inference.percentiles",
                     f"must be ascending values in (0, 100), got {p}")
            object.__setattr__(self, "percentiles", p)
        _require(self.calib_windows >= 1, "inference.calib_windows", f"must be >= 1, got {self.calib_windows}")
        _require(self.execution in ("chunk", "aac", "te"), "inference.execution",
                 f"must be 'chunk', 'aac' or 'te', got {self.execution!r}")
        _require(self.te_decay >= 0, "inference.te_decay", f"must be >= 0, got {self.te_decay}")
        _require(self.entropy_eps > 0, "inference.entropy_eps", f"must be > 0, got {self.entropy_eps}")
        _require(self.delay >= 0, "inference.delay", f"(control steps) must be >= 0, got {self.delay}")
        _require(self.handover in ("naive", "inpaint"), "inference.handover",
                 f"must be 'naive' or 'inpaint', got {self.handover!r}")
        _require(self.semantics in ("rate", "waypoint"), "inference.semantics",
                 f"must be 'rate' or 'waypoint', got {self.semantics!r}")
        _require(self.waypoint_tolerance is None or self.waypoint_tolerance > 0, "inference.waypoint_tolerance",
                 f"(m) must be None (the environment's) or > 0, got {self.waypoint_tolerance}")
        _require(self.waypoint_steps is None or self.waypoint_steps >= 1, "inference.waypoint_steps",
                 f"(control steps per unit of stride) must be None (the environment's) or >= 1, got "
                 f"{self.waypoint_steps}")
        _require(self.controller_speed is None or self.controller_speed > 0, "inference.controller_speed",
                 f"(m/s) must be None (no limit) or > 0, got {self.controller_speed}")
        _require(self.delay == 0 or self.execution == "chunk", "inference.delay",
                 f"asynchronous execution runs whole chunks (--inference.execution chunk), got execution "
                 f"{self.execution!r} with delay {self.delay}")

    def samples_drawn(self, num_freqs: int) -> int:
        """The chunks one decision of a ``num_freqs``-frequency policy draws: N, or 1 for a single-frequency policy
        (one stride: plain Diffusion Policy) whose execution reads no entropy (``chunk``, ``te``). Such a decision
        executes sample 0, and sample 0's key (``jax.random.split(key, N)[0]``) is the key an N = 1 draw uses, so
        drawing it alone executes the same chunk (equal to float rounding: XLA's kernels for N·B and B rows may
        round the last bit differently) at 1/N of the sampler's cost. AAC reads the N samples' entropy curve and
        draws all N; so does any policy with several frequencies."""
        return 1 if num_freqs == 1 and self.execution != "aac" else self.num_samples

    def decision_settings(self, num_freqs: int) -> "InferenceConfig":
        """``sampler_settings`` with ``samples_drawn``: what one decision of a ``num_freqs``-frequency policy
        compiles (the closed-loop policy, the policy server and the export)."""
        return dataclasses.replace(self.sampler_settings(), num_samples=self.samples_drawn(num_freqs))

    def rollout_settings(self) -> "InferenceConfig":
        """``sampler_settings`` plus how actions execute (``semantics``, the waypoint bounds, the controller's
        speed): what a compiled closed-loop rollout depends on."""
        return dataclasses.replace(self.sampler_settings(), semantics=self.semantics,
                                   waypoint_tolerance=self.waypoint_tolerance, waypoint_steps=self.waypoint_steps,
                                   controller_speed=self.controller_speed)

    def sampler_settings(self) -> "InferenceConfig":
        """Only what compiled samplers and rollouts depend on (N, sampler, steps, execution, entropy ε), the rest at
        defaults: their static key, so thresholds or calibration settings never recompile."""
        return InferenceConfig(num_samples=self.num_samples, sampler=self.sampler, num_steps=self.num_steps,
                               execution=self.execution, te_decay=self.te_decay, entropy_eps=self.entropy_eps,
                               delay=self.delay, handover=self.handover)


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Closed-loop evaluation during and after training (the inference settings are ``InferenceConfig``)."""

    episodes: int = 20
    every: int = 1000  # training steps between evaluations (0: only at the end)

    def __post_init__(self):
        _require(self.episodes >= 1, "eval.episodes", f"must be >= 1, got {self.episodes}")
        _require(self.every >= 0, "eval.every", f"must be >= 0, got {self.every}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimiser, schedule, EMA, training windows and checkpointing (Diffusion Policy defaults).

    The HiPolicy release trains with two Diffusion Policy (DP) workspaces that differ from DP and from each other;
    each such setting is a field below, with DP's value, the release's and why ours is what it is. The release's
    optimiser, schedule, EMA switch and windows: ``betas=(0.9, 0.999), max_action_pad=7`` with ``warmup_steps=500``
    (v2: EMA on, no clipping) or ``warmup_steps=8000, grad_clip=1.0, ema=False`` (v1).
    """

    batch_size: int = 128
    num_steps: int = 3000
    lr: float = 1e-4
    # AdamW (β1, β2). DP: (0.95, 0.999); the release (v1 and v2): (0.9, 0.999). Ours: DP's, because our M = 1
    # baseline is DP and HiPolicy runs train with the same optimiser, so a comparison isolates the multi-frequency
    # change; no run of ours has shown the release's β1 to train better.
    betas: tuple[float, float] = (0.95, 0.999)
    weight_decay: float = 1e-6
    # Linear warm-up from 0 to ``lr`` over these updates, then cosine decay to 0 at ``num_steps`` (diffusers'
    # ``get_scheduler('cosine')``, as DP builds it; a run no longer than its warm-up warms up throughout and never
    # reaches ``lr``, as there). DP: 500; the release: 8,000 (v1 workspace) / 500 (v2). Ours: 500, because our
    # budgets are 3,000-20,000 updates, and 8,000 would spend a short run's whole budget, and a long one's first
    # 40 %, below the learning rate it was given.
    warmup_steps: int = 500
    # Clip the gradients' global L2 norm to this before AdamW (torch's ``clip_grad_norm_``; None: no clipping). DP:
    # none; the release: 1.0 in its v1 workspace only. Ours: none, as DP and the release's v2, because our runs
    # trained without it and a step whose loss or gradients go non-finite is skipped and stops the run with a
    # message that suggests this setting; a run whose loss spikes can set 1.0 (the logged grad_norm is unclipped).
    grad_clip: float | None = None
    # Keep an EMA of the parameters and evaluate / export it (off: the raw parameters). DP: on; the release: off
    # (v1), on (v2). Ours: on, as DP and v2, because DP evaluates and checkpoints its EMA policy and users of these
    # systems ask for EMA on by default.
    ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    # How many frames a training window's actions may reach past its episode's last frame (repeats of the last
    # frame; None: no limit, every current frame whose first action a[t+δ] lies in the episode trains). The window's
    # last action frame is t + chunk.action_span - 1, so a limit p keeps current frames t <= end - action_span + p
    # (end: one past the episode's last frame). DP's ``SequenceSampler`` pad_after = n_action_steps - 1; the
    # release: 7 on its 29-frame sequence (7 observation frames + 22 more), i.e. t <= end - 16 with the default
    # chunk. Ours: None, because the last frames of a demo are the only windows that show the policy how an
    # episode ends and holds, and short demos can spare none of them (p = 7 drops 14 of each episode's windows with
    # the default chunk: 12-26 % of a 55-113-frame demo, our Meta-World buffers' lengths). An episode too short for
    # any window under a limit trains none (as DP's sampler), with a warning naming it. Observation padding needs no
    # limit: DP's pad_before = n_obs_steps - 1 pads the whole history of the first frame, as every window here does.
    max_action_pad: int | None = None
    seed: int = 0
    log_every: int = 50
    ckpt_every: int = 1000
    ckpt_keep: int = 3

    def __post_init__(self):
        _require(self.batch_size >= 1, "train.batch_size", f"must be >= 1, got {self.batch_size}")
        _require(self.num_steps >= 1, "train.num_steps", f"must be >= 1, got {self.num_steps}")
        _require(self.lr > 0, "train.lr", f"must be > 0, got {self.lr}")
        _require(len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas), "train.betas",
                 f"must be two values in [0, 1), got {self.betas}")
        _require(self.warmup_steps >= 0, "train.warmup_steps", f"must be >= 0, got {self.warmup_steps}")
        _require(self.grad_clip is None or self.grad_clip > 0, "train.grad_clip",
                 f"must be None (no clipping) or > 0, got {self.grad_clip}")
        _require(self.ema_power > 0, "train.ema_power", f"must be > 0, got {self.ema_power}")
        _require(0 <= self.ema_max_decay < 1, "train.ema_max_decay", f"must be in [0, 1), got {self.ema_max_decay}")
        _require(self.max_action_pad is None or self.max_action_pad >= 0, "train.max_action_pad",
                 f"must be None (no limit) or >= 0, got {self.max_action_pad}")
        _require(self.ckpt_every >= 1, "train.ckpt_every", f"must be >= 1, got {self.ckpt_every}")
        _require(self.ckpt_keep >= 1, "train.ckpt_keep", f"must be >= 1, got {self.ckpt_keep}")
        _require(self.log_every >= 1, "train.log_every", f"must be >= 1, got {self.log_every}")


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """Everything that defines a trained policy: windowing, encoder, denoiser and generative objective.

    ``objective`` picks the generative head (``heads.HEADS``): ``diffusion`` (DDPM, ``diffusion``'s settings) or
    ``flow`` (conditional flow matching, ``flow``'s settings). How the policy is sampled and executed is
    ``InferenceConfig``, not part of this config.
    """

    chunk: ChunkConfig = ChunkConfig()
    encoder: EncoderConfig = EncoderConfig()
    model: ModelConfig = ModelConfig()
    objective: Objective = "diffusion"
    diffusion: DiffusionConfig = DiffusionConfig()
    flow: FlowConfig = FlowConfig()

    def __post_init__(self):
        m, lc, f = self.chunk.num_freqs, self.chunk.chunk_len, self.model.downsample_factor
        # Each frequency segment keeps its own FiLM at every U-Net level, so L_c itself must down-sample cleanly.
        _require(lc % f == 0, "chunk.chunk_len",
                 f"(L_c={lc}) must be divisible by the U-Net's down-sampling factor {f} "
                 f"(2^(len(model.down_dims)-1)) so each frequency segment stays aligned at every level")
        _require(self.objective in ("diffusion", "flow"), "policy.objective",
                 f"must be 'diffusion' or 'flow', got {self.objective!r}")
        if self.model.fusion and m > 1:
            tok = self.model.unet_dims[0] * lc
            _require(tok % self.model.fusion_heads == 0, "model.fusion_heads",
                     f"fusion token size down_dims[0]*L_c={tok} must be divisible by fusion_heads={self.model.fusion_heads}")


def replace(cfg, **changes):
    """``dataclasses.replace`` that also accepts dotted keys: ``replace(cfg, **{"chunk.strides": (1,)})``."""
    nested: dict[str, dict] = {}
    flat = {}
    for key, value in changes.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            flat[key] = value
    for head, sub in nested.items():
        flat[head] = replace(getattr(cfg, head), **sub)
    return dataclasses.replace(cfg, **flat)

