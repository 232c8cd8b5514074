"""The front page's results at a glance: ``docs/glance.png`` drawn from the committed tables, and the cells it
reads printed (``hipolicy_jax.campaigns.glance``).

    python -m experiments.glance                       # after a table it reads is rebuilt
    python -m experiments.glance --out /tmp/glance.png
"""

from __future__ import annotations

import dataclasses

import tyro

from hipolicy_jax.campaigns.glance import FIGURE, fewer_steps, glance_rows, plot_glance


@dataclasses.dataclass(frozen=True)
class GlanceArgs:
    root: str = "."  # the repository (its committed tables)
    out: str = FIGURE  # the figure


def main(args: GlanceArgs) -> str:
    """Draw the figure; print each row's cells and its source; returns the figure's path."""
    rows = glance_rows(args.root)
    plot_glance(rows, args.out)
    for r in rows:
        print(f"{r.label}: success {r.dp_success} -> {r.hip_success} ({r.difference}); steps {r.dp_steps} -> "
              f"{r.hip_steps} ({fewer_steps(r):.0f} % fewer) [{r.source}]")
    print(f"wrote {args.out}")
    return args.out


if __name__ == "__main__":
    try:
        main(tyro.cli(GlanceArgs, description=__doc__))
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}")
