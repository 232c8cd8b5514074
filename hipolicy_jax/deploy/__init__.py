"""Deployment: a trained policy as a service. ``backend`` (what a deployed policy computes: the batched decision,
in-process or from an export), ``artifact`` / ``export`` (the ``jax.export`` files), ``protocol`` (the msgpack
messages), ``server`` (the websocket policy server) and ``client`` (its client, with the evaluator's policy
interface)."""
