"""Export a trained policy: the one sampler, its parameters, normaliser, inference settings and calibrated
thresholds as a ``jax.export`` artifact (``deploy.artifact``), loadable by ``backend.ExportedBackend`` without the
model code.

The exported program is the batched decision of ``backend.batched_decide`` with a symbolic batch size: one artifact
serves any number of observation histories per call. It takes the committed prefix too (``prefix (B, P, A)``,
``prefix_valid (B,)``; P from the manifest's ``inputs``), so a policy served under an inference delay with
``handover='inpaint'`` inpaints remotely as in-process. Its parameters are inputs (a flat list of arrays stored
beside it), so the program stays small and the weights stay plain arrays.
"""

from __future__ import annotations

import jax
from jax import export as jax_export

from hipolicy_jax.deploy.artifact import save_artifact
from hipolicy_jax.deploy.backend import InProcessBackend


def export_backend(backend: InProcessBackend, directory: str, platforms: tuple[str, ...] = ("cpu",)) -> dict:
    """Export ``backend``'s batched decision for ``platforms`` (e.g. ('cpu', 'cuda')) into ``directory``;
    → {file name: path}."""
    leaves, treedef = jax.tree.flatten(backend._args)
    decide = backend._decide

    def program(flat_args, obs, key_data, prefix, prefix_valid):
        return decide(jax.tree.unflatten(treedef, flat_args), obs, key_data, prefix, prefix_valid)

    (b,) = jax_export.symbolic_shape("b")
    obs = {k: jax.ShapeDtypeStruct((b, *spec["shape"]), spec["dtype"]) for k, spec in backend.metadata["obs"].items()}
    args = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
    prefix = backend.metadata["inputs"]["prefix"][1:]  # [P, A]
    exported = jax_export.export(jax.jit(program), platforms=platforms)(
        args, obs, jax.ShapeDtypeStruct((b, 2), "uint32"), jax.ShapeDtypeStruct((b, *prefix), "float32"),
        jax.ShapeDtypeStruct((b,), "bool"))
    manifest = dict(backend.metadata, platforms=list(platforms))
    return save_artifact(directory, exported, leaves, manifest)


__all__ = ["export_backend"]
