"""Deployment, beside evaluation at the end of the flow: a trained policy's decision served to robots or exported.

    sampling -> evaluation (in-process closed loop) | **deploy** (the same decision behind a websocket, or as a
    ``jax.export`` artifact loadable without the model code)

* ``backend``: what a deployed policy computes, ``PolicyBackend.decide`` (the batched decision of
  ``evaluation.policy.make_decision_fn``): ``InProcessBackend`` (the jitted network) and ``ExportedBackend`` (an
  exported artifact); ``make_metadata``, ``batched_decide``, ``obs_spec``, ``prefix_len``, ``zeros_obs``;
* ``export`` / ``artifact``: ``export_backend`` writes the ``jax.export`` program, its parameters and manifest;
  ``save_artifact`` / ``load_artifact`` read and write that directory;
* ``protocol``: the wire protocol, openpi's msgpack-numpy frames (``pack``, ``unpack``, ``parse_request``,
  ``decision_key``);
* ``server``: ``PolicyServer`` / ``ServerConfig``, the websocket policy server (micro-batching, server-side
  execution strategies, an optional API key, ``GET /healthz``);
* ``client``: ``PolicyClient`` (one robot's connection) and ``RemoteEvaluator`` / ``evaluate_remote`` (an MJX
  evaluation through the server, equal to the in-process one on the same keys).

Nothing is re-exported here: import from the modules. A trained run becomes a backend through
``runs.serve.run_backend``; ``experiments.serve`` and ``experiments.export`` are the command lines. Within
``hipolicy_jax`` this package imports ``config``, ``models``, ``evaluation``, ``envs``, ``checkpoint`` and ``jsonio``.
"""
