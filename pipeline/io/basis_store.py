"""The basis store: clusters, spectral bases and normals of originals, by content.

An entry is keyed by the original's sha256 and the parameters that decide its
reference (never by its path), so the catalogue run, detection, scans and the
evaluation share one copy.  An entry is a folder of ``.npy`` files, each
written atomically: ``meta`` (frame and clusters, from the plan task) and one
file per cluster (basis, normals, radius, from the parallel cluster tasks).
With ``output.keep_originals`` the plan task also keeps each original's
bytes as ``originals/SHA256.EXT``, so its copies stay checkable after the
catalogue's file is edited, moved or deleted.

A store that cannot be written (a read-only copy of a ledger kept as
evidence, a scan account without write access) is still read; what it lacks
is written to its stand-in (:func:`stand_in`), a per-user folder that every
process finds from the store's path, and the first such write in a process
says so on stderr.  A writable store never reads its stand-in.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from .pointcloud import atomic_write_bytes

__all__ = ["BasisStore", "reference_params", "stand_in", "find_file", "find_files", "read_file", "map_faiss",
           "write_file", "record_holding", "read_holdings", "STORE_VERSION"]

STORE_VERSION = 1
_REFERENCE_FIELDS = ("n_bits", "crc_bits", "chip_rate", "first_coefficient", "valence", "n_clusters",
                     "cluster_size", "seeds", "on_touch", "cover", "displacement")


_REFUSED = (errno.EROFS, errno.EACCES, errno.EPERM)   # errors that make a store read-only here
_REFUSALS = {}        # real path of a store -> why it cannot be written (None: it can), per process
_ANNOUNCED = set()    # stores whose stand-in this process has announced


def stand_in(folder):
    """The per-user folder that takes what a read-only store lacks.

    ``$POINTMARK_CACHE`` (default ``$XDG_CACHE_HOME/pointmark``, else
    ``~/.cache/pointmark``), then ``stores/`` and 16 hex digits of the
    store's real path.

    Raises
    ------
    RuntimeError
        Neither variable is set and the user has no home folder.
    """
    cache = os.environ.get("POINTMARK_CACHE") or (
        Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "pointmark")
    return Path(cache) / "stores" / hashlib.sha256(os.path.realpath(folder).encode()).hexdigest()[:16]


def _refusal(folder):
    """Why ``folder`` cannot be written (a probe file, once per process), or None when it can.

    Only a refusal (read-only file system, permission) counts; any other
    error is left to the write that meets it.
    """
    key = os.path.realpath(folder)
    if key not in _REFUSALS:
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(prefix=".probe-", dir=folder)
            os.close(fd)
            os.unlink(probe)
            _REFUSALS[key] = None
        except OSError as exc:
            _REFUSALS[key] = exc.strerror if exc.errno in _REFUSED else None
    return _REFUSALS[key]


def find_file(folder, relative):
    """The existing files at ``relative`` in ``folder`` and, when it cannot be written, in its stand-in.

    The store's own file comes first.  A writable store never reads its
    stand-in, so an old stand-in cannot shadow what the store rebuilds.

    Returns
    -------
    list of pathlib.Path
    """
    places = [Path(folder) / relative]
    if _refusal(folder) is not None:
        try:
            places.append(stand_in(folder) / relative)
        except RuntimeError:
            pass
    found = []
    for path in places:
        try:
            if path.is_file():
                found.append(path)
        except OSError:          # a stand-in this user cannot search: as if absent
            pass
    return found


def find_files(folder, relative_glob):
    """The existing files matching ``relative_glob`` in ``folder`` and, when it cannot be written, in its
    stand-in (as :func:`find_file`), newest first.

    Returns
    -------
    list of pathlib.Path
    """
    places = [Path(folder)]
    if _refusal(folder) is not None:
        try:
            places.append(stand_in(folder))
        except RuntimeError:
            pass
    found = []
    for place in places:
        try:
            found += [(path.stat().st_mtime_ns, path) for path in place.glob(relative_glob) if path.is_file()]
        except OSError:          # a stand-in this user cannot search: as if absent
            pass
    return [path for _, path in sorted(found, key=lambda x: (-x[0], str(x[1])))]


def read_file(path):
    """The bytes of a file :func:`find_file` found (an index, a kept state file)."""
    return Path(path).read_bytes()


def map_faiss(path):
    """A faiss IVF index file memory-mapped, read-only: its inverted lists stay on disk, shared by every
    process that maps them (faiss ``IO_FLAG_MMAP``); it cannot grow."""
    import faiss

    return faiss.read_index(str(path), faiss.IO_FLAG_MMAP | faiss.IO_FLAG_READ_ONLY)


def write_file(folder, relative, data):
    """Write bytes at ``relative`` in ``folder`` (atomically), or in its stand-in when it cannot be written.

    Returns
    -------
    pathlib.Path
        Where the bytes are.

    Raises
    ------
    OSError
        The store refuses and so does its stand-in (one message naming both).
    """
    reason = _refusal(folder)
    if reason is None:
        return atomic_write_bytes(Path(folder) / relative, data)
    try:
        spare = stand_in(folder)
        path = atomic_write_bytes(spare / relative, data)
    except (OSError, RuntimeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise OSError(errno.EACCES, f"{folder} cannot be written ({reason}), nor its stand-in ({why}): "
                                    f"set POINTMARK_CACHE to a writable folder") from None
    if os.path.realpath(folder) not in _ANNOUNCED:
        _ANNOUNCED.add(os.path.realpath(folder))
        print(f"[pointmark] {folder} cannot be written ({reason}): what it lacks goes to {spare}",
              file=sys.stderr, flush=True)
    return path


def _holding_folder(whole, other, settings):
    return f"holdings/{whole[:32]}/{other[:32]}-{settings[:16]}"


def record_holding(folder, whole, other, settings, witness, record):
    """Keep one witness of whether ``other``'s originals hold the surface of ``whole``'s.

    A record is a small JSON file per witness (a suspect laid whole on
    ``whole``'s original, then registered on ``other``'s), written once and
    never replaced: a second record from the same witness is not written.

    Parameters
    ----------
    folder : str or Path
        The basis store.
    whole, other : str
        The sha256 of the two originals' bytes.
    settings : str
        Hex digest of the registration's settings the witness was made with.
    witness : str
        The suspect's sha256.
    record : dict
        JSON-serialisable; ``held`` (bool) is what readers use.

    Returns
    -------
    pathlib.Path or None
        Where it was written; None when this witness was recorded before.
    """
    relative = f"{_holding_folder(whole, other, settings)}/{witness[:32]}.json"
    if find_file(folder, relative):
        return None
    return write_file(folder, relative, json.dumps(record, sort_keys=True).encode())


def read_holdings(folder, whole, other, settings):
    """Every witness recorded by :func:`record_holding` for the pair, as dicts.

    Returns
    -------
    list of dict, or None
        None when a record cannot be read or parsed: what it said is unknown.
    """
    records = []
    for path in find_files(folder, f"{_holding_folder(whole, other, settings)}/*.json"):
        try:
            records.append(json.loads(read_file(path)))
        except (OSError, ValueError):
            return None
    return records


def reference_params(params):
    """The parameters that decide a reference (not beta, not the layout)."""
    record = {k: getattr(params, k) for k in _REFERENCE_FIELDS}
    record["n_coefficients"] = params.n_coefficients
    if params.tile_points is not None:          # absent when unset: older entries keep their keys
        record["tile_points"] = params.tile_points
    return record


class BasisStore:
    """A folder of references.

    Parameters
    ----------
    folder : str or Path
    """

    def __init__(self, folder):
        self.folder = Path(folder)

    def key(self, source_sha256, params):
        """Entry name of one original under one parameter set (24 hex digits)."""
        text = json.dumps({"sha256": source_sha256, "store": STORE_VERSION, **reference_params(params)},
                          sort_keys=True, default=list)
        return hashlib.sha256(text.encode()).hexdigest()[:24]

    def _save(self, key, name, arrays):
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        write_file(self.folder, f"{key}/{name}.npz", buf.getvalue())

    def _load(self, key, name):
        for path in find_file(self.folder, f"{key}/{name}.npz"):
            try:
                with np.load(path) as data:
                    return {k: data[k] for k in data.files}
            except (OSError, ValueError, KeyError, zipfile.BadZipFile):
                continue  # a damaged entry is rebuilt, and verified against the ledger
        return None

    def save_meta(self, key, centre, phi, seeds, members):
        """Frame and clusters: centre (3,), phi, seed indices (k,), members list of (n_c,) int."""
        arrays = {"centre": np.asarray(centre, dtype=np.float64), "phi": np.array(float(phi)),
                  "seeds": np.asarray(seeds, dtype=np.int64)}
        arrays.update({f"members_{i}": np.asarray(m, dtype=np.int64) for i, m in enumerate(members)})
        self._save(key, "meta", arrays)

    def load_meta(self, key):
        """(centre (3,), phi, seeds (k,), members list) or None."""
        data = self._load(key, "meta")
        if data is None:
            return None
        members = [data[f"members_{i}"] for i in range(len(data["seeds"]))]
        return data["centre"], float(data["phi"]), data["seeds"], members

    def save_cluster(self, key, index, radius, basis, normals=None):
        """One cluster: radius, basis (n_c, K) and optional normals (n_c, 3)."""
        arrays = {"radius": np.array(float(radius)), "basis": np.asarray(basis, dtype=np.float64)}
        if normals is not None:
            arrays["normals"] = np.asarray(normals, dtype=np.float64)
        self._save(key, f"cluster-{index}", arrays)

    def load_cluster(self, key, index):
        """(radius, basis, normals or None) or None."""
        data = self._load(key, f"cluster-{index}")
        if data is None:
            return None
        return float(data["radius"]), data["basis"], data.get("normals")

    def has(self, key, name):
        """Whether the entry holds a file ``name`` (not whether it loads)."""
        return bool(find_file(self.folder, f"{key}/{name}.npz"))

    def keep_original(self, data, sha256, suffix):
        """Keep an original's bytes as ``originals/SHA256.SUFFIX`` (see :meth:`kept_original`); returns where."""
        return write_file(self.folder, f"originals/{sha256}{suffix}", data)

    def kept_original(self, sha256, suffix):
        """The kept copy of an original's bytes, or None."""
        found = find_file(self.folder, f"originals/{sha256}{suffix}")
        return found[0] if found else None

    def save_array(self, key, name, array):
        """Any further array of an entry (detection aids: normals, spacing, grams)."""
        self._save(key, name, {"array": np.asarray(array)})

    def load_array(self, key, name):
        """The array saved as ``name``, or None."""
        data = self._load(key, name)
        return None if data is None else data["array"]
