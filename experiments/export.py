"""Export a trained policy: ``python -m experiments.export --checkpoint RUN_DIR --out DIR``.

Writes the one sampler (N samples, entropy, frequency selection) with the run's (EMA) parameters, normaliser,
inference settings and calibrated thresholds as a ``jax.export`` artifact into ``DIR``: ``policy.jaxexport`` (the
serialised program, any batch size), ``params.npz`` (its parameter arrays) and ``manifest.json`` (observation keys,
shapes and dtypes, strides, chunk length, action dim, inference settings, thresholds). Load it without the model
code with ``hipolicy_jax.deploy.backend.ExportedBackend(DIR)`` or serve it with
``python -m experiments.serve --export DIR``. ``--inference.*`` default to the run's ``inference.json``;
``--platforms cpu cuda`` exports for both.
"""

from __future__ import annotations

import dataclasses

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.runs.serve import run_backend
from hipolicy_jax.deploy.export import export_backend
from hipolicy_jax.runs.cli import prepare_process, run_main


@dataclasses.dataclass(frozen=True)
class ExportArgs:
    checkpoint: str  # run dir (holding checkpoints/) or its checkpoints/ dir
    out: str  # directory to write the artifact into
    step: int | None = None  # checkpoint step (default: the latest)
    inference: InferenceConfig = InferenceConfig()  # default: the run's inference.json
    platforms: tuple[str, ...] = ("cpu",)  # jax.export lowering platforms, e.g. cpu cuda


def main(args: ExportArgs) -> dict:
    backend = run_backend(args.checkpoint, args.inference, args.step)
    paths = export_backend(backend, args.out, tuple(args.platforms))
    meta = backend.metadata
    print(f"exported the {meta['task']} policy (step {meta['checkpoint_step']}, strides {meta['strides']}, "
          f"N={meta['num_samples']}, thresholds from {meta['thresholds_source']}) for {list(args.platforms)} to "
          f"{args.out}: " + ", ".join(f"{name}" for name in paths))
    return paths


if __name__ == "__main__":
    prepare_process()
    run_main(ExportArgs, main, __doc__)
