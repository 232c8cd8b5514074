"""hipolicy_jax: HiPolicy (hierarchical multi-frequency action chunking) for diffusion policies in JAX/Flax.

The data flow, stage by stage, and where each stage lives:

    data -> encoders -> denoiser -> generative head -> sampling -> evaluation -> experiments

- **data** (``hipolicy_jax.data``): demonstrations on disk -> normalised, batched multi-frequency windows. Demos
  come from the MJX tasks' scripted experts (``envs``), from other projects' formats (``data.importers``) or from
  DemoSpeedup's accelerated buffers (``speedup``);
- **encoders** and **denoiser** (``hipolicy_jax.models``): ``ObsEncoder`` -> per-frequency condition ->
  ``ConditionalUnet1D`` (Diffusion Policy's U-Net with hierarchical FiLM and global fusion) in ``PolicyNet``;
- **generative head** (``hipolicy_jax.heads``): diffusion (DDPM / DDIM) or flow matching: the training target and
  the sampling update;
- training (``training``: train state, optimiser, EMA, the jitted step; ``trainer``: the loop, checkpoints,
  resume; ``checkpoint``: orbax checkpoints with checksums; ``parallel``: data parallelism);
- **sampling** (``hipolicy_jax.sampling``): the one N-sample sampler with entropy-guided frequency selection;
- **evaluation** (``hipolicy_jax.evaluation``): closed-loop rollouts on the MJX tasks (``envs``), execution
  strategies, threshold calibration; ``deploy`` serves or exports the same decision;
- **experiments**: ``runs`` (one run end to end), ``campaigns`` (many runs, records, tables) and the command lines
  in the top-level ``experiments/`` package. ``porting`` brings PyTorch checkpoints in as runs.

Shared by every stage: ``config`` (the frozen, validated configuration dataclasses) and ``jsonio`` (strict JSON).
Nothing is re-exported at this level: import from the packages and modules.
"""

__version__ = "0.1.0"
