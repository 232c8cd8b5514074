"""Runs on disk, one module per thing a user does with them (``experiments/`` parses the flags of each):

- ``train``: ``RunConfig`` and ``train`` / ``dry_run`` / ``ensure_trained``;
- ``evaluate``: ``evaluate_run`` (with / without entropy guidance, traces, video);
- ``calibrate``: ``calibrate_run`` (thresholds from held-out demos or rollouts);
- ``store``: locate and load a run, its stored inference settings and held-out data.
"""
