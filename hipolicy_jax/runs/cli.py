"""What the entry points share: the command-line parsing of those that act on a trained run
(``experiments.evaluate``, ``experiments.calibrate``, ...: their ``--inference.*`` flags default to the run's stored
settings), of those that build tables (``experiments.paper``, ``experiments.metaworld``: ``table_cli``) and the
process set-up every entry point does first (``prepare_process``: the persistent compilation cache and glibc keeping
freed memory)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from typing import Callable, TypeVar

import jax
import tyro

from hipolicy_jax.host_memory import keep_freed_memory
from hipolicy_jax.runs.store import read_inference, resolve_run

T = TypeVar("T")


CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"  # JAX's own variable: JAX reads it at import


def default_cache_dir() -> str:
    """``$XDG_CACHE_HOME/hipolicy_jax/xla`` (``~/.cache/...`` without XDG_CACHE_HOME)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "hipolicy_jax", "xla")


def enable_compilation_cache() -> str | None:
    """Keep compiled XLA executables on disk across processes: a second ``experiments.evaluate`` of a policy, the
    next seed of a campaign or a resumed training loads its rollout, sampler and train step instead of compiling
    them again (30-50 s for a rollout on 2 CPU cores). ``JAX_COMPILATION_CACHE_DIR`` names the folder (an empty
    value turns the cache off); unset, it is ``default_cache_dir()``. Entries are ~1 MB each and the folder can be
    deleted at any time. Call before the first compilation. → the folder, or None when off."""
    if CACHE_ENV in os.environ:
        path = os.environ[CACHE_ENV] or None
        if path:
            jax.config.update("jax_compilation_cache_dir", path)
    else:
        path = default_cache_dir()
        jax.config.update("jax_compilation_cache_dir", path)
    return path


def prepare_process() -> str | None:
    """What every entry point does before its first JAX computation: glibc keeps freed memory for the next step
    (``host_memory.keep_freed_memory``) and compiled programs are kept on disk (``enable_compilation_cache``).
    → the compilation cache's folder, or None when off."""
    keep_freed_memory()
    return enable_compilation_cache()


def parse_with_run_inference(cls: type[T], argv: list[str] | None = None, description: str | None = None) -> T:
    """``tyro.cli(cls)`` where ``cls`` has ``checkpoint: str`` and ``inference: InferenceConfig`` fields; the
    defaults of ``--inference.*`` are the ``inference.json`` of the run ``--checkpoint`` names (when it has one),
    so an evaluation reproduces the run's own settings unless a flag says otherwise."""
    argv = sys.argv[1:] if argv is None else list(argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--checkpoint")
    known, _ = pre.parse_known_args(argv)
    default = None
    if known.checkpoint and os.path.isdir(known.checkpoint):
        try:
            stored = read_inference(resolve_run(known.checkpoint)[0])
        except FileNotFoundError:
            stored = None
        if stored is not None:
            field_defaults = {f.name: f.default for f in dataclasses.fields(cls)
                              if f.default is not dataclasses.MISSING}
            default = cls(**{**field_defaults, "checkpoint": known.checkpoint, "inference": stored})
    return tyro.cli(cls, args=argv, default=default, description=description)


def run_main(cls: type[T], main: Callable[[T], object], description: str | None = None,
             argv: list[str] | None = None) -> None:
    """Parse ``cls`` (``parse_with_run_inference``) and run ``main``; a bad value or a missing file ends the
    program with its one-line message instead of a traceback."""
    try:
        main(parse_with_run_inference(cls, argv, description))
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}")


def table_cli(subcommands: dict[str, type], build: Callable[[object], str], description: str | None, label: str
              ) -> tuple[Callable[[list[str] | None], object], Callable[[object], str]]:
    """``(parse_args, main)`` of an entry point whose sub-commands build tables: ``parse_args(argv)`` parses
    ``TABLE [--flags]`` into that table's args dataclass; ``main(args)`` builds it (``build(args)`` → its markdown
    file), prints the table and returns the file's path."""
    def parse_args(argv: list[str] | None = None):
        return tyro.extras.subcommand_cli_from_dict(subcommands, args=argv, description=description)

    def main(args) -> str:
        t0 = time.perf_counter()
        path = build(args)
        with open(path) as f:
            print(f.read())
        print(f"[{label}] {time.perf_counter() - t0:.0f}s -> {path}")
        return path

    return parse_args, main


def run_table_cli(parse_args: Callable, main: Callable, argv: list[str] | None = None) -> None:
    """An entry point's ``__main__``: ``prepare_process()``, then ``main(parse_args(argv))``; a bad value or a
    missing file ends the program with its one-line message instead of a traceback."""
    prepare_process()
    try:
        main(parse_args(sys.argv[1:] if argv is None else argv))
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}")
