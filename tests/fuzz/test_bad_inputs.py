"""The table of bad inputs and configs (tests/fuzz/bad_inputs.py): every case is handled cleanly."""

import io

import pytest

from tests.fuzz import bad_inputs

# Known not clean, owned elsewhere: remove a name once it is fixed (the xfail is strict).
KNOWN = {"attack strength negative"}   # pipeline/surface.py parse_attack accepts noise:-1


def test_the_table_has_at_least_100_cases_in_every_category():
    cases = bad_inputs.cases()
    assert len(cases) >= 100
    assert len({c.name for c in cases}) == len(cases)
    assert {c.category for c in cases} == {"PLY file", "LAS/LAZ file", "PCD/XYZ/PTS file", "argument",
                                          "output path", "config"}


@pytest.mark.slow
def test_every_bad_input_is_handled_cleanly(secret_env):
    selected = [c for c in bad_inputs.cases() if c.name not in KNOWN]
    out = io.StringIO()
    rows, failures = bad_inputs.run_all(selected, stream=out)
    assert not failures, out.getvalue()
    assert sum(t for t, _ in rows.values()) == len(selected)


@pytest.mark.xfail(strict=True, reason="owned by pipeline/surface.py: a negative attack strength is accepted")
@pytest.mark.parametrize("name", sorted(KNOWN))
def test_known_gaps(secret_env, name):
    case = next(c for c in bad_inputs.cases() if c.name == name)
    _, failures = bad_inputs.run_all([case], stream=io.StringIO())
    assert not failures
