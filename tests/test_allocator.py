"""The detection path's allocator: freed memory kept for the next array."""

import json
import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc",
                                reason="glibc's allocator only (elsewhere a no-op)")

# resident memory after a 64 MB array (beyond glibc's largest threshold for a block of its own
# mapping) is touched and freed, before and after keep_freed_memory; in a fresh process
PROBE = """
import json
import os
import numpy as np
from pipeline.allocator import keep_freed_memory, keeps_freed_memory, TRIM_THRESHOLD

def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

def after_free():
    a = np.ones(8 * 2**20)
    del a
    return resident()

assert not keeps_freed_memory()
base = after_free()
given_back = after_free() - base
kept = keep_freed_memory(), keep_freed_memory(), keeps_freed_memory()
held = after_free() - base
print(json.dumps([kept, given_back, held, TRIM_THRESHOLD]))
"""


def test_a_freed_array_stays_resident_for_the_next_one_once_kept():
    # glibc's own way in the child, whatever allocator settings this process's environment carries
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, env=env)
    kept, given_back, held, trim = json.loads(out.stdout)
    assert kept == [True, True, True]
    assert given_back < 8 * 2**20       # glibc's way: the 64 MB went back to the system
    assert 56 * 2**20 < held <= trim    # kept: under the trim threshold, it stays for the next array
