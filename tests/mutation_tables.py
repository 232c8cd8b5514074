"""The mutation check of the recompute tests: edit each printed number of a copy of the tables in turn and see a
check fail.

A copy of ``results/**/*.md`` and ``README.md`` goes to a temporary directory; for every number printed in a table
row (and in the sentences the checks recompute: findings.md's tally and bootstrap summary, budget.md's answer, each
table's cost line) of
every file ``recompute.py`` covers, its last digit is changed (0→1, …, 9→8) in the copy, that file's own checks run
in this process (the records' side is cached, so an edit costs milliseconds), and the edit counts as caught when one
of them fails. The README's copies are edited too, checked by ``check_readme_copies`` alone; a table file's edits
by its own checks alone (not by the README comparison, which would catch them whatever the recomputation does).

Numbers on the other lines of a table file (its notes describing the settings) are edited as well and
tallied apart: they are the table's inputs and descriptions, not cells; the tally says how many of them a check
catches anyway.

    python -m tests.mutation_tables          # prints the tally and every uncaught edit; exit status 1 if a cell edit
                                             # is uncaught
"""

from __future__ import annotations

import os
import re
import shutil
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import recompute as rc  # noqa: E402

CHECKS = {
    "results/findings.md": [rc.check_findings_table, lambda r: rc.check_findings_speed(r, "100 demos"),
                            lambda r: rc.check_findings_speed(r, "Rlow"), rc.check_findings_budget,
                            rc.check_findings_bootstrap],
    "results/metaworld/main.md": [lambda r: rc.check_metaworld_main(r, "main")],
    "results/metaworld/target/main.md": [lambda r: rc.check_metaworld_main(r, "amendment-1"),
                                         rc.check_metaworld_amendment],
    "results/main.md": [lambda r: rc.check_main(r, "main")],
    "results/main_rlow.md": [lambda r: rc.check_main(r, "main_rlow")],
    "results/execution.md": [lambda r: rc.check_execution(r, "execution")],
    "results/execution_rlow.md": [lambda r: rc.check_execution(r, "execution_rlow")],
    "results/ablation_rlow.md": [rc.check_ablation],
    "results/hparams_rlow.md": [rc.check_hparams],
    "results/thresholds_rlow.md": [rc.check_thresholds],
    "results/budget.md": [rc.check_budget],
    "README.md": [rc.check_readme_copies],
}
# the sentences (besides table rows) whose numbers the checks recompute
CHECKED_SENTENCES = (re.compile(r"^Over the \d+ \(comparison, task\) cells"), re.compile(r"^They give the same verdict"),
                     re.compile(r"^\*\*The answer\*\*"), re.compile(r"^- Cost: "))
NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _readme_copy_lines(lines: list[str]) -> set[int]:
    """The README lines inside its copies of the table files (their notes included: a copy must be exact): from a
    copy's title to the next heading as high as it, or the generated section's end marker."""
    out, level = set(), None
    for i, line in enumerate(lines):
        heading = re.match(r"^(#+) ", line)
        if re.match(r"^#+ .* — `results/[^`]+\.md`$", line):
            level = len(heading.group(1))
        elif line.startswith("<!--") or (heading and level is not None and len(heading.group(1)) <= level):
            level = None
        if level is not None:
            out.add(i)
    return out


def sites(rel: str, text: str) -> list[tuple[int, int, str]]:
    """(line, offset of the digit to change, kind) for every printed number: kind 'cell' for table rows and checked
    sentences (the README: every line of its copies), 'note' for the rest of a table file; commands left out."""
    lines = text.split("\n")
    copies = _readme_copy_lines(lines) if rel == "README.md" else None
    out = []
    for i, line in enumerate(lines):
        if line.startswith("Command: "):
            continue
        if copies is not None:
            if i not in copies:
                continue
            kind = "cell"
        else:
            kind = "cell" if line.startswith("|") or any(p.match(line) for p in CHECKED_SENTENCES) else "note"
        for m in NUMBER.finditer(line):
            out.append((i, m.end() - 1, kind))
    return out


def _edit(line: str, pos: int) -> str:
    d = int(line[pos])
    return line[:pos] + str(d + 1 if d < 9 else 8) + line[pos + 1:]


def _fails(checks, root: str) -> str | None:
    for check in checks:
        try:
            check(root)
        except Exception as e:  # noqa: BLE001 - any failure of a check is a catch
            return f"{type(e).__name__}: {str(e).splitlines()[0][:160]}"
    return None


def run(files=None, verbose: bool = False) -> dict:
    """Edit every printed number of ``files`` (default: every covered file) in a copy, one at a time → the tally
    {'cell': [tried, caught], 'note': [tried, caught], 'uncaught': [(file, kind, line no, edited line)], ...}."""
    files = list(CHECKS) if files is None else files
    tally = {"cell": [0, 0], "note": [0, 0], "uncaught": [], "per_file": {}}
    with tempfile.TemporaryDirectory() as root:
        for rel in set(CHECKS) | {p for p in rc.README_COPIES}:
            os.makedirs(os.path.dirname(os.path.join(root, rel)) or root, exist_ok=True)
            shutil.copy(os.path.join(rc.ROOT, rel), os.path.join(root, rel))
        for rel in files:
            path = os.path.join(root, rel)
            with open(path) as f:
                original = f.read()
            reason = _fails(CHECKS[rel], root)
            assert reason is None, f"{rel}: the unedited copy fails its checks: {reason}"
            lines = original.split("\n")
            per = tally["per_file"].setdefault(rel, {"cell": [0, 0], "note": [0, 0]})
            for i, pos, kind in sites(rel, original):
                edited = lines[:i] + [_edit(lines[i], pos)] + lines[i + 1:]
                with open(path, "w") as f:
                    f.write("\n".join(edited))
                reason = _fails(CHECKS[rel], root)
                for t in (tally[kind], per[kind]):
                    t[0] += 1
                    t[1] += reason is not None
                if reason is None:
                    tally["uncaught"].append((rel, kind, i + 1, edited[i]))
                elif verbose:
                    print(f"{rel}:{i + 1}: caught ({reason})")
            with open(path, "w") as f:
                f.write(original)
    return tally


def report(tally: dict) -> str:
    lines = ["file | cell edits caught / tried | note edits caught / tried"]
    for rel, per in tally["per_file"].items():
        lines.append(f"{rel} | {per['cell'][1]} / {per['cell'][0]} | {per['note'][1]} / {per['note'][0]}")
    lines.append(f"all | {tally['cell'][1]} / {tally['cell'][0]} | {tally['note'][1]} / {tally['note'][0]}")
    cells = [u for u in tally["uncaught"] if u[1] == "cell"]
    lines.append(f"uncaught cell edits: {len(cells)}")
    lines += [f"  {rel}:{n}: {line[:200]}" for rel, _, n, line in cells]
    notes = [u for u in tally["uncaught"] if u[1] == "note"]
    lines.append(f"uncaught note edits (descriptions of the settings): {len(notes)}")
    lines += [f"  {rel}:{n}: {line[:160]}" for rel, _, n, line in notes]
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    start = time.time()
    tally = run(argv or None)
    print(report(tally))
    print(f"{time.time() - start:.0f} s")
    return 1 if any(u[1] == "cell" for u in tally["uncaught"]) else 0


if __name__ == "__main__":
    sys.exit(main())
