"""Runs on disk, one module per thing a user does with them (``experiments/`` parses the flags of each):

- ``train``: ``RunConfig`` and ``train`` / ``dry_run`` / ``ensure_trained``;
- ``evaluate``: ``evaluate_run`` (with / without entropy guidance, traces, video);
- ``calibrate``: ``calibrate_run`` (thresholds from held-out demos or rollouts);
- ``store``: locate and load a run, its stored inference settings and held-out data;
- ``budgets``: the budgets and demo regimes, and the run config of a (task, observation type, changes, seed);
- ``campaign``: many evaluations kept as JSON records (``Campaign``, ``Column``, cost model, scheduling, shards);
- ``report``: cells, tables and figures from those records (intervals, paired tests, cost);
- ``tables``: the paper's tables and the whole campaign (``build(args)``; ``experiments.paper`` parses its flags).
"""
