"""Read-only folders for tests: a store or ledger that a command cannot write."""

import contextlib
import os
import shutil
from pathlib import Path

import pytest

# root writes anywhere unless it lacks these capabilities: then a folder's mode refuses root too
_CAPS = "-dac_override,-dac_read_search"


def unprivileged():
    """argv prefix that runs a command unable to write a folder without write permission.

    As root, ``setpriv`` drops the capabilities that override file modes;
    as any other user, nothing is needed.
    """
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.fail("running as root, a read-only folder needs setpriv (util-linux) to drop root's override")
    return [setpriv, f"--bounding-set={_CAPS}", f"--inh-caps={_CAPS}"]


@contextlib.contextmanager
def frozen(folder):
    """Write permission taken off a folder tree, and given back after."""
    paths = [Path(folder), *Path(folder).rglob("*")]
    for path in paths:
        path.chmod(0o555 if path.is_dir() else 0o444)
    try:
        yield Path(folder)
    finally:
        for path in paths:
            path.chmod(0o755 if path.is_dir() else 0o644)


def tree_bytes(folder):
    """Every file of a tree and its bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}
