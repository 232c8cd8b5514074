"""Every printed number of the committed tables, recomputed from the committed run records.

What a reader quotes — ``results/findings.md``; the campaign's tables (``main.md``, ``main_rlow.md``,
``execution.md``, ``execution_rlow.md``, ``ablation_rlow.md``, ``hparams_rlow.md``, ``thresholds_rlow.md``,
``budget.md``), its pilot, index and plan (``pilot.md``, ``campaign.md``, ``campaign_plan.md``) and version 1's
``entropy.md``; the Meta-World tables (``results/metaworld/main.md``, amendment 1's ``target/main.md``), their
pilot, plans and post hoc diagnosis (``diagnosis/diagnose.md``, ``target/diagnosis/diagnose.md``, the basketball
note ``diagnosis/README.md``); and the results page's generated copies of them (``docs/results.md``) — is rebuilt by
``recompute.py`` cell by cell (point, interval, p, verdict, every column, every average and total row, the cost
lines, the settings lines and the notes' record-given numbers) from
``results/runs/<budget>/<task>/<obs>/<variant>/seed<k>.json`` and the committed diagnosis files, with json, numpy
and scipy alone — not the project's statistics module, not its table code, not the tables' JSON (``entropy.json``
excepted: its runs are not among the records) — and compared with the printed text, so a table left stale after new
records, a pairing of the wrong seeds or episodes, a slip in an interval, a p or a verdict, or an edit of one
printed digit fails here, naming the cell. A missing file or section fails, it is never skipped, and each test
counts the cells it compared and fails below the count stated beside it (the committed tables' full size).

The mutation check (``tests/mutation_tables.py``, the slow test ``tests/test_tables_mutation.py``) edits each
printed number of a copy of the tables in turn and shows that these checks fail on every edit of a cell.
"""

from __future__ import annotations

import numpy as np
import pytest

import recompute as rc

# the number of cells each check compares in the committed tables (headers, labels and numbers; a table that
# loses rows or columns, or a check that stops comparing, falls below it)
MINIMUM = {
    "findings": 114, "speed": 42, "budget": 25, "bootstrap": 287,
    "metaworld main": 354, "metaworld amendment-1": 166, "amendment secondary": 75,
    "main": 81, "main_rlow": 57, "execution": 129, "execution_rlow": 129, "ablation_rlow": 65, "hparams_rlow": 45,
    "thresholds_rlow": 63, "budget.md": 83, "results page": 395, "diagnose displacements": 169, "diagnose targets": 78,
    "diagnosis note": 42, "diagnosis reading": 76, "protocol pilots": 32, "cpu pilot": 26, "metaworld pilot": 43, "campaign": 29, "metaworld plans": 42, "entropy": 32,
}


def test_every_paired_cell_recomputes_from_the_records():
    """findings.md's main table: each task's paired cell (point, interval, verdict), the average with its Welch
    interval, p and verdict, the exact sign-flip p, the episode-level McNemar p, the leave-one-task-out column and
    the W/T/L tally of every row, and the sentence counting wins, ties and losses."""
    n = rc.check_findings_table(rc.ROOT)
    assert n >= MINIMUM["findings"], f"findings.md's main table: {n} cells checked"


@pytest.mark.parametrize("regime", ["100 demos", "Rlow"])
def test_same_network_speed_rows_recompute_from_the_records(regime):
    """HiPolicy vs w/o EG on one network: both success rates, the success cost, both steps to success and the steps
    saved with its p and word, per task and on average."""
    n = rc.check_findings_speed(rc.ROOT, regime)
    assert n >= MINIMUM["speed"], f"speed table ({regime}): {n} cells checked"


def test_training_budget_rows_recompute_from_the_records():
    """DP+HiPolicy − DP by training steps (2,000 steps are the main table's runs, longer ones ``_t<steps>``) and the
    protocol's shrinks / holds / grows answer per task."""
    n = rc.check_findings_budget(rc.ROOT)
    assert n >= MINIMUM["budget"], f"budget rows: {n} cells checked"


def test_bootstrap_beside_the_t_interval_recomputes_from_the_records():
    """Every row of the side-by-side section: the t cell as the main table's, version 1's hierarchical bootstrap
    interval written again from its definition (its random stream included, so it reproduces to the printed
    decimal), each verdict, and the summary's count and list of splits."""
    n = rc.check_findings_bootstrap(rc.ROOT)
    assert n >= MINIMUM["bootstrap"], f"bootstrap section: {n} cells checked"


@pytest.mark.parametrize("table", ["main", "amendment-1"])
def test_metaworld_table_recomputes_from_the_records(table):
    """Every row of the Meta-World success table — task rows, each DP3 group's average and the total — with its
    DP3 group, demo steps, both columns' success with intervals, the paired differences with p and verdict; each
    paired cell's exact sign-flip p and episode-level McNemar p (the section the paired note points to); and DP3's
    metric beside the published numbers, with the averages and the gaps."""
    n = rc.check_metaworld_main(rc.ROOT, table)
    assert n >= MINIMUM[f"metaworld {table}"], f"{table}: {n} cells checked"


def test_metaworld_target_secondary_tables_recompute_from_the_records():
    """Amendment 1's secondary comparison (DP on targets − DP on displacements, per task, per group, in total) and
    its steps table (success, the success cost, steps, steps saved with p and word, the chunked expert's steps and
    the demos' steps at the bound; the average's steps over the tasks where both columns have steps, named in the
    notes)."""
    n = rc.check_metaworld_amendment(rc.ROOT)
    assert n >= MINIMUM["amendment secondary"], f"amendment 1's secondary tables: {n} cells checked"


@pytest.mark.parametrize("name", ["main", "main_rlow"])
def test_main_tables_recompute_from_the_records(name):
    """results/main.md and main_rlow.md: every task row, each group's average and the total — the Precise and Demo
    steps columns, each column's success with its interval (the baseline seeds 3, 4 included), the relative gains of
    the average rows and the paired differences with p and verdict."""
    n = rc.check_main(rc.ROOT, name)
    assert n >= MINIMUM[name], f"{name}.md: {n} cells checked"


@pytest.mark.parametrize("name", ["execution", "execution_rlow"])
def test_execution_tables_recompute_from_the_records(name):
    """Success, steps to success and decisions of DP, DP+TE, DP+AAC, w/o EG and HiPolicy, HiPolicy's strides and
    the three paired columns, per task and on average."""
    n = rc.check_execution(rc.ROOT, name)
    assert n >= MINIMUM[name], f"{name}.md: {n} cells checked"


def test_ablation_hparams_and_thresholds_tables_recompute_from_the_records():
    """The Rlow ablations: conditioning / fusion / hierarchy columns with the paired Hier. − w/o Hier. (every group
    average); the (L_h, L_c, M) rows; each threshold pair's mean thresholds, success, steps and strides."""
    for name, check in (("ablation_rlow", rc.check_ablation), ("hparams_rlow", rc.check_hparams),
                        ("thresholds_rlow", rc.check_thresholds)):
        n = check(rc.ROOT)
        assert n >= MINIMUM[name], f"{name}.md: {n} cells checked"


def test_budget_table_recomputes_from_the_records():
    """results/budget.md: both columns' success and steps per training length, the paired difference with p and
    verdict, and the answer sentence (each gap and the protocol's shrinks / holds / grows)."""
    n = rc.check_budget(rc.ROOT)
    assert n >= MINIMUM["budget.md"], f"budget.md: {n} cells checked"


def test_readme_copies_are_the_committed_tables():
    """The results page's generated sections (docs/results.md, the README's before issue #61) hold each table file
    line for line (which the tests above recompute)."""
    n = rc.check_readme_copies(rc.ROOT)
    assert n >= MINIMUM["results page"], f"{rc.RESULTS_PAGE}: {n} lines checked"


@pytest.mark.parametrize("which", ["displacements", "targets"])
def test_metaworld_diagnosis_recomputes_from_the_records(which):
    """The post hoc diagnosis on displacements and on absolute targets: the demos' coverage and share at the bound,
    DP+HiPolicy's strides, the chunked expert's success in both action spaces, DP, DP+HiPolicy and the same network
    at stride 1 (its committed pass, checked to be the recorded network) with both paired differences, per task and
    on average; the pooled lines, the missing passes and the cost line."""
    n = rc.check_diagnose(rc.ROOT, which)
    assert n >= MINIMUM[f"diagnose {which}"], f"diagnose ({which}): {n} cells checked"


def test_basketball_diagnosis_note_recomputes_from_the_records():
    """The note's per-seed table and pooled line, and the numbers of its reading (success, entropies against the
    thresholds, stride shares, coverage and bound ranges over the tasks, the chunked expert per stride)."""
    n = rc.check_diagnosis_note(rc.ROOT)
    assert n >= MINIMUM["diagnosis note"], f"diagnosis README: {n} cells checked"
    n = rc.check_diagnosis_note_prose(rc.ROOT)
    assert n >= MINIMUM["diagnosis reading"], f"diagnosis README's reading: {n} numbers checked"


def test_pilot_tables_recompute_from_the_records():
    """The CPU pilot (DP at 100 demos, each candidate until one lands in range, the protocol's choice, which
    results/pilot_choice.json must hold) and the Meta-World pilot (success per checkpoint, T by its rule, the
    measured rates and the budget rules' outcome from them, its cost)."""
    n = rc.check_cpu_pilot(rc.ROOT)
    assert n >= MINIMUM["cpu pilot"], f"pilot.md: {n} cells checked"
    n = rc.check_metaworld_pilot(rc.ROOT)
    assert n >= MINIMUM["metaworld pilot"], f"metaworld/pilot.md: {n} cells checked"


def test_the_protocols_pilot_entries_are_the_pilots_numbers():
    """results/PROTOCOL.md's Rlow pilot entry and results/metaworld/PROTOCOL.md's training-length pilot entry: each
    number recomputed as the pilots' tables are."""
    n = rc.check_protocol_pilot_entries(rc.ROOT)
    assert n >= MINIMUM["protocol pilots"], f"the protocols' pilot entries: {n} cells checked"


def test_campaign_index_and_plans_recompute_from_the_records():
    """campaign.md's cost of every cpu record and count of the tables' evaluations, campaign_plan.md's '366 of 366'
    with nothing left, the Meta-World plans' pending count and spent CPU-hours, and the results page's copies of
    them."""
    n = rc.check_campaign(rc.ROOT)
    assert n >= MINIMUM["campaign"], f"campaign: {n} cells checked"
    n = rc.check_metaworld_plans(rc.ROOT)
    assert n >= MINIMUM["metaworld plans"], f"metaworld plans: {n} cells checked"


def test_entropy_table_recomputes_from_its_per_seed_summaries():
    n = rc.check_entropy(rc.ROOT)
    assert n >= MINIMUM["entropy"], f"entropy.md: {n} cells checked"


@pytest.mark.parametrize("rel", rc.SETTINGS_FILES)
def test_each_tables_settings_line_recomputes_from_the_records(rel):
    """The settings line under each table's command: protocol, regime (Rlow's change per task from its runs'
    records), seeds, the interval's level, the budget's model, steps, batch, demos, episodes, samples and sampler
    steps from the records."""
    assert rc.check_protocol_line(rc.ROOT, rel) >= 10, rel


@pytest.mark.parametrize("rel", rc.NOTES_FILES)
def test_each_tables_notes_recompute_from_the_records(rel):
    """The numbers in a table's notes that the records give: the protocol's version, the interval's level and its
    p threshold, the calibration percentiles, the point clouds' size, TE's decay, the strides, the episodes and
    their initial states, the training steps and demos, the periodic checkpoints."""
    assert rc.check_notes(rc.ROOT, rel) >= 2, rel


def test_a_missing_table_or_section_fails(tmp_path):
    """The checks read what is committed: a missing file or a renamed section fails with its name, never skips."""
    with pytest.raises(AssertionError, match="findings.md: a committed table is missing"):
        rc.check_findings_table(str(tmp_path))
    (tmp_path / "results").mkdir()
    text = open(f"{rc.ROOT}/results/findings.md").read()
    (tmp_path / "results" / "findings.md").write_text(text.replace("## Training budget", "## Budget"))
    with pytest.raises(AssertionError, match="no section 'Training budget"):
        rc.check_findings_budget(str(tmp_path))


def test_one_edited_digit_fails_its_check(tmp_path):
    """A cell whose printed value moves by one in its last digit fails (the comparison is of the printed text)."""
    (tmp_path / "results").mkdir()
    text = open(f"{rc.ROOT}/results/findings.md").read()
    edited = text.replace("+32.2 [+7.8, +56.6], p=0.032 (faster)", "+32.2 [+7.8, +56.6], p=0.033 (faster)")
    assert edited != text
    (tmp_path / "results" / "findings.md").write_text(edited)
    with pytest.raises(AssertionError, match="Steps saved"):
        rc.check_findings_speed(str(tmp_path), "Rlow")


MW_MAIN, MW_TARGET = "results/metaworld/main.md", "results/metaworld/target/main.md"
MW_DIAGNOSES = ("results/metaworld/diagnosis/diagnose.md", "results/metaworld/target/diagnosis/diagnose.md")


def _copy_with(tmp_path, rel: str, old: str, new: str) -> str:
    """A copy of the committed tables under ``tmp_path`` with ``old`` (which must be in ``rel``) replaced by
    ``new`` in ``rel``; → the copy's root."""
    for name in (MW_MAIN, MW_TARGET, *MW_DIAGNOSES, "results/findings.md"):
        dest = tmp_path / name
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_text(open(f"{rc.ROOT}/{name}").read())
    text = (tmp_path / rel).read_text()
    assert old in text, f"{rel} no longer holds {old!r}"
    (tmp_path / rel).write_text(text.replace(old, new))
    return str(tmp_path)


def test_a_steps_average_over_other_tasks_than_its_partner_fails(tmp_path):
    """Issue #58: the steps table's average row once gave DP's steps over 3 tasks beside DP+HiPolicy's over the 2
    it succeeded on (83.3 against 84.6; over those 2 DP takes 90.9), and findings.md's w/o EG steps over 3 tasks
    beside HiPolicy's over 4. Both numbers fail, and so does the table without the sentence naming the tasks the
    average covers."""
    root = _copy_with(tmp_path, MW_TARGET, "| 90.9 [89.1, 92.7] |", "| 83.3 [82.1, 84.5] |")
    with pytest.raises(AssertionError, match="column 'DP steps'.*83.3"):
        rc.check_metaworld_amendment(root)
    sentence = "; its steps and steps saved average the 2 on which both DP and DP+HiPolicy have steps to success"
    root = _copy_with(tmp_path, MW_TARGET, sentence, "")
    with pytest.raises(AssertionError, match="its steps and steps saved average"):
        rc.check_metaworld_amendment(root)
    root = _copy_with(tmp_path, "results/findings.md", "| 50.9 [48.8, 52.9] |", "| 97.0 [27.2, 166.8] |")
    with pytest.raises(AssertionError, match="column 'HiPolicy steps'.*97.0"):
        rc.check_findings_speed(root, "100 demos")


@pytest.mark.parametrize("rel", [MW_MAIN, MW_TARGET])
def test_the_meta_world_tables_report_their_mcnemar_and_sign_flip_p(tmp_path, rel):
    """Issue #58: the Meta-World tables said their episode-level McNemar p was in findings.md (which has no row of
    theirs) and reported no sign-flip p, which their protocol promises. The old pointer fails, a table without the
    section fails, and a wrong p in it fails (the Monte Carlo sign-flip p of 0 that 30 differences once gave)."""
    table = "main" if rel == MW_MAIN else "amendment-1"
    pointer = "Each paired cell's sign-flip p over seeds and episode-level McNemar p are in the section"
    text = open(f"{rc.ROOT}/{rel}").read()
    old_note = text[text.index(pointer):].split("\n")[0]
    root = _copy_with(tmp_path, rel, old_note, "The episode-level McNemar p is in findings.md.")
    with pytest.raises(AssertionError, match="Paired columns"):
        rc.check_notes(root, rel)
    section = text[text.index("## Paired comparisons: sign-flip and McNemar p"):text.index("## DP3's metric")]
    root = _copy_with(tmp_path, rel, section, "")
    with pytest.raises(AssertionError, match="no section 'Paired comparisons: sign-flip and McNemar p'"):
        rc.check_metaworld_main(root, table)
    if rel == MW_MAIN:
        root = _copy_with(tmp_path, rel, "| **Total average** | 1.9e-09 | <1e-300 |",
                          "| **Total average** | <1e-300 | <1e-300 |")
        with pytest.raises(AssertionError, match="Total average.*sign-flip p"):
            rc.check_metaworld_main(root, table)
        root = _copy_with(tmp_path, rel, "| metaworld:basketball | 0.25 | 3.6e-12 |",
                          "| metaworld:basketball | 0.25 | 3.7e-12 |")
        with pytest.raises(AssertionError, match="McNemar p"):
            rc.check_metaworld_main(root, table)


@pytest.mark.parametrize("rel", MW_DIAGNOSES)
def test_the_diagnosis_says_what_ends_where_the_demo_did(tmp_path, rel):
    """Issue #58: on absolute targets the diagnosis said 'a segment ends where the demo did', true of its commanded
    targets, not of the hand, which moves at most 1 cm a step towards them; and it pointed to findings.md for a
    McNemar p it has none of. The old wording fails, and so does the old pointer."""
    now = ("Both are '–' on absolute hand targets (`metaworld-target:<task>`), where a segment's commanded targets "
           "end where the demo's did, and the hand, moved at most 1 cm a step towards them, may lag them.")
    root = _copy_with(tmp_path, rel, now, "Both are '–' on absolute hand targets (`metaworld-target:<task>`), where "
                                          "a segment ends where the demo did.")
    with pytest.raises(AssertionError, match="commanded targets"):
        rc.check_notes(root, rel)
    end = "wins / loses when the interval excludes 0 (p < 0.05).\n"
    root = _copy_with(tmp_path, rel, end, end[:-1] + " The episode-level McNemar p is in findings.md.\n")
    with pytest.raises(AssertionError, match="Paired columns"):
        rc.check_notes(root, rel)


def test_the_recomputed_sign_flip_count_is_the_enumeration():
    """The recomputation's exact sign-flip count past 16 differences (branch and bound) equals the count over
    every sign pattern, on differences of mixed signs, with ties and zeros."""
    rng = np.random.default_rng(0)
    for n in (1, 5, 12, 14):
        for v in (rng.normal(size=n), rng.integers(-2, 3, size=n).astype(float), np.abs(rng.normal(size=n))):
            signs = 1 - 2 * ((np.arange(2 ** n)[:, None] >> np.arange(n)) & 1)
            for threshold in (abs(v.sum()) - 1e-12, 0.5 * np.abs(v).sum(), 1e-3):
                assert rc.sign_flip_count(v, threshold) == int(np.sum(np.abs(signs @ v) >= threshold)), (n, v)
    # 30 differences of one sign (the Meta-World total): only all-plus and all-minus reach the observed mean
    v = -0.5 - 0.01 * np.arange(30)
    assert rc.sign_flip_count(v, abs(v.sum()) - 1e-12) == 2
