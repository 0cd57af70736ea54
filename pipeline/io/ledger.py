"""The issuance ledger: an append-only Parquet dataset, one row per issued copy.

Layout of a ledger folder::

    deployment.json          the deployment's public salt (created once)
    copies/part-*.parquet    rows, each file written once under a fresh name
    locks/                   one flock per asset, held by the run issuing it
    bases/                   the default basis store (see basis_store.py)

Nothing here is ever rewritten or deleted: reruns, new recipients, new
parameters, keys and tool versions add part files.  Readers take the union
of all part files (``pyarrow.dataset``), ignoring temporary files.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import json
import os
import sys
import uuid
from datetime import datetime, timezone
from pathlib import Path

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

__all__ = ["LEDGER_SCHEMA", "LEDGER_VERSION", "Ledger", "LedgerError"]

LEDGER_VERSION = 2

LEDGER_SCHEMA = pa.schema([
    ("schema_version", pa.int16()),
    ("run_id", pa.string()),
    ("generation", pa.int32()),
    ("generation_id", pa.string()),
    ("asset_key", pa.string()),
    ("source_path", pa.string()),
    ("source_sha256", pa.string()),
    ("recipient", pa.string()),
    ("mark", pa.string()),
    ("key_id", pa.string()),
    ("key_fingerprint", pa.string()),
    ("key_salt", pa.string()),
    ("output_path", pa.string()),
    ("output_sha256", pa.string()),
    ("n_points", pa.int64()),
    ("params_json", pa.string()),
    ("n_bits", pa.int32()),
    ("chip_rate", pa.int32()),
    ("beta", pa.float64()),
    ("valence", pa.float64()),
    ("n_clusters", pa.int32()),
    ("cluster_size", pa.int32()),
    ("chip_layout", pa.string()),
    ("displacement", pa.string()),
    ("reference_key", pa.string()),
    ("fingerprint_length", pa.int64()),
    ("cluster_seeds", pa.list_(pa.int64())),
    ("cluster_sizes", pa.list_(pa.int64())),
    ("cluster_radii", pa.list_(pa.float64())),
    ("cluster_membership_digests", pa.list_(pa.string())),
    ("cluster_basis_digests", pa.list_(pa.string())),
    ("rmse_rel_diag", pa.float64()),
    ("hausdorff_rel_diag", pa.float64()),
    ("surface_rmse_rel_diag", pa.float64()),
    ("mrms_rel_diag", pa.float64()),
    ("surface_hausdorff_rel_diag", pa.float64()),
    ("normal_deviation_deg", pa.float64()),
    ("msdm", pa.float64()),
    ("realized_ratio", pa.float64()),
    ("seconds_copy", pa.float64()),
    ("status", pa.string()),
    ("error", pa.string()),
    ("tool_version", pa.string()),
    ("created_at", pa.timestamp("ms", tz="UTC")),
])


class LedgerError(RuntimeError):
    """The ledger folder cannot be used (unreadable, or not a ledger)."""


class Ledger:
    """An issuance ledger folder.

    Parameters
    ----------
    folder : str or Path
    """

    def __init__(self, folder):
        self.folder = Path(folder)
        self.copies = self.folder / "copies"

    # -- the deployment salt ------------------------------------------------
    def salt(self, create=False):
        """The deployment's public salt (hex), created once with ``create``; None if absent."""
        path = self.folder / "deployment.json"
        if path.is_file():
            try:
                return json.loads(path.read_text())["salt"]
            except (ValueError, KeyError) as exc:
                raise LedgerError(f"{path}: not a deployment file ({exc})") from None
        if not create:
            return None
        from ..kernels.keys import new_salt

        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.folder / f".deployment.{uuid.uuid4().hex}.tmp"
        tmp.write_text(json.dumps({"salt": new_salt(), "created_at": _now().isoformat()}) + "\n")
        try:  # a hard link is atomic and exclusive: two first runs agree on one salt, and no
            os.link(tmp, path)       # reader ever sees the file before its contents
        except FileExistsError:
            pass
        finally:
            tmp.unlink(missing_ok=True)
        return self.salt()

    # -- rows ---------------------------------------------------------------
    def parts(self):
        """Part files, sorted (temporary files of interrupted writers are ignored)."""
        if not self.copies.is_dir():
            return []
        return sorted(p for p in self.copies.glob("part-*.parquet") if not p.name.startswith("."))

    def version(self):
        """A short digest of which part files exist: changes whenever rows are added."""
        names = "\n".join(p.name for p in self.parts())
        return hashlib.sha256(names.encode()).hexdigest()[:16]

    def table(self):
        """Every row as one pyarrow Table (``LEDGER_SCHEMA``)."""
        parts = self.parts()
        if not parts:
            return LEDGER_SCHEMA.empty_table()
        try:
            return ds.dataset([str(p) for p in parts], schema=LEDGER_SCHEMA, format="parquet").to_table()
        except (OSError, pa.ArrowInvalid) as exc:
            raise LedgerError(f"{self.copies}: unreadable ledger part: {exc}") from None

    def rows(self, status="ok", asset_key=None):
        """Rows as dicts (each with ``ledger_part``, its file's name), optionally one status and asset."""
        out = []
        for part in self.parts():
            try:
                rows = pq.read_table(part, schema=LEDGER_SCHEMA).to_pylist()
            except (OSError, pa.ArrowInvalid) as exc:
                raise LedgerError(f"{part}: unreadable ledger part: {exc}") from None
            out += [{**r, "ledger_part": part.name} for r in rows
                    if (status is None or r["status"] == status) and (asset_key is None or r["asset_key"] == asset_key)]
        return out

    def append(self, rows):
        """Write rows as a new part file (never an existing name); returns its path."""
        if not rows:
            return None
        stamp = _now()
        filled = [{**{n: None for n in LEDGER_SCHEMA.names}, **r, "schema_version": LEDGER_VERSION,
                   "created_at": r.get("created_at") or stamp} for r in rows]
        buf = io.BytesIO()
        pq.write_table(pa.Table.from_pylist(filled, schema=LEDGER_SCHEMA), buf)
        self.copies.mkdir(parents=True, exist_ok=True)
        name = f"part-{stamp.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:12]}.parquet"
        tmp = self.copies / f".{name}.tmp"
        tmp.write_bytes(buf.getvalue())
        final = self.copies / name
        os.link(tmp, final)          # fails rather than replace an existing part
        tmp.unlink()
        return final

    # -- concurrency --------------------------------------------------------
    @contextlib.contextmanager
    def lock(self, asset_keys):
        """Hold the exclusive lock of every asset named (blocks while another run holds one).

        Locks are taken in sorted order, so two runs never deadlock; shards
        of one catalogue (disjoint assets) run side by side.
        """
        folder = self.folder / "locks"
        folder.mkdir(parents=True, exist_ok=True)
        with contextlib.ExitStack() as stack:
            for key in sorted(set(asset_keys)):
                name = hashlib.sha256(key.encode()).hexdigest()[:24]
                stack.enter_context(_flock(folder / f"{name}.lock"))
            yield self


@contextlib.contextmanager
def _flock(path):
    with open(path, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"[pointmark] waiting for another run holding {path}", file=sys.stderr, flush=True)
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _now():
    return datetime.now(timezone.utc).replace(microsecond=0)
