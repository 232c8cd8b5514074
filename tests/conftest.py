import os

# Tests run on the CPU with deterministic, single-process XLA; keep compile caches per process.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MUJOCO_GL", "egl")
