"""Campaigns: the experiments stage of the data flow — the pre-registered campaigns (``results/PROTOCOL.md``,
``results/metaworld/PROTOCOL.md``), their many runs and evaluations kept as JSON records, and the tables built from
those records. It sits above ``runs`` (one run's lifecycle: train, calibrate, evaluate) and is driven by
``experiments.paper`` (the MJX tables) and ``experiments.metaworld`` (the Meta-World benchmark).

- ``budgets``: the budgets and demo regimes, and the run config of a (task, observation type, changes, seed);
- ``campaign``: many evaluations kept as JSON records (``Campaign``, ``Column``, cost model, scheduling, shards);
  external tasks are evaluated through the policy server and their bridge (``runs.external``);
- ``cluster``: a campaign's runs as submitit jobs (local processes or a SLURM job array);
- ``report``: cells, tables and figures from those records (intervals, paired tests, cost);
- ``tables``: the MJX paper's tables and the whole campaign (``build(args)``; ``experiments.paper``), a package with
  one module a table (``tables.main``, ``tables.ablation``, ...), what they share (``tables.common``), the findings
  (``tables.findings``), the registry (``tables.registry``) and the campaign driver (``tables.protocol``);
- ``metaworld``: the Meta-World benchmark's pilot, campaign and table (``experiments.metaworld``);
- ``metaworld_amendment2``: amendment 2 of the Meta-World protocol (its pilot and campaign);
- ``speedup``: amendment 5 of the MJX protocol, HiPolicy against DemoSpeedup (``experiments.paper speedup``): each
  task's accelerated demos made from a proxy, five methods, the table;
- ``glance``: the README's results at a glance (its table's cells read from the result tables, and its figure).

A new MJX table is one module in ``tables`` (its args class with its ``TABLE``, its columns and its builder) and
one line in ``tables.registry.ENTRIES``; ``experiments.paper`` then has its sub-command.
"""
