"""Read-only folders for tests: a store or ledger that a command cannot write."""

import contextlib
import os
import shutil
import subprocess
from pathlib import Path

import pytest

# root writes anywhere unless it lacks these capabilities: then a folder's mode refuses root too
_CAPS = "-dac_override,-dac_read_search"


def unprivileged():
    """argv prefix that runs a command unable to write a folder without write permission.

    As root, ``setpriv`` (util-linux) drops the capabilities that override
    file modes; as any other user, nothing is needed.
    """
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    prefix = [setpriv, f"--bounding-set={_CAPS}", f"--inh-caps={_CAPS}"]
    if setpriv is None or subprocess.run([*prefix, "true"], capture_output=True).returncode != 0:
        pytest.fail("running as root, a read-only folder needs setpriv (util-linux) and the capability to drop "
                    "root's file-mode override (CAP_SETPCAP)")
    return prefix


@contextlib.contextmanager
def frozen(*folders):
    """Write permission taken off folder trees, and their modes given back after."""
    modes = {p: p.stat().st_mode & 0o7777 for f in folders for p in [Path(f), *Path(f).rglob("*")]}
    for path in modes:
        path.chmod(0o555 if path.is_dir() else 0o444)
    try:
        yield
    finally:
        for path, mode in modes.items():
            path.chmod(mode)


def tree_bytes(folder):
    """Every file of a tree and its bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}
