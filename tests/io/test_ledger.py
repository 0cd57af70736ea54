"""The ledger's deployment salt under concurrent first runs (workflow shards start together)."""

import threading

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
    from pipeline.kernels.keys import ledger_mac_key, row_mac

    ledger = Ledger(tmp_path)
    old_schema = pa.schema([f for f in LEDGER_SCHEMA if f.name != "row_mac"])     # a version-2 part
    row = {n: None for n in old_schema.names}
    row.update(schema_version=2, asset_key="a", recipient="alice", key_id="k", status="ok", generation=1,
               key_salt="0" * 32, key_fingerprint="1" * 16, source_sha256="2" * 64, output_sha256="3" * 64)
    ledger.copies.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist([row, {**row, "recipient": "bob"}], schema=old_schema),
                   ledger.copies / "part-20260101T000000-old.parquet")
    assert [r["row_mac"] for r in ledger.rows()] == [None, None]
    key = ledger_mac_key(b"a master secret of 24 bytes")
    assert ledger.seal(key) == 2 and ledger.seal(key) == 0
    rows = ledger.rows()
    assert all(r["row_mac"] == row_mac(key, r, MAC_FIELDS) for r in rows)
    assert rows[0]["row_mac"] != rows[1]["row_mac"]
    ledger.append([{**row, "recipient": "carol", "schema_version": None}], mac_key=key)
    assert all(r["row_mac"] == row_mac(key, r, MAC_FIELDS) for r in ledger.rows())


def test_the_seal_command_needs_the_secret_and_a_ledger(tmp_path):
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT

    env = dict(os.environ, PYTHONPATH=str(ROOT), POINTMARK_SECRET="a master secret of 24 bytes")
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "ledger", "seal", str(tmp_path)], env=env,
                         capture_output=True, text=True)
    assert res.returncode == 2 and str(tmp_path) in res.stderr and "no ledger part" in res.stderr
    Ledger(tmp_path).append([{"asset_key": "a", "recipient": "r", "key_id": "k", "status": "ok",
                              "key_salt": "0" * 32, "key_fingerprint": "1" * 16, "source_sha256": "2" * 64,
                              "output_sha256": "3" * 64}])
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "ledger", "seal", str(tmp_path)], env=env,
                         capture_output=True, text=True)
    assert res.returncode == 0 and "sealed 1 row" in res.stdout
    assert Ledger(tmp_path).rows()[0]["row_mac"] is not None
