"""The table of bad inputs and configs (tests/fuzz/bad_inputs.py): every case is handled cleanly."""

import io

import pytest

from tests.fuzz import bad_inputs



def test_the_table_has_at_least_100_cases_in_every_category():
    cases = bad_inputs.cases()
    assert len(cases) >= 100
    assert len({c.name for c in cases}) == len(cases)
    assert {c.category for c in cases} == {"PLY file", "LAS/LAZ file", "PCD/XYZ/PTS file", "argument",
                                          "output path", "config"}


@pytest.mark.slow
def test_every_bad_input_is_handled_cleanly(secret_env):
    selected = bad_inputs.cases()
    out = io.StringIO()
    rows, failures = bad_inputs.run_all(selected, stream=out)
    assert not failures, out.getvalue()
    assert sum(t for t, _ in rows.values()) == len(selected)
