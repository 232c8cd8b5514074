"""Meta-World bridge: scripted-expert demos of Meta-World v3 tasks in the project's zarr layout.

Runs in its own venv (``bash scripts/setup_metaworld.sh`` → ``.venv-metaworld``: metaworld 3.1.1 pins mujoco 3.3.0,
which cannot share the project's venv) and imports only numpy, zarr, mujoco, metaworld, gymnasium and openpi's
client (msgpack, websockets) — never jax or ``hipolicy_jax``. Run it from the repository root::

    .venv-metaworld/bin/python -m metaworld_bridge.collect --task assembly --episodes 10 --out data/metaworld_assembly_10.zarr
    .venv-metaworld/bin/python -m metaworld_bridge.check_experts --seeds 50      # results/metaworld/experts.json
    .venv-metaworld/bin/python -m metaworld_bridge.evaluate --task assembly --url ws://127.0.0.1:8000 --episodes 100

The project's ``.venv`` trains on the zarr with ``python -m experiments.train --task metaworld:assembly --data ...``.

Modules: ``env`` (seeded task env, scripted expert, the execution semantics ``rate`` | ``waypoint``), ``evaluate``
(closed-loop episodes against the policy server, ``experiments.serve``, through ``openpi_client``), ``pointcloud``
(CPU ray-cast point clouds from DP3's corner2 camera, DP3's crop, farthest-point sampling), ``store`` (the zarr
layout), ``tasks`` (DP3's difficulty groups).
"""
