"""Finished performance studies: one-off before / after measurements whose answers PERFORMANCE.md states.

Each is still a command, ``python -m benchmarks.studies.<name> --help``, that reruns its measurement on this
machine and writes ``benchmarks/studies/results/<name>_<device>.json`` (``common.default_results_dir``);
``benchmarks.report`` reads those JSONs for PERFORMANCE.md next to the ones in ``benchmarks/results``.

- ``optimisation``: the sampler's FiLM observation half computed once per call and the one-``exp`` Mish, before /
  after, interleaved;
- ``convolutions``: the U-Net's short-sequence convolutions (im2col where the sequence is shorter than the kernel,
  the transposed convolution as one stride-1 convolution) against the native ones, interleaved;
- ``compute_dtype``: the train step's non-finite guard as a branch, and ``model.compute_dtype='bfloat16'``, before /
  after, interleaved;
- ``precision``: does bf16 change what a trained policy samples (per-dimension sample statistics, float32 vs
  bfloat16);
- ``small_matmul``: the N = 1 latency's bound, XLA's CPU dot with few rows against the read bandwidth;
- ``checkpoint_load``: what verifying the checkpoint checksums costs a load;
- ``point_encoder``: the point-cloud train step with DP3's PointNet backward written out and glibc keeping freed
  memory, against the module autodiff and glibc's defaults, interleaved, with the loss trajectories side by side;
- ``pytorch_peer``: Diffusion Policy's 1D U-Net in plain PyTorch, timed on this machine (needs torch, not a
  dependency; the JAX side is ``benchmarks.sampling`` / ``benchmarks.train_step --shapes``).
"""
