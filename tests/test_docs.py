"""README.md and docs/*.md (issue #61): every relative link resolves (the file, and for ``#anchor`` a heading of that
file by GitHub's anchor rules); every command a fenced shell block (or an inline code span) shows as
``python -m experiments.X ...``, ``python -m benchmarks.X ...``, ``python -m hipolicy_jax...`` or, in the Meta-World
venv, ``python -m metaworld_bridge.X ...`` parses with its entry point's own parser; the README's first screen says
what the project is, whether HiPolicy works, with numbers checked against the tables they come from, and the two
fresh-machine commands CI runs.

Commands are parsed, not run: one subprocess per venv imports each entry point with ``runpy`` and stops it with an
exception right after its parser (``argparse``'s ``parse_args``, ``tyro.cli`` or tyro's sub-command parser) has
returned, so an unknown flag, a bad value or a misspelt sub-command fails, and nothing trains or evaluates.
Placeholders (``<run>``) become plain words and shell variables (``$k``) a number first.
"""

from __future__ import annotations

import glob
import json
import os
import re
import shlex
import subprocess
import sys

import pytest

from metaworld_venv import PYTHON as METAWORLD_PYTHON  # tests/metaworld_venv.py

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
DOCS = [README] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))
MODULES = ("experiments.", "benchmarks.", "hipolicy_jax", "metaworld_bridge.")
STOP = {";", "&", "&&", "|", "||", ">", ">>", "<", "<<", "2>", "2>&1", ">&"}


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


def _rel(path: str) -> str:
    return os.path.relpath(path, ROOT)


# ------------------------------------------------------------------------------------------------------ markdown

def fenced_blocks(text: str) -> list[tuple[str, str, int]]:
    """(language, body, line number of the opening fence) of every fenced code block."""
    out, lang, body, start = [], None, [], 0
    for i, line in enumerate(text.split("\n"), 1):
        if line.startswith("```"):
            if lang is None:
                lang, body, start = line[3:].strip(), [], i
            else:
                out.append((lang, "\n".join(body), start))
                lang = None
        elif lang is not None:
            body.append(line)
    assert lang is None, f"a fenced block opened at line {start} is never closed"
    return out


def unfenced(text: str) -> str:
    """``text`` with its fenced blocks blanked (line numbers kept)."""
    kept, inside = [], False
    for line in text.split("\n"):
        if line.startswith("```"):
            inside = not inside
            kept.append("")
        else:
            kept.append("" if inside else line)
    return "\n".join(kept)


def prose(text: str) -> str:
    """``text`` without its fenced blocks and inline code spans (links inside code are not links)."""
    return re.sub(r"`[^`]*`", "", unfenced(text))


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: its text (links and code marks dropped), lower case, characters other than
    letters, digits, '_', '-' and spaces removed, spaces as '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = text.replace("`", "").replace("*", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every heading's anchor (repeated headings get GitHub's -1, -2, ... suffixes)."""
    seen: dict[str, int] = {}
    out = set()
    for line in unfenced(text).split("\n"):
        m = re.match(r"^#{1,6} (.+?)\s*#*$", line)
        if m:
            a = github_anchor(m.group(1))
            out.add(a if a not in seen else f"{a}-{seen[a]}")
            seen[a] = seen.get(a, 0) + 1
    return out


LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def links(text: str) -> list[str]:
    return LINK.findall(prose(text))


# ----------------------------------------------------------------------------------------------------- commands

def shell_commands(text: str) -> list[tuple[str, str, list[str], int, bool]]:
    """(python, module, argv, line, inline) of every ``<python> -m <module> ...`` in the fenced shell blocks of
    ``text`` and in its inline code spans that start with ``python -m`` (``inline``; one elided with '...' left
    out)."""
    pieces = [(body, start, False) for lang, body, start in fenced_blocks(text) if lang in ("", "bash", "sh", "shell")]
    plain = unfenced(text)
    for m in re.finditer(r"`(python -m [^`]+)`", plain):
        if "..." not in m.group(1):
            pieces.append((" ".join(m.group(1).split()), plain[:m.start()].count("\n") + 1, True))
    out = []
    for body, start, inline in pieces:
        body = re.sub(r"\\\n", " ", body)
        body = re.sub(r"<([^<>\n]+)>", lambda m: re.sub(r"\W+", "_", m.group(1)).strip("_") or "x", body)
        body = re.sub(r"\$\{?[A-Za-z_]\w*\}?", "0", body)
        body = re.sub(r"\{([^{},\s]+),[^{}\s]*\}", r"\1", body)  # {a,b}: the first alternative
        for offset, line in enumerate(body.split("\n")):
            lex = shlex.shlex(line, posix=True, punctuation_chars=";&|<>")
            lex.whitespace_split = True
            tokens = list(lex)
            for i, tok in enumerate(tokens[:-2]):
                if re.search(r"(^|/)python3?$", tok) and tokens[i + 1] == "-m" and tokens[i + 2].startswith(MODULES):
                    argv = []
                    for t in tokens[i + 3:]:
                        if t in STOP:
                            break
                        argv.append(t)
                    out.append((tok, tokens[i + 2], argv, start + offset, inline))
    return out


def all_commands() -> list[tuple[str, str, str, list[str], bool]]:
    """(where, python, module, argv, a module named in prose without arguments) of every command in README.md and
    docs/*.md."""
    return [(f"{_rel(path)}:{line}", py, module, argv, inline and not argv)
            for path in DOCS for py, module, argv, line, inline in shell_commands(_read(path))]


# Runs in the venv's own python: each entry point as ``__main__`` with its parsers patched to raise Parsed once
# they have returned (a module that does not parse with argparse or tyro is refused, never run).
DRIVER = r'''
import argparse, contextlib, io, json, runpy, sys, traceback
class Parsed(BaseException):
    pass
depth = [0]
def after(fn):
    def wrapped(*a, **k):
        depth[0] += 1
        try:
            fn(*a, **k)
        finally:
            depth[0] -= 1
        raise Parsed()
    return wrapped
real_parse_args = argparse.ArgumentParser.parse_args
def parse_args(self, *a, **k):
    if depth[0]:
        return real_parse_args(self, *a, **k)
    return after(real_parse_args)(self, *a, **k)
argparse.ArgumentParser.parse_args = parse_args
try:
    import tyro, tyro.extras
    tyro.cli = after(tyro.cli)
    tyro.extras.subcommand_cli_from_dict = after(tyro.extras.subcommand_cli_from_dict)
except ImportError:
    pass
import importlib.util
results = []
for module, argv in json.load(sys.stdin):
    spec = importlib.util.find_spec(module)
    source = open(spec.origin).read() if spec and spec.origin and spec.origin.endswith(".py") else ""
    if not any(w in source for w in ("argparse", "tyro", "parse_args", "table_cli", "run_main")):
        results.append([module, argv, "not found, or parses no arguments (never run here)"])
        continue
    err = io.StringIO()
    sys.argv = [module] + argv
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            runpy.run_module(module, run_name="__main__", alter_sys=True)
        results.append([module, argv, "returned without parsing its arguments"])
    except Parsed:
        results.append([module, argv, None])
    except SystemExit as e:
        ok = e.code in (0, None) and ("--help" in argv or "-h" in argv)
        results.append([module, argv, None if ok else f"exit {e.code}: {err.getvalue()[-1500:]}"])
    except BaseException:
        results.append([module, argv, traceback.format_exc()[-1500:]])
print("RESULTS" + json.dumps(results))
'''


def parse_in(python: str, commands: list[tuple[str, list[str]]]) -> list[tuple[str, list[str], str | None]]:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
    r = subprocess.run([python, "-c", DRIVER], input=json.dumps(commands), capture_output=True, text=True, cwd=ROOT,
                       env=env, timeout=240)
    assert "RESULTS" in r.stdout, (r.stdout[-2000:], r.stderr[-3000:])
    return [tuple(x) for x in json.loads(r.stdout.split("RESULTS", 1)[1])]


# -------------------------------------------------------------------------------------------------------- tests

@pytest.mark.parametrize("path", DOCS, ids=_rel)
def test_every_relative_link_resolves(path):
    """Each relative link or image of the page names a file or folder of the repository, and each ``#anchor`` a
    heading of the page it points into."""
    bad = []
    for target in links(_read(path)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = os.path.normpath(os.path.join(os.path.dirname(path), file)) if file else path
        if not os.path.exists(dest):
            bad.append(f"{target}: no {_rel(dest)}")
        elif anchor and dest.endswith(".md") and anchor not in anchors(_read(dest)):
            bad.append(f"{target}: no heading #{anchor} in {_rel(dest)}")
    assert not bad, f"{_rel(path)}: " + "; ".join(bad)


def test_the_link_and_command_finders_find_what_they_should(tmp_path):
    """The checks above and below see links in prose (not in code) and every command of a block, with
    continuations, placeholders, shell variables, pipes and comments."""
    text = ("# A `title` — x (y)\n\n## A title, again\n\n[a](b.md#c) `[d](e)`\n\n```bash\n[f](g)\n"
            "for k in 0 1; do taskset -c $k python -m experiments.paper campaign --shard $k 2 > s$k.log 2>&1 & done\n"
            "python -m experiments.evaluate --checkpoint runs/<run> \\\n    --episodes 5   # comment\n"
            ".venv-metaworld/bin/python -m metaworld_bridge.collect --task assembly\npython -m pytest -q\n```\n"
            "and `python -m benchmarks.sampling --help` but not `python -m experiments.paper ... --x`\n")
    assert links(text) == ["b.md#c"]
    assert anchors(text) == {"a-title--x-y", "a-title-again"}
    got = [(py, m, argv) for py, m, argv, _, _ in shell_commands(text)]
    assert got == [("python", "experiments.paper", ["campaign", "--shard", "0", "2"]),
                   ("python", "experiments.evaluate", ["--checkpoint", "runs/run", "--episodes", "5"]),
                   (".venv-metaworld/bin/python", "metaworld_bridge.collect", ["--task", "assembly"]),
                   ("python", "benchmarks.sampling", ["--help"])]


def test_every_command_in_the_docs_parses():
    """Every ``python -m experiments|benchmarks|hipolicy_jax...`` command of README.md and docs/*.md parses with its
    entry point's own parser (in-process, one interpreter for all); a module a sentence names without arguments
    exists and answers ``--help``."""
    import importlib.util

    named = [(where, m, argv, bare) for where, py, m, argv, bare in all_commands() if not m.startswith("metaworld_bridge.")]
    missing = [f"{where}: python -m {m}: no such module" for where, m, _, _ in named if importlib.util.find_spec(m) is None]
    assert not missing, "\n".join(missing)
    # a module named in prose without arguments: its --help answers
    commands = [(where, m, ["--help"] if bare else argv) for where, m, argv, bare in named]
    assert len(commands) >= 60, f"only {len(commands)} commands found"
    unique = sorted({(m, tuple(argv)) for _, m, argv in commands})
    results = parse_in(sys.executable, [[m, list(argv)] for m, argv in unique])
    failed = {(m, tuple(argv)): why for m, argv, why in results if why}
    bad = [f"{where}: python -m {m} {shlex.join(argv)}\n  {failed[(m, tuple(argv))]}"
           for where, m, argv in commands if (m, tuple(argv)) in failed]
    assert not bad, "\n".join(bad)


@pytest.mark.skipif(not os.path.exists(METAWORLD_PYTHON), reason="no Meta-World venv: bash scripts/setup_metaworld.sh")
def test_every_bridge_command_in_the_docs_parses():
    """The ``metaworld_bridge`` commands parse in the Meta-World venv they run in."""
    commands = [(where, m, argv) for where, py, m, argv, bare in all_commands()
                if m.startswith("metaworld_bridge.") and not bare]
    assert len(commands) >= 3, commands
    results = parse_in(METAWORLD_PYTHON, [[m, argv] for _, m, argv in commands])
    bad = [f"{where}: python -m {m} {shlex.join(argv)}\n  {why}"
           for (where, m, argv), (_, _, why) in zip(commands, results) if why]
    assert not bad, "\n".join(bad)


def test_a_bad_flag_fails_the_command_check():
    """The parse check is not a formality: a misspelt flag, a bad value and a misspelt sub-command fail, for tyro,
    tyro's sub-commands and argparse entry points alike."""
    results = parse_in(sys.executable, [["experiments.train", ["--trian.num-steps", "5"]],
                                        ["experiments.evaluate", ["--checkpoint", "x", "--episodes", "many"]],
                                        ["experiments.paper", ["mian"]],
                                        ["experiments.import_data", ["nosuchformat", "a", "b"]],
                                        ["experiments.train", ["--train.num-steps", "5"]]])
    assert [why is None for _, _, why in results] == [False, False, False, False, True], results


# ------------------------------------------------------------------------------------------------ the front page

def _table(text: str, first_header: str) -> tuple[list[str], list[list[str]]]:
    lines = [ln for ln in text.split("\n")]
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"| {first_header} |"))
    rows = []
    for ln in lines[start:]:
        if not ln.startswith("|"):
            break
        rows.append([c.strip() for c in ln.strip().strip("|").split("|")])
    return rows[0], rows[2:]


def _source_row(text: str, section: str, first_cells: tuple[str, ...]) -> dict[str, str]:
    """The row starting with ``first_cells`` of the first table after the heading ``section``."""
    part = text[text.index(section):]
    header = next(ln for ln in part.split("\n") if ln.startswith("| "))
    head = [c.strip() for c in header.strip().strip("|").split("|")]
    for ln in part.split("\n"):
        cells = [c.strip() for c in ln.strip().strip("|").split("|")]
        if ln.startswith("|") and tuple(cells[:len(first_cells)]) == first_cells:
            return dict(zip(head, cells))
    raise AssertionError(f"no row {first_cells} under {section!r}")


def _mean(cell: str) -> float:
    return float(cell.split()[0])


def test_the_glance_table_quotes_its_tables():
    """Every number of the README's glance table is the cell of the table file it names (results/budget.md at
    24,000 steps; the Meta-World amendment-1 table's total average and its steps table's average), and the sentences
    around it say what those tables say: the settings, the steps saved, who ties and who loses."""
    readme = _read(README)
    budget = _read(os.path.join(ROOT, "results", "budget.md"))
    target = _read(os.path.join(ROOT, "results", "metaworld", "target", "main.md"))
    header, rows = _table(readme, "Benchmark")
    assert header == ["Benchmark", "DP success (%)", "DP+HiPolicy success (%)", "DP+HiPolicy − DP (points)",
                      "DP steps", "DP+HiPolicy steps"]
    want = []
    for task in ("press_button", "stack_cubes"):
        r = _source_row(budget, "# Training-budget sensitivity", (task, "24,000"))
        want.append([f"MJX {task}, 24,000 training steps", r["DP SR (%)"], r["DP+HiPolicy SR (%)"],
                     r["DP+HiPolicy − DP (points)"], r["DP steps"], r["DP+HiPolicy steps"]])
    success = _source_row(target, "# Meta-World: success rate", ("**Total average**",))
    steps = _source_row(target, "## Amendment 1, secondary: steps to success", ("**Average**",))
    tasks = [ln for ln in target.split("## ")[0].split("\n") if ln.startswith("| metaworld-target:")]
    want.append([f"Meta-World, {len(tasks)} tasks on absolute hand targets", success["DP"], success["DP+HiPolicy"],
                 success["DP+HiPolicy − DP (points)"], steps["DP steps"], steps["DP+HiPolicy steps"]])
    assert rows == want
    # the settings the text names, as the tables' settings lines say them
    flat = " ".join(readme.split())
    for text in (budget, target):
        assert "seeds 0, 1, 2" in text and "100 per seed" in text
    assert "3 seeds × 100 episodes per cell" in flat
    assert "100 demos" in budget and "(MJX, 100 demos)" in flat
    assert "Training: 4000 steps on 10 demos" in target and "10 demos, 4000 training steps" in flat
    both = [r for r in target.split("## Amendment 1, secondary: steps to success")[1].split("\n")
            if r.startswith("| metaworld-target:") and r.split("|")[6].strip() != "–"]
    assert f"its steps average the {len(both)} tasks where both columns succeed" in flat
    # the reading: ties on MJX with fewer steps (the printed means), a loss on Meta-World
    fewer = [round(100 * (1 - _mean(r[5]) / _mean(r[4]))) for r in want[:2]]
    assert (f"DP+HiPolicy keeps DP's success in {fewer[0]} % (press_button) and {fewer[1]} % (stack_cubes) fewer "
            f"control steps") in flat
    assert all(r[3].endswith("(ties)") for r in want[:2]) and want[2][3].endswith("(loses)")
    assert "On Meta-World it loses." in flat
    short = _source_row(budget, "# Training-budget sensitivity", ("press_button", "2,000 (budget)"))
    assert short["DP+HiPolicy − DP (points)"].endswith("(loses)")
    assert "at the campaign's shorter 2,000-step budget the verdicts are mixed (it loses on press_button" in flat
    # executed one action per control step: the tables' own evaluations (rate semantics, the default)
    assert "`rate` semantics" in flat and "whole-chunk execution" in target


def test_the_glance_figure_draws_the_glance_table(tmp_path):
    """``campaigns.glance`` reads the same cells as the README prints and plots their means; the README shows its
    figure (committed under docs/) with a caption naming the execution semantics."""
    from hipolicy_jax.campaigns.glance import FIGURE, fewer_steps, glance_rows, plot_glance

    rows = glance_rows(ROOT)
    _, printed = _table(_read(README), "Benchmark")
    assert [[r.label, r.dp_success, r.hip_success, r.difference, r.dp_steps, r.hip_steps] for r in rows] == printed
    assert [round(fewer_steps(r)) for r in rows[:2]] == [41, 43]
    plotted = plot_glance(rows, str(tmp_path / "glance.png"))
    assert os.path.getsize(tmp_path / "glance.png") > 10_000
    assert plotted["success"]["DP"] == [_mean(r[1]) for r in printed]
    assert plotted["success"]["DP+HiPolicy"] == [_mean(r[2]) for r in printed]
    assert plotted["steps"]["DP"] == [_mean(r[4]) for r in printed]
    assert plotted["steps"]["DP+HiPolicy"] == [_mean(r[5]) for r in printed]
    readme = _read(README)
    assert f"]({FIGURE})" in readme and os.path.exists(os.path.join(ROOT, FIGURE))
    caption = readme[readme.index(f"]({FIGURE})"):].split("\n\n")[1]
    assert "`rate` semantics (one action per control step)" in " ".join(caption.split())


def test_the_readme_is_a_front_page():
    """At most 250 lines; its first screen (45 lines) says what the project is, the glance table, and the
    fresh-machine block; the defaults it names are the config's."""
    from hipolicy_jax.config import ChunkConfig

    lines = _read(README).split("\n")
    assert len(lines) <= 250, len(lines)
    first = "\n".join(lines[:45])
    assert first.startswith("# hipolicy_jax\n\nHiPolicy — hierarchical multi-frequency action chunking")
    assert "## Does it work?" in first and "| MJX press_button" in first and "| Meta-World" in first
    assert "## Fresh machine" in first and "python -m pytest -q -m slow" in first
    assert "Meta-World is under re-test" in first
    c = ChunkConfig()
    flat = " ".join(first.split())
    strides = "/".join(map(str, c.strides))
    assert (f"default strides {strides} of the control rate, L_h = {c.obs_horizon} observation frames and "
            f"L_c = {c.chunk_len} actions per frequency") in flat


def _fresh_block(path: str) -> str:
    text = _read(path)
    after = text[text.index("## Fresh machine"):]
    return next(body for lang, body, _ in fenced_blocks(after) if lang == "bash")


def test_the_fresh_machine_block_is_what_ci_runs():
    """The README's fresh-machine block is two commands — set-up + the main job, and the tests as .ci/run runs
    them — and docs/install.md shows the same block."""
    block = _fresh_block(README)
    commands = [ln for ln in block.split("\n") if ln and not ln.startswith("#")]
    assert commands == [
        "bash scripts/setup_venv.sh && . .venv/bin/activate && python -m experiments.train",
        "bash scripts/setup_metaworld.sh && . .venv/bin/activate && python -m pytest -q && python -m pytest -q -m slow"]
    ci = _read(os.path.join(ROOT, ".ci", "run"))
    for line in ("bash scripts/setup_venv.sh", "bash scripts/setup_metaworld.sh", "python -m pytest -q\n",
                 "python -m pytest -q -m slow\n"):
        assert line in ci, line
    assert _fresh_block(os.path.join(ROOT, "docs", "install.md")) == block


def test_every_docs_page_is_linked_from_the_readme():
    """The README's documentation table reaches every page of docs/."""
    readme = _read(README)
    for path in DOCS[1:]:
        assert f"(docs/{os.path.basename(path)})" in readme, f"README.md does not link {_rel(path)}"
