"""Run PyTorch policies' weights in JAX: Diffusion Policy's and the HiPolicy release's checkpoints.

A side entrance to the flow: instead of data -> training, a PyTorch checkpoint becomes the trained encoder,
denoiser, head settings and normaliser of a run directory, which sampling, evaluation and deployment then use
unchanged.

* ``torch_checkpoint``: read a ``.ckpt`` (torch's zip format) without torch, through an allow-list unpickler, or a
  ``safetensors`` state dict: ``{name: np.ndarray}`` plus the workspace config (``read_torch_file``,
  ``read_safetensors``, ``plain_config``, ``resolve_config``).
* ``unet``: Diffusion Policy's / the release's ``ConditionalUnet1D`` state dict -> our ``ConditionalUnet1D`` params
  (``unet_params``, ``unet_shape``).
* ``encoders``: Diffusion Policy's ResNet-18 (GroupNorm) image encoder -> our ``ResNetAvgPoolEncoder`` params
  (``resnet_params_from_torch``, ``resnet_torch_shapes``).
* ``convert``: a whole checkpoint -> a ``PolicyConfig``, EMA parameters and normaliser (``convert`` ->
  ``Converted``), written as a run directory (``write_run``) that ``experiments.evaluate``, ``calibrate``,
  ``export`` and ``serve`` use unchanged (``experiments.import_checkpoint``).

Nothing is re-exported here: import from the modules. docs/fidelity.md lists what matches the originals and the
test that checks each piece.
"""
