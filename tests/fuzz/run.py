"""Run the reader fuzz targets for a fixed time each and print executions per target.

    python -m tests.fuzz.run [--seconds 600] [--target NAME ...] [--data DIR]

Used by ``make fuzz`` (FUZZ_SECONDS per target, 600 by default) and, for a few
seconds per target, by ``tests/fuzz/test_fuzz.py``.  Each target runs in this
process under an address-space limit (a huge allocation fails as a
MemoryError, which counts as a failure) and a per-input alarm (a hang
counts as a failure).  Failing inputs are saved under ``--failures``.
Exit status: 0 when no target failed, 1 otherwise, 2 when the real scans
are missing.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import signal
import sys
import tempfile
import time
import traceback
from collections import Counter
from pathlib import Path

from hypothesis import HealthCheck, Phase, given, settings

from tests.fuzz.targets import TARGETS

ROOT = Path(__file__).resolve().parents[2]
HEADROOM = 3 << 30        # address space allowed beyond what the interpreter holds at start
PER_INPUT_SECONDS = 20    # one input taking longer is a hang


class Hang(Exception):
    """An input took longer than PER_INPUT_SECONDS."""


def _alarm(signum, frame):
    raise Hang(f"no answer within {PER_INPUT_SECONDS} s")


def _limit_memory():
    with open("/proc/self/status") as f:
        size = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    limit = size + HEADROOM
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return limit


def _save(failures, name, example, fixed=False):
    data = example if isinstance(example, bytes) else example[1]
    suffix = ".yaml" if isinstance(example, bytes) else example[0]
    failures.mkdir(parents=True, exist_ok=True)
    path = failures / (f"{name}{suffix}" if fixed else f"{name}-{hashlib.sha256(data).hexdigest()[:12]}{suffix}")
    path.write_bytes(data)
    return path


def run_target(name, seconds, data_dir, failures, max_failures=5, keep_last=True, derandomize=False):
    """Fuzz one target for ``seconds``; returns (executions, outcome counts, failure lines).

    With ``derandomize`` the examples are the same on every run (the test
    suite's regression pass: one batch, reproducible); ``make fuzz`` explores.
    """
    target = TARGETS[name]
    strategy = target.strategy(data_dir)
    counts = Counter()
    found = []
    last = {}
    with tempfile.TemporaryDirectory(prefix=f"pointmark-fuzz-{name}-") as tmp:
        folder = Path(tmp)

        @settings(max_examples=200, deadline=None, database=None, derandomize=derandomize,
                  suppress_health_check=list(HealthCheck), phases=[Phase.generate, Phase.shrink],
                  print_blob=False, report_multiple_bugs=False)
        @given(strategy)
        def one(example):
            if keep_last:   # a crash that kills the process (a native abort) leaves its input here
                _save(failures, f"{name}-last", example, fixed=True)
            signal.alarm(PER_INPUT_SECONDS)
            try:
                outcome = target.check(example, folder)
            except BaseException:
                last["example"] = example
                raise
            finally:
                signal.alarm(0)
            counts[outcome] += 1

        end = time.monotonic() + seconds
        rounds = 0
        while time.monotonic() < end and len(found) < max_failures and not (derandomize and rounds):
            rounds += 1
            try:
                one()
            except Exception as exc:  # the property failed; hypothesis has shrunk the input
                counts["failure"] += 1
                saved = _save(failures, name, last["example"])
                where = traceback.extract_tb(exc.__traceback__)[-1]
                found.append(f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]} "
                             f"(at {Path(where.filename).name}:{where.lineno}; input saved as {saved})")
    return sum(counts.values()), counts, found


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=float(os.environ.get("FUZZ_SECONDS", 600)))
    parser.add_argument("--target", action="append", choices=sorted(TARGETS), help="default: all")
    parser.add_argument("--data", default=os.environ.get("POINTMARK_TEST_DATA", str(ROOT.parent / "shared" / "data")))
    parser.add_argument("--failures", default=str(Path(tempfile.gettempdir()) / "pointmark-fuzz-failures"))
    parser.add_argument("--derandomize", action="store_true",
                        help="the same examples every run, one batch (the test suite's pass)")
    args = parser.parse_args(argv)
    names = args.target or list(TARGETS)
    data_dir = Path(args.data)
    if not data_dir.is_dir() and any(not TARGETS[n].config for n in names):
        print(f"fuzz: the real scans that seed the targets are not at {data_dir} "
              f"(set POINTMARK_TEST_DATA or --data)", file=sys.stderr)
        return 2
    signal.signal(signal.SIGALRM, _alarm)
    limit = _limit_memory()
    print(f"fuzz: {len(names)} targets, {args.seconds:g} s each, address space limit "
          f"{limit / 2**30:.1f} GiB, seeds from {data_dir}", flush=True)
    failed = False
    for name in names:
        t0 = time.monotonic()
        runs, counts, found = run_target(name, args.seconds, data_dir, Path(args.failures),
                                         derandomize=args.derandomize)
        took = time.monotonic() - t0
        print(f"{name}: {runs} executions in {took:.0f} s ({runs / max(took, 1e-9):.0f}/s): "
              f"{counts['ok']} valid clouds or configs, {counts['error']} clean one-line errors, "
              f"{counts['failure']} failures", flush=True)
        for line in found:
            print(f"  FAILURE {line}", flush=True)
        failed |= bool(found)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
