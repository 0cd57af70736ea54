"""The basis store: a read-only store is read, and what it lacks goes to its stand-in."""

import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.io.basis_store import BasisStore, stand_in
from tests.conftest import ROOT
from tests.readonly import frozen, tree_bytes, unprivileged

SCRIPT = """
import sys
import numpy as np
from pipeline.io.basis_store import BasisStore
store = BasisStore(sys.argv[1])
try:
    for name in sys.argv[2:]:
        store.save_array("entry", name, np.arange(3))
except OSError as exc:
    print(exc.strerror, file=sys.stderr)
    sys.exit(2)
print(*[None if a is None else a.tolist() for a in (store.load_array("entry", n) for n in ("first", "kept"))],
      store.has("entry", "second"), sep=";")
"""


def _run(tmp_path, store, cache, *names):
    env = dict(os.environ, PYTHONPATH=str(ROOT), POINTMARK_CACHE=str(cache))
    return subprocess.run([*unprivileged(), sys.executable, "-c", SCRIPT, str(store), *names], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)


@pytest.fixture()
def store(tmp_path):
    folder = tmp_path / "bases"
    BasisStore(folder).save_array("entry", "kept", np.array([7.0]))
    return folder


def test_a_read_only_store_is_read_and_what_it_lacks_goes_to_its_stand_in_with_one_notice(tmp_path, store,
                                                                                           monkeypatch):
    cache = tmp_path / "cache"
    with frozen(store):
        before = tree_bytes(store)
        res = _run(tmp_path, store, cache, "first", "second")
        assert tree_bytes(store) == before                            # the store is untouched
    assert res.returncode == 0, res.stderr
    assert res.stdout.split(";") == ["[0, 1, 2]", "[7.0]", "True\n"]
    notice = res.stderr.strip().splitlines()
    assert len(notice) == 1 and f"{store} cannot be written" in notice[0], res.stderr
    monkeypatch.setenv("POINTMARK_CACHE", str(cache))
    assert sorted(p.name for p in (stand_in(store) / "entry").iterdir()) == ["first.npz", "second.npz"]


def test_a_stand_in_that_cannot_be_written_either_is_one_error_naming_the_store(tmp_path, store):
    cache = tmp_path / "cache"
    cache.mkdir()
    with frozen(store, cache):
        res = _run(tmp_path, store, cache, "first")
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{store} cannot be written" in lines[0] and "POINTMARK_CACHE" in lines[0], lines


def test_the_store_is_read_before_its_stand_in_and_a_damaged_entry_falls_back(tmp_path, store, monkeypatch):
    monkeypatch.setenv("POINTMARK_CACHE", str(tmp_path / "cache"))
    spare = stand_in(store) / "entry"
    spare.mkdir(parents=True)
    np.savez(spare / "kept.npz", array=np.array([-1.0]))
    np.savez(spare / "first.npz", array=np.arange(4))
    (store / "entry" / "first.npz").write_bytes(b"not an npz")
    with frozen(store):
        res = _run(tmp_path, store, tmp_path / "cache")
    assert res.returncode == 0, res.stderr
    assert res.stdout.split(";")[:2] == ["[0, 1, 2, 3]", "[7.0]"]     # the stand-in's only where the store fails


def test_a_writable_store_never_reads_its_stand_in(tmp_path, store, monkeypatch):
    # an old stand-in (the store was read-only once, or was cleared since) cannot shadow a rebuild
    monkeypatch.setenv("POINTMARK_CACHE", str(tmp_path / "cache"))
    spare = stand_in(store) / "entry"
    spare.mkdir(parents=True)
    np.savez(spare / "gone.npz", array=np.arange(2))
    assert BasisStore(store).load_array("entry", "gone") is None
    assert BasisStore(store).load_array("entry", "kept").tolist() == [7.0]


def test_a_store_path_that_is_a_file_stops_with_that_error(tmp_path, monkeypatch):
    monkeypatch.setenv("POINTMARK_CACHE", str(tmp_path / "cache"))
    (tmp_path / "bases").write_text("a file where the store's folder should be\n")
    with pytest.raises(OSError):
        BasisStore(tmp_path / "bases").save_array("entry", "x", np.arange(2))
    assert not (tmp_path / "cache").exists()


def test_find_files_lists_the_matching_files_newest_first(tmp_path):
    from pipeline.io.basis_store import find_files, write_file

    for i, name in enumerate(["index-v6-aa.npz", "index-v6-bb.npz", "other.npz"]):
        path = write_file(tmp_path, f"state/{name}", b"x")
        os.utime(path, ns=(10**18 + i * 10**9, 10**18 + i * 10**9))
    assert [p.name for p in find_files(tmp_path, "state/index-v6-*.npz")] == ["index-v6-bb.npz", "index-v6-aa.npz"]
    assert find_files(tmp_path / "absent", "state/*.npz") == []
