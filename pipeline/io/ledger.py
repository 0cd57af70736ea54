"""The issuance ledger: an append-only Parquet dataset, one row per issued copy.

Layout of a ledger folder::

    deployment.json          the deployment's public salt (created once)
    copies/part-*.parquet    rows, each file written once under a fresh name
    seals/seal-*.parquet     MACs of rows written before rows carried one (``pointmark ledger seal``)
    intents/*.json           copies a run is about to publish (removed once published)
    locks/                   one flock per asset, held by the run issuing it
    bases/                   the default basis store (see basis_store.py)

Nothing in ``copies/`` is ever rewritten or deleted: reruns, new recipients,
new parameters, keys and tool versions add part files.  Readers take the
union of all part files, ignoring temporary files.  Each row carries
``row_mac``, an HMAC under a key derived from the master secret
(:func:`pipeline.kernels.keys.ledger_mac_key`) over every other column, so a
row added or altered by anyone without the secret is recognised.

A copy is published only after its row is durable: the issue task writes it
under a pending name, the run appends the rows (written, flushed and synced),
then links each pending file to its final name.  Before issuing, the run
writes an intent file listing the copies it will publish; a run that finds
an intent of an asset it holds finishes it (publishes a pending copy whose
row records its sha256) or removes the pending copy (no row holds it).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import json
import os
import re
import stat
import sys
import uuid
from datetime import datetime, timezone
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

__all__ = ["LEDGER_SCHEMA", "LEDGER_VERSION", "MAC_FIELDS", "Ledger", "LedgerError", "mac_ok"]

LEDGER_VERSION = 3   # 3: row_mac

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
    ("row_mac", pa.string()),
])

_SEAL_SCHEMA = pa.schema([("ledger_part", pa.string()), ("row_index", pa.int64()), ("row_mac", pa.string())])

# the columns a row's MAC covers: all of them but the MAC
MAC_FIELDS = tuple(n for n in LEDGER_SCHEMA.names if n != "row_mac")
_HEX = {"key_salt": re.compile(r"[0-9a-f]{32}"), "source_sha256": re.compile(r"[0-9a-f]{64}"),
        "output_sha256": re.compile(r"[0-9a-f]{64}"), "key_fingerprint": re.compile(r"[0-9a-f]{16}")}


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
    def salt(self):
        """The deployment's public salt (hex); None if the ledger is new.

        Raises
        ------
        LedgerError
            ``deployment.json`` is missing while the ledger holds rows (it is
            never recreated silently: a new salt would start a new generation
            of every asset), or it is not a deployment file.
        """
        path = self.folder / "deployment.json"
        if path.is_file():
            try:
                salt = json.loads(path.read_text())["salt"]
            except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
                raise LedgerError(f"{path}: not a deployment file ({type(exc).__name__})") from None
            if not isinstance(salt, str) or not _HEX["key_salt"].fullmatch(salt):
                raise LedgerError(f"{path}: its salt is not 32 hex digits")
            return salt
        if self.parts():
            salts = sorted({r["key_salt"] for r in self.rows(status=None)})
            hint = (f"restore it with: echo '{{\"salt\": \"{salts[0]}\"}}' > {path}" if len(salts) == 1
                    else f"the rows hold {len(salts)} salts ({', '.join(salts)}): restore it from a backup")
            raise LedgerError(f"{path}: missing, though the ledger holds issued rows; {hint} "
                              f"(the salt is public and recorded in every row)")
        return None

    def create_salt(self, salt):
        """Record ``salt`` as the deployment's (once); returns the salt in force (another run's if it won)."""
        path = self.folder / "deployment.json"
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.folder / f".deployment.{uuid.uuid4().hex}.tmp"
        try:
            _write_durable(tmp, (json.dumps({"salt": salt, "created_at": _now().isoformat()}) + "\n").encode())
            try:  # a hard link is atomic and exclusive: two first runs agree on one salt, and no
                os.link(tmp, path)       # reader ever sees the file before its contents
            except FileExistsError:
                pass
        finally:
            tmp.unlink(missing_ok=True)
        _sync_folder(self.folder)
        return self.salt()

    # -- rows ---------------------------------------------------------------
    def parts(self):
        """Part files, sorted (temporary files of interrupted writers are ignored)."""
        if not self.copies.is_dir():
            return []
        return sorted(p for p in self.copies.glob("part-*.parquet") if not p.name.startswith("."))

    def version(self):
        """A short digest of which part files exist: changes whenever rows are added."""
        seals = self.folder / "seals"
        names = [p.name for p in self.parts()] + sorted(p.name for p in seals.glob("seal-*.parquet")
                                                        if seals.is_dir())
        return hashlib.sha256("\n".join(names).encode()).hexdigest()[:16]

    def rows(self, status="ok", asset_key=None):
        """Rows as dicts (each with ``ledger_part``, its file's name), optionally one status and asset.

        Raises
        ------
        LedgerError
            A part file that is not a ledger part (unreadable, another schema,
            or a row whose salt or hashes are not hex), named with the row.
        """
        sealed = self.seals()
        out = []
        for part in self.parts():
            for i, r in enumerate(_read_part(part)):
                if r["row_mac"] is None:                       # a row older than MACs: sealed since?
                    r["seal_macs"] = sealed.get((part.name, i), [])
                if (status is None or r["status"] == status) and (asset_key is None or r["asset_key"] == asset_key):
                    out.append({**r, "ledger_part": part.name, "ledger_row": i})
        return out

    # -- rows written before rows carried a MAC --------------------------------
    def seals(self):
        """{(part name, row index): [MAC, ...]} of rows sealed after they were written (any may verify)."""
        folder = self.folder / "seals"
        out = {}
        for path in sorted(folder.glob("seal-*.parquet")) if folder.is_dir() else []:
            try:
                rows = pq.read_table(path, schema=_SEAL_SCHEMA).to_pylist()
            except (OSError, pa.ArrowException, ValueError, TypeError):
                raise LedgerError(f"{path}: not a seal file: a foreign or damaged file in the ledger; "
                                  f"move it out to continue") from None
            for r in rows:
                out.setdefault((r["ledger_part"], r["row_index"]), []).append(r["row_mac"])
        return out

    def seal(self, secret):
        """MAC the rows under this secret's key that have none (ledgers older than MACs); how many.

        Only rows whose key fingerprint the secret gives are sealed, so a
        holder of another key never vouches for (nor blocks) rows not theirs.

        Whoever holds the secret vouches, by sealing, for the rows as they
        stand: run it once after upgrading, on a ledger you trust.
        """
        from ..kernels.keys import key_fingerprint, ledger_mac_key, row_mac

        mac_key = ledger_mac_key(secret)
        prints = {salt: key_fingerprint(secret, salt) for salt in {r["key_salt"] for r in self.rows(status=None)}}
        mine = [r for r in self.rows(status=None) if r["key_fingerprint"] == prints[r["key_salt"]]]
        if not mine:
            raise LedgerError(f"{self.folder}: the secret opens none of the ledger's rows: nothing it may seal")
        rows = [r for r in mine if r["row_mac"] is None and not mac_ok(mac_key, r)]
        if not rows:
            return 0
        table = pa.Table.from_pylist(
            [{"ledger_part": r["ledger_part"], "row_index": r["ledger_row"],
              "row_mac": row_mac(mac_key, r, MAC_FIELDS)} for r in rows], schema=_SEAL_SCHEMA)
        buf = io.BytesIO()
        pq.write_table(table, buf)
        folder = self.folder / "seals"
        folder.mkdir(parents=True, exist_ok=True)
        name = f"seal-{_now().strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:12]}.parquet"
        tmp = folder / f".{name}.tmp"
        try:
            _write_durable(tmp, buf.getvalue())
            os.link(tmp, folder / name)
        finally:
            tmp.unlink(missing_ok=True)
        _sync_folder(folder)
        return len(rows)

    def append(self, rows, mac_key=None):
        """Write rows as a new part file (never an existing name), durably; returns its path.

        Parameters
        ----------
        rows : list of dict
        mac_key : bytes, optional
            From :func:`pipeline.kernels.keys.ledger_mac_key`: each row gets its
            ``row_mac`` over :data:`MAC_FIELDS`, computed on the values as a
            reader gets them back.
        """
        if not rows:
            return None
        from ..kernels.keys import row_mac

        stamp = _now()
        filled = [{**{n: None for n in LEDGER_SCHEMA.names}, **{k: v for k, v in r.items() if k in LEDGER_SCHEMA.names},
                   "schema_version": LEDGER_VERSION, "created_at": r.get("created_at") or stamp, "row_mac": None}
                  for r in rows]
        table = pa.Table.from_pylist(filled, schema=LEDGER_SCHEMA)
        if mac_key is not None:
            macs = [row_mac(mac_key, r, MAC_FIELDS) for r in table.to_pylist()]
            table = table.set_column(LEDGER_SCHEMA.get_field_index("row_mac"), LEDGER_SCHEMA.field("row_mac"),
                                     pa.array(macs, pa.string()))
        buf = io.BytesIO()
        pq.write_table(table, buf)
        self.copies.mkdir(parents=True, exist_ok=True)
        name = f"part-{stamp.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:12]}.parquet"
        tmp = self.copies / f".{name}.tmp"
        final = self.copies / name
        try:
            _write_durable(tmp, buf.getvalue())
            os.link(tmp, final)          # fails rather than replace an existing part
        finally:
            tmp.unlink(missing_ok=True)
        _sync_folder(self.copies)
        return final

    # -- copies about to be published ----------------------------------------
    def write_intent(self, asset_key, run_id, paths):
        """Record, before issuing, the final paths of the copies a run will publish for an asset."""
        folder = self.folder / "intents"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{_asset_tag(asset_key)}.{run_id}.json"
        tmp = folder / f".{path.name}.tmp"
        try:
            _write_durable(tmp, json.dumps({"asset_key": asset_key, "paths": [str(p) for p in paths]}).encode())
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return path

    def intents(self, asset_key):
        """(intent file, final paths) of every unfinished intent of an asset."""
        folder = self.folder / "intents"
        out = []
        for path in sorted(folder.glob(f"{_asset_tag(asset_key)}.*.json")) if folder.is_dir() else []:
            try:
                record = json.loads(path.read_text())
            except (ValueError, UnicodeDecodeError):
                continue             # not written whole: its copies were never written either
            paths = record.get("paths") if isinstance(record, dict) else None
            if not isinstance(paths, list) or not all(isinstance(p, str) and os.path.isabs(p) for p in paths):
                raise LedgerError(f"{path}: not an intent file this tool wrote; move it out to continue")
            if record.get("asset_key") == asset_key:
                out.append((path, [Path(p) for p in paths]))
        return out

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
                stack.enter_context(_flock(folder / f"{_asset_tag(key)}.lock"))
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


def mac_ok(mac_key, row):
    """Whether a row (as :meth:`Ledger.rows` gives it) carries the MAC ``mac_key`` gives it."""
    import hmac

    from ..kernels.keys import row_mac

    macs = [row.get("row_mac")] + list(row.get("seal_macs") or [])
    want = row_mac(mac_key, row, MAC_FIELDS)
    return any(isinstance(mac, str) and hmac.compare_digest(mac, want) for mac in macs)


def _asset_tag(key):
    return hashlib.sha256(key.encode()).hexdigest()[:24]


def _read_part(part):
    """The rows of one part file, checked to be ledger rows."""
    if part.is_symlink() or not stat.S_ISREG(os.lstat(part).st_mode):
        raise LedgerError(f"{part}: a link or not a regular file: a ledger part is a file of its own "
                          f"(a foreign part?); move it out to continue")
    try:
        rows = pq.read_table(part, schema=LEDGER_SCHEMA).to_pylist()
    except (OSError, pa.ArrowException, ValueError, TypeError) as exc:
        raise LedgerError(f"{part}: not a ledger part ({type(exc).__name__}): "
                          f"a foreign or damaged file in the ledger; move it out to continue") from None
    for i, r in enumerate(rows):
        for name, pattern in _HEX.items():      # a failed row may lack its hashes
            value = r[name]
            if not (r["status"] != "ok" and not value) and not (isinstance(value, str) and pattern.fullmatch(value)):
                raise LedgerError(f"{part}: row {i}: {name} is not hex of the right length: a foreign or "
                                  f"altered part file; move it out to continue")
        if not all(isinstance(r[n], str) and r[n] for n in ("asset_key", "recipient", "key_id", "status")):
            raise LedgerError(f"{part}: row {i}: asset_key, recipient, key_id or status is empty: a foreign "
                              f"or altered part file; move it out to continue")
    return rows


def _write_durable(path, data):
    """Write bytes to a new file and sync them to disk."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def _sync_folder(folder):
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _now():
    return datetime.now(timezone.utc).replace(microsecond=0)
