"""Scratch files of an issue task: each recipient's displacements, appended cluster by cluster.

A large asset's bases do not fit in memory, nor do the marked copies of many
recipients: the issue task reads the bases once, appends each recipient's
displacements of each cluster to that recipient's scratch file, and then
builds one copy at a time from its file.  The folder lives beside the
outputs (same file system) and is removed when the task ends, whatever
happens.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["Scratch"]


class Scratch:
    """A temporary folder of append-only float64 row files, one per name.

    Parameters
    ----------
    near : str or Path
        A folder on the file system to use (created if missing).
    """

    def __init__(self, near):
        Path(near).mkdir(parents=True, exist_ok=True)
        self.folder = Path(tempfile.mkdtemp(prefix=".pointmark-scratch-", dir=near))
        self._files = {}

    def append(self, name, rows):
        """Append (m, 3) float rows to ``name``."""
        if name not in self._files:
            self._files[name] = open(self.folder / f"{name}.f64", "wb")
        self._files[name].write(np.ascontiguousarray(rows, dtype=np.float64).tobytes())

    def read(self, name):
        """All rows appended to ``name``, (m, 3) float64."""
        self._files.pop(name).close()
        return np.fromfile(self.folder / f"{name}.f64", dtype=np.float64).reshape(-1, 3)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for f in self._files.values():
            f.close()
        shutil.rmtree(self.folder, ignore_errors=True)
        return False
