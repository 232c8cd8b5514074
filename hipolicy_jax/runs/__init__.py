"""Runs on disk, one module per thing a user does with them (``experiments/`` parses the flags of each):

- ``train``: ``RunConfig`` and ``train`` / ``dry_run`` / ``ensure_trained``;
- ``evaluate``: ``evaluate_run`` (with / without entropy guidance, traces, video);
- ``calibrate``: ``calibrate_run`` (thresholds from held-out demos or rollouts);
- ``store``: locate and load a run, its stored inference settings and held-out data;
- ``records``: a run record's network fingerprint, superseding and checks;
- ``serve``: a run as a deployable policy (``deploy``'s ``InProcessBackend``: what is served and exported);
- ``external``: an external task's run (``metaworld:<task>``): demos and closed-loop evaluation through its bridge;
- ``lock``, ``cli``: one process per run dir; the command-line plumbing of ``experiments/``.

Campaigns of many runs (budgets, records, tables) are the stage above: ``hipolicy_jax.campaigns``.
"""
