"""The mutation check of the recompute tests (``tests/mutation_tables.py``): every single-number edit of a printed
cell in a copy of the committed tables — per-task rows, averages and totals, intervals, p-values, counts, the
sentences the checks recompute, each table's cost line and the README's generated sections — fails a check of
``tests/recompute.py``."""

import pytest

import mutation_tables


@pytest.mark.slow
def test_every_single_number_edit_of_a_cell_fails_a_check():
    tally = mutation_tables.run()
    tried, caught = tally["cell"]
    print(mutation_tables.report(tally))
    assert tried >= 6500, f"only {tried} printed numbers edited"
    assert caught == tried, mutation_tables.report(tally)
    for rel, per in tally["per_file"].items():
        assert per["cell"][0] > 0, f"{rel}: no printed number edited"


def test_the_mutation_check_catches_and_misses_what_it_should(monkeypatch):
    """Over one small table: every cell edit is caught by its check, and with a check that reads nothing every edit
    is listed as uncaught (the harness counts misses, it does not only count runs)."""
    tally = mutation_tables.run(["results/hparams_rlow.md"])
    assert tally["cell"][0] >= 60 and tally["cell"][1] == tally["cell"][0], mutation_tables.report(tally)
    monkeypatch.setitem(mutation_tables.CHECKS, "results/hparams_rlow.md", [lambda root: 0])
    blind = mutation_tables.run(["results/hparams_rlow.md"])
    assert blind["cell"] == [tally["cell"][0], 0]
    assert len([u for u in blind["uncaught"] if u[1] == "cell"]) == tally["cell"][0]
