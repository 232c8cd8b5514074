"""hipolicy_jax: HiPolicy (hierarchical multi-frequency action chunking) for diffusion policies in JAX/Flax."""

__version__ = "0.1.0"
