"""Campaigns: a protocol's many runs and evaluations, kept as JSON records, and the tables built from them — the
stage above ``runs`` (one run's lifecycle), used by ``experiments.paper`` (the MJX tables) and
``experiments.metaworld`` (the Meta-World benchmark).

- ``budgets``: the budgets and demo regimes, and the run config of a (task, observation type, changes, seed);
- ``campaign``: many evaluations kept as JSON records (``Campaign``, ``Column``, cost model, scheduling, shards);
  external tasks are evaluated through the policy server and their bridge (``runs.external``);
- ``report``: cells, tables and figures from those records (intervals, paired tests, cost);
- ``tables``: the MJX paper's tables and the whole campaign (``build(args)``; ``experiments.paper``);
- ``metaworld``: the Meta-World benchmark's pilot, campaign and table (``experiments.metaworld``).
"""
