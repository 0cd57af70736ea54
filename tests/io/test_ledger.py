"""The ledger's deployment salt under concurrent first runs (workflow shards start together)."""

import threading

import pytest

from pipeline.io.ledger import Ledger
from pipeline.kernels.keys import new_salt


def test_concurrent_first_runs_agree_on_one_salt_and_never_read_a_partial_file(tmp_path):
    for round_ in range(40):
        folder = tmp_path / f"ledger-{round_}"
        start = threading.Barrier(8)
        salts, errors = [], []

        def first_run():
            start.wait()
            try:
                salts.append(Ledger(folder).create_salt(new_salt()))
            except Exception as exc:           # a reader that saw the file before its contents
                errors.append(exc)

        workers = [threading.Thread(target=first_run) for _ in range(8)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        assert not errors, errors[0]
        assert len(salts) == 8 and len(set(salts)) == 1
        assert [p.name for p in folder.iterdir()] == ["deployment.json"]    # no temporary file left


def test_rows_older_than_macs_are_sealed_once_and_then_verify(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.io.ledger import LEDGER_SCHEMA, MAC_FIELDS
    from pipeline.io.ledger import LedgerError, mac_ok
    from pipeline.kernels.keys import key_fingerprint, ledger_mac_key, row_mac

    ledger = Ledger(tmp_path)
    secret, other = b"a master secret of 24 bytes", b"another master secret, 31 bytes"
    old_schema = pa.schema([f for f in LEDGER_SCHEMA if f.name != "row_mac"])     # a version-2 part
    row = {n: None for n in old_schema.names}
    row.update(schema_version=2, asset_key="a", recipient="alice", key_id="k", status="ok", generation=1,
               key_salt="0" * 32, key_fingerprint=key_fingerprint(secret, "0" * 32), source_sha256="2" * 64,
               output_sha256="3" * 64)
    theirs = {**row, "recipient": "dave", "key_fingerprint": key_fingerprint(other, "0" * 32)}
    ledger.copies.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist([row, {**row, "recipient": "bob"}, theirs], schema=old_schema),
                   ledger.copies / "part-20260101T000000-old.parquet")
    assert [r["row_mac"] for r in ledger.rows()] == [None, None, None]
    with pytest.raises(LedgerError, match="opens none"):
        ledger.seal(b"a secret that opens no row here")
    key, their_key = ledger_mac_key(secret), ledger_mac_key(other)
    assert ledger.seal(secret) == 2 and ledger.seal(secret) == 0      # only the rows under its own key
    rows = {r["recipient"]: r for r in ledger.rows()}
    assert mac_ok(key, rows["alice"]) and mac_ok(key, rows["bob"]) and not mac_ok(key, rows["dave"])
    assert not mac_ok(their_key, rows["dave"])
    assert ledger.seal(other) == 1 and mac_ok(their_key, {r["recipient"]: r for r in ledger.rows()}["dave"])
    ledger.append([{**row, "recipient": "carol", "schema_version": None}], mac_key=key)
    carol = {r["recipient"]: r for r in ledger.rows()}["carol"]
    assert carol["row_mac"] == row_mac(key, carol, MAC_FIELDS)


def test_the_seal_command_needs_the_secret_and_a_ledger(tmp_path):
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT

    env = dict(os.environ, PYTHONPATH=str(ROOT), POINTMARK_SECRET="a master secret of 24 bytes")
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "ledger", "seal", str(tmp_path)], env=env,
                         capture_output=True, text=True)
    assert res.returncode == 2 and str(tmp_path) in res.stderr and "no ledger part" in res.stderr
    from pipeline.kernels.keys import key_fingerprint

    Ledger(tmp_path).append([{"asset_key": "a", "recipient": "r", "key_id": "k", "status": "ok",
                              "key_salt": "0" * 32, "source_sha256": "2" * 64, "output_sha256": "3" * 64,
                              "key_fingerprint": key_fingerprint(b"a master secret of 24 bytes", "0" * 32)}])
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "ledger", "seal", str(tmp_path)], env=env,
                         capture_output=True, text=True)
    assert res.returncode == 0 and "sealed 1 row" in res.stdout
    assert Ledger(tmp_path).rows()[0]["seal_macs"]
