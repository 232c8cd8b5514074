"""The mutation check of the recompute tests: edit each printed number of a copy of the tables in turn and see a
check fail.

A copy of ``results/**/*.md`` and ``docs/results.md`` (the results page) goes to a temporary directory. For every number printed in a table
row, and in the sentences the checks recompute (a table's cost line, findings.md's tally and bootstrap summary,
budget.md's answer, the pilots' rules and choices, the plans' and the campaign's counts, the diagnosis's pooled
lines), of every file ``recompute.py`` covers, its last digit is changed (0→1, …, 9→8) in the copy, that file's own
checks run in this process (the records' side is cached, so an edit costs milliseconds), and the edit counts as
caught when one of them fails. A table file's edits are judged by its own checks alone, not by the results page's
comparison (which would catch them whatever the recomputation does); the results page's generated sections (its
copies of the table files, the campaign's cost sentence, the Meta-World tables' count of recorded runs) by the checks
that read the page.

Numbers on the other lines of a table file (its notes describing the settings: protocol version, interval level,
seeds, budget) are edited as well and tallied apart as notes, with the number of them a check catches anyway;
``NOT_RECOMPUTED`` names the printed numbers no committed record can give again, and why. The protocols
(``results/PROTOCOL.md``, ``results/metaworld/PROTOCOL.md``) are the pre-registered plan: only their pilot entries,
copies of the pilots' numbers, are edited (``ONLY_TABLES``).

    python -m tests.mutation_tables          # prints the tally and every uncaught edit; exit status 1 if a cell edit
                                             # is uncaught (file arguments: only those files)
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
    "results/entropy.md": [rc.check_entropy],
    "results/pilot.md": [rc.check_cpu_pilot],
    "results/campaign.md": [rc.check_campaign],
    "results/campaign_plan.md": [rc.check_campaign],
    "results/metaworld/pilot.md": [rc.check_metaworld_pilot],
    "results/metaworld/plan.md": [rc.check_metaworld_plans],
    "results/metaworld/target/plan.md": [rc.check_metaworld_plans],
    "results/metaworld/diagnosis/diagnose.md": [lambda r: rc.check_diagnose(r, "displacements")],
    "results/metaworld/target/diagnosis/diagnose.md": [lambda r: rc.check_diagnose(r, "targets")],
    "results/metaworld/diagnosis/README.md": [rc.check_diagnosis_note, rc.check_diagnosis_note_prose],
    rc.RESULTS_PAGE: [rc.check_readme_copies, rc.check_campaign, rc.check_metaworld_plans],
    "results/PROTOCOL.md": [rc.check_protocol_pilot_entries],
    "results/metaworld/PROTOCOL.md": [rc.check_protocol_pilot_entries],
}
for _rel in rc.SETTINGS_FILES:  # each table's settings line
    CHECKS[_rel] = CHECKS[_rel] + [lambda r, rel=_rel: rc.check_protocol_line(r, rel)]
for _rel in rc.NOTES_FILES:  # the notes whose numbers come from the records
    CHECKS[_rel] = CHECKS[_rel] + [lambda r, rel=_rel: rc.check_notes(r, rel)]
# the sentences (besides table rows) whose numbers the checks recompute
CHECKED_SENTENCES = tuple(re.compile(p) for p in (
    r"^Over the \d+ \(comparison, task\) cells", r"^They give the same verdict", r"^\*\*The answer\*\*",
    r"^- Cost: ", r"^- DP\+HiPolicy (at stride 1 − DP|− DP\+HiPolicy at stride 1), over the ",
    r"^- No DP\+HiPolicy at stride 1 pass for", r"^- Record the choice", r"^- DP only \(one stride\)",
    r"^- Rule: T = ", r"^- Measured costs", r"^- Budget rules", r"^\d+ of \d+ evaluations (pending|recorded)",
    r"^Spent so far", r"^The campaign cost", r"^\d+ evaluations; tables", r"^The stride-1 pass minus DP",
    r"^Protocol: `", r"^- Paired columns: ", r"^- Success rate \(%\) (with entropy-guided|over \d+ episodes)",
    r"^- DP3 columns: ", r"^- DP: one stride", r"^- Strides: share of HiPolicy", r"^- Does the gap",
    r"^- Point-cloud columns on no task"))
# the protocols are the pre-registered plan; only their pilot entries (copies of the pilots' numbers) are results
ONLY_TABLES = {"results/PROTOCOL.md": "| task | DP @ 100 demos", "results/metaworld/PROTOCOL.md": "| task | DP @ "}
# lines with printed numbers that no committed record can give again, with the reason (tallied as notes)
NOT_RECOMPUTED = {("results/pilot.md", "- Cost: "): "the pilot's cost counts the training of pick_place runs "
                                                     "retrained since, whose training times the records no longer "
                                                     "hold"}
NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _readme_copy_lines(lines: list[str]) -> set[int]:
    """The results page's generated sections: from a table's begin marker to its end marker (the copies of the
    table files, the campaign's cost sentence and the Meta-World tables' count of recorded runs)."""
    out, inside = set(), False
    for i, line in enumerate(lines):
        if line.startswith("<!-- end of"):
            inside = False
        elif line.startswith("<!-- Meta-World table:") or line.startswith("<!-- campaign tables:"):
            inside = True
        elif inside:
            out.add(i)
    return out


def sites(rel: str, text: str) -> list[tuple[int, int, str]]:
    """(line, offset of the digit to change, kind) for every printed number: kind 'cell' for table rows and checked
    sentences (the results page: every line of its copies), 'note' for the rest of a table file; commands left
    out."""
    lines = text.split("\n")
    copies = _readme_copy_lines(lines) if rel == rc.RESULTS_PAGE else None
    if rel in ONLY_TABLES:  # the table starting so, to its last row
        start = next(i for i, line in enumerate(lines) if line.startswith(ONLY_TABLES[rel]))
        end = next(i for i in range(start, len(lines)) if not lines[i].startswith("|"))
        copies = set(range(start, end))
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
            if any(rel == f and line.startswith(start) for f, start in NOT_RECOMPUTED):
                kind = "note"
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
