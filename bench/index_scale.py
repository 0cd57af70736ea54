"""The catalogue index at scale (issue 38): build time, bytes, search time and recall of the faiss IVF.

``python bench/index_scale.py [ASSETS ...]`` (default 100 1000 10000) writes
``bench/results/index_scale.md``.

Catalogues are synthetic, :data:`features.INDEX_KEYPOINTS` (2,000) descriptors an asset (3,000 before
2026-12-06).  A pool of real FPFH
descriptor sets (the 14 shared scans and 24 procedural shapes, 4 kinds x 6
seeds, each described at the 4 query scales: 152 sets) stands in for
asset geometry; asset ``j`` resamples that many rows of pool set ``j mod 152``
and scales every bin by log-normal noise (sigma 0.15), after which its
three histograms are rescaled to equal sums (as FPFH's are) and each row to
unit norm.  Assets are seeded by their number, so a catalogue is built in
chunks of 100 and regenerated for the exact search.  A suspect is 4 x as many
rows of one asset's pool set under fresh noise (sigma 0.1), voted as
:meth:`FeatureIndex.votes` votes (8 neighbours).  Recall@1: the share of
1,000 of the suspects' rows whose nearest row through the IVF is the exact
nearest row (exact search over every regenerated chunk).

``INDEX_CODEC=SQ8 python bench/index_scale.py scale 1000 10000`` builds and measures only the IVF at
those sizes, with those faiss codes, into ``bench/results/index_scale-SQ8-2000.md`` (``INDEX_ROWS`` sets the
descriptors an asset, :data:`features.INDEX_KEYPOINTS` unless given).

Two more tables: the faiss codecs on the real scans (why fp16 codes), and
exact against IVF search per suspect around :data:`IVF_MIN` (the threshold).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data")) / "models"
OUT = ROOT / "bench" / "results"
CHUNK = 100          # assets generated and added at a time
SUSPECTS = 3
RECALL_QUERIES = 1000
PROBES = (16, 32)     # cells searched per query: the default (features.IVF_PROBE) and twice that

from pipeline import features  # noqa: E402

features.IVF_CODEC = os.environ.get("INDEX_CODEC", features.IVF_CODEC)
ROWS = int(os.environ.get("INDEX_ROWS", features.INDEX_KEYPOINTS))   # descriptors an asset ...
features.INDEX_KEYPOINTS = ROWS                                        # ... and a real suspect's description
POOL_KEYPOINTS = 3000   # rows kept of each pool set (the pool's cache was first built at the old cap)


def _pool():
    """Real FPFH descriptor sets: the shared scans and procedural shapes at every query scale (cached)."""
    cache = OUT / "index_scale_pool.npz"
    if cache.is_file():
        data = np.load(cache)
        return [data[k] for k in sorted(data.files, key=int)]
    from pipeline.demo import procedural_shape
    from pipeline.io.pointcloud import read_points

    clouds = [read_points(p).points for p in sorted(DATA.glob("*.ply"))]
    clouds += [procedural_shape(kind, 20000, seed=s) for kind in ("blob", "torus", "terrain", "shell")
               for s in range(6)]
    sets = [features.describe(c, factor=f, max_keypoints=POOL_KEYPOINTS)[1] for c in clouds
            for f in features.QUERY_SCALES]
    sets = [s for s in sets if len(s) >= 100]
    OUT.mkdir(parents=True, exist_ok=True)
    np.savez(cache, **{str(i): s for i, s in enumerate(sets)})
    return sets


def _fpfh_like(rows):
    """(n, 33) float32: rows with three equal histogram sums, unit norm (as FPFH rows are)."""
    blocks = rows.reshape(len(rows), 3, 11)
    blocks = blocks / np.maximum(blocks.sum(axis=2, keepdims=True), 1e-12)
    out = blocks.reshape(len(rows), 33)
    return (out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def _noisy(source, n, sigma, gen):
    rows = source[gen.integers(0, len(source), n)]
    return _fpfh_like(rows * np.exp(gen.normal(0.0, sigma, rows.shape)))


def _asset(pool, j):
    """(ROWS, 33) float32, the descriptors of synthetic asset ``j``."""
    return _noisy(pool[j % len(pool)], ROWS, 0.15, np.random.default_rng([38, j]))


def _chunks(pool, n_assets):
    for lo in range(0, n_assets, CHUNK):
        ids = range(lo, min(lo + CHUNK, n_assets))
        yield ids, [_asset(pool, j) for j in ids]


def _suspects(pool, n_assets):
    gen = np.random.default_rng([38, n_assets, 1])
    return [[_noisy(pool[j % len(pool)], ROWS, 0.1, gen) for _ in features.QUERY_SCALES]
            for j in gen.choice(n_assets, SUSPECTS, replace=False)]


def _exact_top1(pool, n_assets, queries):
    """Row and similarity of each query's exact nearest row, over every regenerated chunk."""
    best = np.full(len(queries), -np.inf, dtype=np.float32)
    row = np.zeros(len(queries), dtype=np.int64)
    for ids, sets in _chunks(pool, n_assets):
        top, sim = features.nearest_exact(queries, np.concatenate(sets), 1)
        better = sim[:, 0] > best
        best[better], row[better] = sim[better, 0], top[better, 0] + ids[0] * ROWS
    return row


def scale(pool, n_assets, keep_index=False):
    """Build, bytes, search and recall of the IVF index of ``n_assets`` synthetic assets (and the index
    itself under ``"index"`` with ``keep_index``)."""
    import faiss

    n_rows = n_assets * ROWS
    t0 = time.perf_counter()
    gen = np.random.default_rng([38, n_assets])
    cells = features.ivf_cells(n_rows)
    picked = gen.choice(n_assets, min(n_assets, -(-cells * features.IVF_SAMPLE // ROWS)), replace=False)
    ivf = features.train_ivf(np.concatenate([_asset(pool, j) for j in picked]), n_rows)
    index = features.FeatureIndex([], None, np.zeros(0, dtype=np.int32), [], ivf=ivf)
    trained = time.perf_counter() - t0
    for ids, sets in _chunks(pool, n_assets):
        index.add([f"a{j}" for j in ids], sets, ["h"] * len(ids))
    built = time.perf_counter() - t0
    size = faiss.serialize_index(ivf).nbytes + index.owner.nbytes
    suspects = _suspects(pool, n_assets)
    queries = np.concatenate([np.concatenate(s) for s in suspects])
    queries = queries[np.random.default_rng(0).choice(len(queries), RECALL_QUERIES, replace=False)]
    exact = _exact_top1(pool, n_assets, queries)
    out = {"assets": n_assets, "rows": n_rows, "cells": ivf.nlist, "train_s": trained, "build_s": built,
           "bytes": size}
    out["processes"] = _processes(index, suspects)
    for probe in PROBES:
        t0 = time.perf_counter()
        for suspect in suspects:
            for feats in suspect:
                index.votes(feats, probe=probe)
        search = (time.perf_counter() - t0) / len(suspects)
        found, _ = index.nearest(queries, 1, probe=probe)
        out[probe] = {"search_s": search, "recall": float((found[:, 0] == exact).mean()),
                      "asset_recall": float((found[:, 0] // ROWS == exact // ROWS).mean())}
    if keep_index:
        out["index"] = index
    return out


def _real_suspects():
    """A crop of the birdbath and the bunny among clutter of three times its points (real scans)."""
    from pipeline import surface
    from pipeline.io.pointcloud import read_points

    bunny = read_points(DATA / "bunny_zipper_faceref_34834.ply").points
    birdbath = read_points(DATA / "nikolov_birdbath_18793.ply").points
    return [surface.apply_chain(birdbath, [("crop", 0.5), ("random_similarity", None)], rng=1),
            surface.apply_chain(bunny, [("random_similarity", None), ("clutter", 3.0)], rng=1)]


def _real_search(index, n_assets):
    """Seconds of the whole candidate search of each real suspect (:func:`_real_suspects`): its descriptors
    at every query scale voted through ``index`` (:meth:`FeatureIndex.rank`), and its shape views against
    ``n_assets`` x :data:`SHAPE_VIEWS` seeded random views (:meth:`FeatureIndex.shape_distances`); best of 2."""
    index.shapes, index.shape_owner = _random_shapes(n_assets)
    index.prior = np.zeros(len(index.keys))
    suspects = _real_suspects()
    index.shape_distances(suspects[0])          # the cumulative histograms, computed once per index
    out = []
    for points in suspects:
        best = [np.inf, np.inf]
        for _ in range(2):
            t0 = time.perf_counter()
            index.rank(points, top_k=10)
            t1 = time.perf_counter()
            index.shape_distances(points)
            best = [min(best[0], t1 - t0), min(best[1], time.perf_counter() - t1)]
        out.append(best)
    index.shapes = index.shape_owner = None
    return out


def _processes(index, suspects):
    """Per way of loading the saved index (read whole, memory-mapped), in a fresh process: seconds to load,
    seconds per suspect, and the process's private (RssAnon) and file-backed (RssFile) resident MB after."""
    import subprocess
    import tempfile

    from pipeline.io.basis_store import write_file

    out = {}
    if index.prior is None:                        # (votes do not use it; the file holds one)
        index.prior = np.zeros(len(index.keys))
    with tempfile.TemporaryDirectory() as tmp:
        npz, ivf = index.to_parts()
        write_file(tmp, "index.ivf", ivf)
        path = write_file(tmp, "index.npz", npz)
        np.savez(Path(tmp) / "suspects.npz", *[f for suspect in suspects for f in suspect])
        for mode in ("whole", "mapped"):
            res = subprocess.run([sys.executable, __file__, "--child", mode, str(path), str(len(suspects))],
                                 capture_output=True, text=True, check=True)
            out[mode] = dict(zip(("load_s", "search_s", "anon_mb", "file_mb"), map(float, res.stdout.split())))
    return out


def _child(mode, path, n_suspects):
    """Load the index at ``path`` (``whole``: read; ``mapped``: as a scan does), vote every suspect beside it."""
    import io

    from pipeline.io.basis_store import read_file
    from pipeline.orchestrate import candidates

    t0 = time.perf_counter()
    if mode == "mapped":
        index = candidates.load_index(path)
    else:
        index = features.FeatureIndex.load(io.BytesIO(read_file(path)), lambda _: read_file(Path(path).with_suffix(".ivf")))
    loaded = time.perf_counter() - t0
    data = np.load(Path(path).parent / "suspects.npz")
    t0 = time.perf_counter()
    for k in data.files:
        index.votes(data[k])
    status = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":" in line)
    mb = [float(status.get(k, "0 kB").split()[0]) / 1024 for k in ("RssAnon", "RssFile")]
    print(loaded, (time.perf_counter() - t0) / int(n_suspects), *mb)


def codecs():
    """Exact-nearest-row recall and bytes a row of faiss codecs on the real scans (a kitten crop's rows)."""
    import faiss

    from pipeline import surface
    from pipeline.io.pointcloud import read_points

    rows = np.concatenate([features.describe(read_points(p).points)[1] for p in sorted(DATA.glob("*.ply"))])
    kitten = read_points(DATA / "kitten_12623.ply").points
    suspect = surface.apply_chain(kitten, [("crop", 0.5), ("random_similarity", None)], rng=5)
    queries = np.concatenate([features.describe(suspect, factor=f)[1] for f in features.QUERY_SCALES])
    exact, _ = features.nearest_exact(queries, rows, 1)
    cells = int(np.sqrt(len(rows)))
    out = []
    for codec, dims in (("SQ8", 33), ("PQ11", 33), ("SQfp16", 33), ("SQ8", 32), ("SQfp16", 32)):
        ivf = faiss.index_factory(dims, f"IVF{cells},{codec}", faiss.METRIC_INNER_PRODUCT)
        ivf.cp.seed, ivf.cp.spherical = 0, True
        x, q = (rows, queries) if dims == 33 else (features.fold_fpfh(rows), features.fold_queries(queries))
        ivf.train(x)
        ivf.add(x)
        t0 = time.perf_counter()
        _, top = ivf.search(q, 8, params=faiss.SearchParametersIVF(nprobe=features.IVF_PROBE))
        out.append({"codec": codec, "dims": dims, "recall": float((top[:, 0] == exact[:, 0]).mean()),
                    "code_bytes": ivf.code_size, "search_s_per_12000": (time.perf_counter() - t0)
                    / len(q) * 12000})
    return len(rows), len(queries), out


def threshold(pool):
    """Seconds per suspect (12,000 rows), exact and through the IVF, around IVF_MIN."""
    out = []
    queries = np.concatenate(_suspects(pool, 100)[0])
    for n_assets in (10, 33, 66):
        rows = np.concatenate([s for _, sets in _chunks(pool, n_assets) for s in sets])
        exact = features.FeatureIndex([f"a{j}" for j in range(n_assets)], rows,
                                      np.repeat(np.arange(n_assets, dtype=np.int32), ROWS), ["h"] * n_assets)
        ivf = exact.with_ivf()
        times = []
        for index, part in ((exact, queries[::10]), (ivf, queries)):
            t0 = time.perf_counter()
            index.votes(part)
            times.append((time.perf_counter() - t0) / len(part) * len(queries))
        out.append({"rows": len(rows), "exact_s": times[0], "ivf_s": times[1]})
    return out


SHAPE_VIEWS = 146     # D2 rows an asset holds: whole, 48 directions x 3 cut shares, its dense view


def _random_shapes(n_assets):
    """Seeded random D2 rows, :data:`SHAPE_VIEWS` an asset, and their owners (shape views' time does not
    depend on their values)."""
    gen = np.random.default_rng([38, n_assets, 2])
    shapes = gen.random((n_assets * SHAPE_VIEWS, 32))
    return shapes / shapes.sum(axis=1, keepdims=True), np.repeat(np.arange(n_assets, dtype=np.int32), SHAPE_VIEWS)


def shape_scale(n_assets):
    """Seconds per suspect of :meth:`FeatureIndex.shape_distances` over ``n_assets`` assets' shape views.

    The rows are seeded random histograms (the time does not depend on their values); the suspects are
    real: a crop of the birdbath and the bunny among clutter of three times its points (every view of
    :func:`features.suspect_views`).
    """
    shapes, owner = _random_shapes(n_assets)
    index = features.FeatureIndex([f"a{j}" for j in range(n_assets)], np.zeros((0, 33), dtype=np.float32),
                                  np.zeros(0, dtype=np.int32), ["h"] * n_assets, shapes=shapes, shape_owner=owner)
    suspects = _real_suspects()
    index.shape_distances(suspects[0])          # the cumulative histograms, computed once per index
    out = []
    for points in suspects:
        t0 = time.perf_counter()
        index.shape_distances(points)
        seconds = time.perf_counter() - t0
        out.append((len(features.suspect_views(points)), seconds))
    return out


def main(sizes):
    pool = _pool()
    lines = ["# Catalogue index at scale (bench/index_scale.py)", "",
             f"One thread, {time.strftime('%Y-%m-%d')}; faiss IVF (fp16 residual codes, 32 folded dims, "
             f"features.ivf_cells(N) cells found through an HNSW graph, {features.IVF_PROBE} probed unless said); {ROWS:,} descriptors an asset; synthetic "
             f"assets from {len(pool)} real FPFH sets.", ""]
    n_rows, n_queries, rows = codecs()
    lines += [f"## Codecs on the real scans ({n_rows:,} rows, {n_queries:,} queries of a kitten crop)", "",
              "| codec | dims | exact nearest row found | code bytes | s per 12,000 queries |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {r['codec']} | {r['dims']} | {r['recall']:.2%} | {r['code_bytes']} | {r['search_s_per_12000']:.2f} |"
              for r in rows]
    print("\n".join(lines), flush=True)
    lines += ["", "## Exact against IVF, seconds per suspect (12,000 descriptors)", "",
              "| rows | exact s | IVF s |", "|---:|---:|---:|"]
    print("\n".join(lines[-4:]), flush=True)
    for r in threshold(pool):
        lines.append(f"| {r['rows']:,} | {r['exact_s']:.1f} | {r['ivf_s']:.2f} |")
        print(lines[-1], flush=True)
    lines += ["", f"## Shape distances over {SHAPE_VIEWS} views an asset, seconds per suspect (views of the suspect)", "",
              "| assets | shape rows | birdbath crop | bunny among clutter |", "|---:|---:|---:|---:|"]
    for n in sizes:
        (v1, s1), (v2, s2) = shape_scale(n)
        lines.append(f"| {n:,} | {n * SHAPE_VIEWS:,} | {s1:.2f} ({v1}) | {s2:.2f} ({v2}) |")
        print(lines[-1], flush=True)
    lines += ["", "## IVF at scale (search, recall@1 and same asset@1 at 16 / 32 cells probed)", "",
              "| assets | rows | cells | train s | build s | index bytes | bytes a row | search s per suspect "
              "| recall@1 | same asset@1 |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    procs = ["", "## A fresh process loading the saved index, read whole or memory-mapped as a scan's worker does",
             "", "| assets | way | load s | search s per suspect | private MB | file-backed MB |",
             "|---:|---|---:|---:|---:|---:|"]
    for n in sizes:
        r = scale(pool, n)

        def both(key, fmt):
            return " / ".join(format(r[p][key], fmt) for p in PROBES)

        lines.append(f"| {r['assets']:,} | {r['rows']:,} | {r['cells']:,} | {r['train_s']:.1f} | {r['build_s']:.1f} "
                     f"| {r['bytes']:,} | {r['bytes'] / r['rows']:.1f} | {both('search_s', '.2f')} "
                     f"| {both('recall', '.2%')} | {both('asset_recall', '.2%')} |")
        print(lines[-1], flush=True)
        procs += [f"| {r['assets']:,} | {mode} | {m['load_s']:.1f} | {m['search_s']:.2f} | {m['anon_mb']:,.0f} "
                  f"| {m['file_mb']:,.0f} |" for mode, m in r["processes"].items()]
        print("\n".join(procs[-2:]), flush=True)
        (OUT / "index_scale.md").write_text("\n".join(lines + procs) + "\n")
    (OUT / "index_scale.md").write_text("\n".join(lines + procs) + "\n")


def scale_only(sizes):
    """The IVF-at-scale rows alone, with the whole candidate search of two real suspects
    (:func:`_real_search`), printed and kept in ``index_scale-CODEC-ROWS.md`` (``INDEX_CODEC``,
    ``INDEX_ROWS``)."""
    pool = _pool()
    lines = [f"IVF codes {features.IVF_CODEC}, {time.strftime('%Y-%m-%d')}, one thread; 16 / 32 cells probed", "",
             "| assets | rows | cells | build s | index bytes | bytes a row | search s per suspect | recall@1 "
             "| same asset@1 | mapped: load s, search s, private MB, file-backed MB "
             "| real suspects, votes + shape views s: birdbath crop; bunny among clutter |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for n in sizes:
        r = scale(pool, n, keep_index=True)
        r["real"] = _real_search(r.pop("index"), n)
        m = r["processes"]["mapped"]
        lines.append(f"| {n:,} | {r['rows']:,} | {r['cells']:,} | {r['build_s']:.1f} | {r['bytes']:,} "
                     f"| {r['bytes'] / r['rows']:.1f} | " + " | ".join(
                         " / ".join(format(r[p][key], fmt) for p in PROBES)
                         for key, fmt in (("search_s", ".2f"), ("recall", ".2%"), ("asset_recall", ".2%")))
                     + f" | {m['load_s']:.1f}, {m['search_s']:.2f}, {m['anon_mb']:,.0f}, {m['file_mb']:,.0f} | "
                     + "; ".join(f"{a:.2f} + {b:.2f}" for a, b in r["real"]) + " |")
        print(lines[-1], flush=True)
        (OUT / f"index_scale-{features.IVF_CODEC}-{ROWS}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        _child(*sys.argv[2:])
    elif sys.argv[1:2] == ["scale"]:
        scale_only([int(a) for a in sys.argv[2:]])
    else:
        main([int(a) for a in sys.argv[1:]] or [100, 1000, 10000])
