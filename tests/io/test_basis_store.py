"""The basis store: a read-only store is read, and what it lacks goes to its stand-in."""

import os
import subprocess
import sys

import numpy as np

from pipeline.io.basis_store import BasisStore, stand_in
from tests.conftest import ROOT
from tests.readonly import frozen, tree_bytes, unprivileged

SCRIPT = """
import sys
import numpy as np
from pipeline.io.basis_store import BasisStore
store = BasisStore(sys.argv[1])
store.save_array("entry", "first", np.arange(3))
store.save_array("entry", "second", np.arange(2))
print(store.load_array("entry", "first").tolist(), store.load_array("entry", "kept").tolist(),
      store.has("entry", "second"))
"""


def test_a_read_only_store_is_read_and_what_it_lacks_goes_to_its_stand_in_with_one_notice(tmp_path, monkeypatch):
    store, cache = tmp_path / "bases", tmp_path / "cache"
    BasisStore(store).save_array("entry", "kept", np.array([7.0]))
    env = dict(os.environ, PYTHONPATH=str(ROOT), POINTMARK_CACHE=str(cache))
    with frozen(store):
        before = tree_bytes(store)
        res = subprocess.run([*unprivileged(), sys.executable, "-c", SCRIPT, str(store)], cwd=tmp_path, env=env,
                             capture_output=True, text=True, timeout=120)
        assert tree_bytes(store) == before                            # the store is untouched
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["[0,", "1,", "2]", "[7.0]", "True"]
    notice = res.stderr.strip().splitlines()
    assert len(notice) == 1 and f"{store} cannot be written" in notice[0], res.stderr
    assert {p.relative_to(cache).parts[-2:] for p in cache.rglob("*.npz")} == {("entry", "first.npz"),
                                                                               ("entry", "second.npz")}
    monkeypatch.setenv("POINTMARK_CACHE", str(cache))
    assert (stand_in(store) / "entry" / "first.npz").is_file()         # every process finds the same one


def test_a_store_that_refuses_for_another_reason_stops_with_that_error(tmp_path, monkeypatch):
    monkeypatch.setenv("POINTMARK_CACHE", str(tmp_path / "cache"))
    (tmp_path / "bases").write_text("a file where the store's folder should be\n")
    try:
        BasisStore(tmp_path / "bases").save_array("entry", "x", np.arange(2))
    except OSError as exc:
        assert exc.filename is None or "bases" in str(exc.filename)
    else:
        raise AssertionError("a store path that is a file was written to")
    assert not (tmp_path / "cache").exists()


def test_a_damaged_entry_in_the_store_is_read_from_the_stand_in(tmp_path, monkeypatch):
    monkeypatch.setenv("POINTMARK_CACHE", str(tmp_path / "cache"))
    (tmp_path / "bases" / "entry").mkdir(parents=True)
    (tmp_path / "bases" / "entry" / "x.npz").write_bytes(b"not an npz")
    spare = stand_in(tmp_path / "bases") / "entry"
    spare.mkdir(parents=True)
    np.savez(spare / "x.npz", array=np.arange(4))
    assert BasisStore(tmp_path / "bases").load_array("entry", "x").tolist() == [0, 1, 2, 3]
