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
