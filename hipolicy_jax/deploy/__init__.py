"""Deployment: a trained policy as a service. ``backend`` (what a deployed policy computes: the batched decision,
in-process or from an export), ``artifact`` / ``export`` (the ``jax.export`` files), ``protocol`` (the wire
protocol: openpi's msgpack-numpy frames), ``server`` (the websocket policy server: micro-batching, server-side
execution, API key) and ``client`` (its client, and remote closed-loop evaluation)."""
