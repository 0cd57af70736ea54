"""Spatial verification of the candidate search: does a suspect's descriptor matches to an asset fit one similarity?

``python bench/spatial_fit.py run PART PARTS`` (after ``python bench/rescan_compare.py issue``): every
asset of the leak benchmark described as the catalogue index describes it (:func:`features.describe`,
keypoints kept), searched exactly (faiss flat); each suspect described at the index's query scales,
its 8 nearest index rows taken, and for every asset among them the correspondences (each suspect
keypoint to its nearest row of that asset) fitted by RANSAC with scale
(:func:`registration.ransac_similarity`; inlier distance 1.5 of the asset's keypoint voxels, scale
within 1.6 of the ratio the voxels imply, each asset keypoint counted once).  The fit of an asset is
its most weighted inliers over the scales.  Results go to ``spatial_fit-PART.json`` in the
benchmark's folder; ``python bench/spatial_fit.py summary`` prints the leaks' own fits by attack
and the innocents' fits on other assets.
"""

from __future__ import annotations

import json
import os
import pickle
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
WORK = ROOT / "bench" / "results" / "leaks"
TWINS = {"bunny_res3_1889": ["bunny_res2_8171"], "bunny_res2_8171": ["bunny_res3_1889", "bunny_zipper_faceref_34834"],
         "shell-005": ["shell-001"], "shell-001": ["shell-005"]}


def _assets():
    import numpy as np
    import pyarrow.parquet as pq

    from pipeline import features
    from pipeline.io.pointcloud import read_points

    cache = WORK / "spatial_fit-assets.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    out = {}
    for r in pq.read_table(WORK / "catalog.parquet").to_pylist():
        path = Path(r["path"]) if Path(r["path"]).is_absolute() else WORK / r["path"]
        pts = read_points(path).points
        keys, feats = features.describe(pts)
        out[r["asset_key"]] = dict(keys=keys, feats=feats, spacing=features.median_spacing(features.dense_part(pts)),
                                   diag=float(np.linalg.norm(pts.max(0) - pts.min(0))))
    cache.write_bytes(pickle.dumps(out))
    return out


def run(part, parts):
    import faiss
    import numpy as np

    from pipeline import features
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import registration

    assets = _assets()
    names = sorted(assets)
    pos = np.vstack([assets[n]["keys"] for n in names])
    owner = np.concatenate([np.full(len(assets[n]["keys"]), i) for i, n in enumerate(names)])
    flat = faiss.IndexFlatIP(33)
    flat.add(np.vstack([assets[n]["feats"] for n in names]).astype(np.float32))
    truth = json.loads((WORK / "truth.json").read_text())
    out = {}
    for s in sorted(truth)[part::parts]:
        t0 = time.perf_counter()
        pts = read_points(WORK / "suspects" / f"{s}.ply").points
        spacing = features.median_spacing(features.dense_part(pts))
        fits = {}
        for factor in features.QUERY_SCALES:
            keys, feats = features.describe(pts, factor=factor)
            if len(keys) < 3:
                continue
            _, top = flat.search(np.ascontiguousarray(feats, dtype=np.float32), 8)
            owners = owner[top]
            for a in np.unique(owners):
                hit = owners == a
                q = np.flatnonzero(hit.any(axis=1))
                if len(q) < 3:
                    continue
                rows = top[q, hit[q].argmax(axis=1)]
                info = assets[names[a]]
                voxel_a, voxel_s = features.INDEX_VOXEL * info["spacing"], features.INDEX_VOXEL * factor * spacing
                e = voxel_a / voxel_s
                w = 1.0 / np.bincount(rows, minlength=len(pos))[rows]
                found, inl = registration.ransac_similarity(
                    keys[q], pos[rows], threshold=1.5 * voxel_a, iterations=2000, rng=0, scale_range=(e / 1.6, e * 1.6),
                    min_edge=2 * voxel_s, weights=w, local_radius=0.3 * info["diag"] / e)
                fit = float(w[inl].sum()) if found is not None else 0.0
                if fit > fits.get(names[a], (0.0,))[0]:
                    fits[names[a]] = (fit, int(len(q)), factor)
        out[s] = {"truth": truth[s], "fits": fits, "seconds": time.perf_counter() - t0}
        print(s, truth[s][:2], f"{out[s]['seconds']:.1f} s", flush=True)
    (WORK / f"spatial_fit-{part}.json").write_text(json.dumps(out))


def summary():
    import numpy as np

    out = {}
    for f in sorted(WORK.glob("spatial_fit-*.json")):
        out.update(json.loads(f.read_text()))
    by_attack, others = {}, []
    for s, o in out.items():
        kind, asset, _, attack = o["truth"]
        if kind == "leak":
            fit = max(o["fits"].get(a, [0.0])[0] for a in [asset] + TWINS.get(asset, []))
            by_attack.setdefault(attack, []).append(fit)
        else:
            others += [v[0] for k, v in o["fits"].items() if k != asset]
    for attack, v in sorted(by_attack.items()):
        print(f"{attack}: leaks {len(v)}, own fit min {min(v):.1f}, 10th pct {np.percentile(v, 10):.1f}, "
              f"median {np.median(v):.1f}")
    print("innocents' fits on other assets: median / 90th / 99th pct / max",
          np.round(np.percentile(others, [50, 90, 99, 100]), 1))
    print("seconds a suspect, median", round(float(np.median([o["seconds"] for o in out.values()])), 2))


if __name__ == "__main__":
    if sys.argv[1] == "run":
        run(int(sys.argv[2]), int(sys.argv[3]))
    else:
        summary()
