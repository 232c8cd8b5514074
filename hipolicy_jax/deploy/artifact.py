"""The exported-policy directory: ``policy.jaxexport`` (the serialised ``jax.export`` program), ``params.npz`` (its
flat parameter leaves: network variables, normaliser, thresholds) and ``manifest.json`` (``backend.make_metadata``
plus the file format). Reading it needs jax and numpy only, not the model code.

``MANIFEST_VERSION`` is the program's calling convention: version 2 takes the committed prefix
(``prefix (B, P, A)``, ``prefix_valid (B,)``, the manifest's ``inputs``) after the observations and keys; a
version-1 artifact (no prefix) is refused with a request to re-export it."""

from __future__ import annotations

import os

import jax
import numpy as np
from jax import export as jax_export

from hipolicy_jax import jsonio

PROGRAM_FILE = "policy.jaxexport"
PARAMS_FILE = "params.npz"
MANIFEST_FILE = "manifest.json"
MANIFEST_VERSION = 2  # 2: the program takes the committed prefix (remote inpainting); 1: observations and keys only


def save_artifact(directory: str, exported: jax_export.Exported, leaves: list, manifest: dict) -> dict:
    """Write the three files into ``directory`` (created); → {name: path}."""
    os.makedirs(directory, exist_ok=True)
    paths = {name: os.path.join(directory, name) for name in (PROGRAM_FILE, PARAMS_FILE, MANIFEST_FILE)}
    with open(paths[PROGRAM_FILE], "wb") as f:
        f.write(exported.serialize())
    np.savez(paths[PARAMS_FILE], **{f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)})
    manifest = dict(manifest, files={PROGRAM_FILE: os.path.getsize(paths[PROGRAM_FILE]),
                                     PARAMS_FILE: os.path.getsize(paths[PARAMS_FILE])},
                    num_param_leaves=len(leaves), jax_version=jax.__version__)
    jsonio.dump(manifest, paths[MANIFEST_FILE])
    return paths


def load_artifact(directory: str) -> tuple[dict, jax_export.Exported, list[np.ndarray]]:
    """(manifest, the deserialised program, its parameter leaves) from an export directory; ``ValueError`` /
    ``FileNotFoundError`` name the file and what was expected."""
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"export: {directory} is not a directory; expected what experiments.export wrote "
                                f"({MANIFEST_FILE}, {PROGRAM_FILE}, {PARAMS_FILE})")
    paths = {name: os.path.join(directory, name) for name in (PROGRAM_FILE, PARAMS_FILE, MANIFEST_FILE)}
    missing = [n for n, p in paths.items() if not os.path.isfile(p)]
    if missing:
        raise FileNotFoundError(f"export: {directory} lacks {missing}; expected what experiments.export wrote")
    try:
        manifest = jsonio.load(paths[MANIFEST_FILE])
    except ValueError as e:
        raise ValueError(f"export: {paths[MANIFEST_FILE]} is not valid JSON ({e})") from None
    if manifest.get("format") != "hipolicy_jax.policy":
        raise ValueError(f"export: {paths[MANIFEST_FILE]} is not a hipolicy_jax policy manifest "
                         f"(format {manifest.get('format')!r})")
    if manifest.get("version") != MANIFEST_VERSION:
        raise ValueError(f"export: {paths[MANIFEST_FILE]} is manifest version {manifest.get('version')!r}, this code "
                         f"reads version {MANIFEST_VERSION} (its program also takes the committed prefix); re-export "
                         f"the policy with python -m experiments.export --checkpoint RUN_DIR --out {directory}")
    try:
        with open(paths[PROGRAM_FILE], "rb") as f:
            exported = jax_export.deserialize(bytearray(f.read()))
    except Exception as e:  # noqa: BLE001 - any decoding failure means a corrupt artifact
        raise ValueError(f"export: {paths[PROGRAM_FILE]} is not a readable jax.export program "
                         f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    try:
        with np.load(paths[PARAMS_FILE]) as z:
            leaves = [z[name] for name in sorted(z.files)]
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"export: {paths[PARAMS_FILE]} is unreadable ({type(e).__name__}: {e})") from None
    if len(leaves) != manifest.get("num_param_leaves"):
        raise ValueError(f"export: {paths[PARAMS_FILE]} holds {len(leaves)} arrays, the manifest says "
                         f"{manifest.get('num_param_leaves')}")
    return manifest, exported, leaves


__all__ = ["MANIFEST_FILE", "MANIFEST_VERSION", "PARAMS_FILE", "PROGRAM_FILE", "load_artifact", "save_artifact"]
