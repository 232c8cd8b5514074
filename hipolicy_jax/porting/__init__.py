"""Run PyTorch policies' weights in JAX: Diffusion Policy's and the HiPolicy release's checkpoints.

* ``torch_checkpoint``: read a ``.ckpt`` (torch's zip format) without torch, through an allow-list unpickler, or a
  ``safetensors`` state dict: ``{name: np.ndarray}`` plus the workspace config.
* ``unet``: Diffusion Policy's / the release's ``ConditionalUnet1D`` state dict -> our ``ConditionalUnet1D`` params.
* ``encoders``: Diffusion Policy's ResNet-18 (GroupNorm) image encoder -> our ``ResNetAvgPoolEncoder`` params.
* ``convert``: a whole checkpoint -> a ``PolicyConfig``, EMA parameters and normaliser, written as a run directory
  that ``experiments.evaluate``, ``calibrate``, ``export`` and ``serve`` use unchanged
  (``experiments.import_checkpoint``).
"""
