"""pointmark benchmarks: ``make bench`` (or ``python bench/run.py [spectral] [catalog] [scan]``).

Every figure is a ratio of two timings taken side by side in this one run,
since shared machines are noisy; each timing is the best of a few repeats.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def best_of(func, repeat=3):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        func()
        times.append(time.perf_counter() - t0)
    return min(times)


def spectral_bench():
    """Spectral basis (sparse shift-invert Lanczos) against dense numpy.linalg.eigh."""
    from pipeline.demo import procedural_shape
    from pipeline.kernels import graph
    from pipeline.kernels.spectral import spectral_basis

    points = procedural_shape("blob", 4000, seed=1)
    radius = graph.valence_radius(points, 12)
    adjacency, _ = graph.connect_components(points, graph.radius_graph(points, radius))
    k = graph.laplacian(adjacency)
    dense = k.toarray()
    t_sparse = best_of(lambda: spectral_basis(k, 320))
    t_dense = best_of(lambda: np.linalg.eigh(dense), repeat=2)
    print("spectral basis, n = 4,000, 320 vectors (N_n = 12)")
    print(f"  pointmark spectral_basis : {t_sparse:8.2f} s")
    print(f"  numpy.linalg.eigh (dense): {t_dense:8.2f} s")
    print(f"  speed-up                 : {t_dense / t_sparse:8.1f} x")


BENCHES = {"spectral": spectral_bench}


def main(argv):
    names = argv or list(BENCHES)
    for name in names:
        BENCHES[name]()
        print()


if __name__ == "__main__":
    main(sys.argv[1:])
