"""One run on disk from end to end: the stages of the flow put together for one policy, a seed and a task.

    data (demos) -> training (``trainer.fit``: encoders, denoiser, generative head) -> calibration (sampling) ->
    evaluation -> a run directory; **runs** drives these steps, the ``experiments/`` command lines parse the flags
    of each, and ``hipolicy_jax.campaigns`` (many runs, their records and tables) is the stage above.

One module per thing a user does with a run:

- ``train``: ``RunConfig`` and ``train`` / ``dry_run`` / ``ensure_trained``;
- ``evaluate``: ``evaluate_run`` (with / without entropy guidance, traces, video);
- ``calibrate``: ``calibrate_run`` (thresholds from held-out demos or rollouts);
- ``store``: locate and load a run (``load_run`` -> ``Run``), its stored inference settings, calibration and
  held-out data (``heldout_dataset``), and the evaluation keys (``eval_key``);
- ``records``: a run record's network fingerprint, superseding and checks;
- ``serve``: a run as a deployable policy (``run_backend``: ``deploy``'s ``InProcessBackend``, what is served and
  exported);
- ``external``: an external task's run (``metaworld:<task>``): demos and closed-loop evaluation through its bridge;
- ``lock``, ``cli``: one process per run dir (``RunLock``); the command-line plumbing of ``experiments/``.

Nothing is re-exported here: import from the modules.
"""
