"""The basis store: clusters, spectral bases and normals of originals, by content.

An entry is keyed by the original's sha256 and the parameters that decide its
reference (never by its path), so the catalogue run, detection, scans and the
evaluation share one copy.  An entry is a folder of ``.npy`` files, each
written atomically: ``meta`` (frame and clusters, from the plan task) and one
file per cluster (basis, normals, radius, from the parallel cluster tasks).
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from .pointcloud import atomic_write_bytes

__all__ = ["BasisStore", "reference_params", "STORE_VERSION"]

STORE_VERSION = 1
_REFERENCE_FIELDS = ("n_bits", "crc_bits", "chip_rate", "first_coefficient", "valence", "n_clusters",
                     "cluster_size", "seeds", "on_touch", "cover", "displacement")


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

    def _path(self, key, name):
        return self.folder / key / f"{name}.npz"

    def _save(self, key, name, arrays):
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write_bytes(self._path(key, name), buf.getvalue())

    def _load(self, key, name):
        path = self._path(key, name)
        if not path.is_file():
            return None
        try:
            with np.load(path) as data:
                return {k: data[k] for k in data.files}
        except (OSError, ValueError):
            return None  # a damaged entry is rebuilt, and verified against the ledger

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
        return self._path(key, name).is_file()

    def save_array(self, key, name, array):
        """Any further array of an entry (detection aids: normals, spacing, grams)."""
        self._save(key, name, {"array": np.asarray(array)})

    def load_array(self, key, name):
        """The array saved as ``name``, or None."""
        data = self._load(key, name)
        return None if data is None else data["array"]
