"""The command lines, the last stage of the flow: each module is ``python -m experiments.<name> --help``.

    data -> encoders -> denoiser -> generative head -> sampling -> evaluation -> **experiments**

They parse flags and call the library (``hipolicy_jax.runs`` for one run, ``hipolicy_jax.campaigns`` for many).

- data: ``collect`` (the MJX tasks' scripted-expert demos), ``import_data`` (another project's dataset into the zarr
  layout), ``speedup`` (DemoSpeedup's accelerated demos);
- one run: ``train``, ``evaluate``, ``calibrate``;
- deployment: ``export`` (a ``jax.export`` artifact), ``serve`` (the websocket policy server);
- PyTorch checkpoints: ``import_checkpoint`` (Diffusion Policy's or the HiPolicy release's weights as a run);
- campaigns: ``paper`` (the paper's tables on the MJX tasks), ``metaworld`` (the Meta-World benchmark),
  ``records`` (check and upgrade the campaign's run records);
- ``expert_semantics``: the scripted experts chunked at each stride under each execution semantics.
"""
