"""The leak benchmark's triage with the catalogue index searched exactly and through a faiss IVF.

``python bench/triage_ivf.py`` (after ``python bench/rescan_compare.py issue``): for every suspect of
``bench/results/leaks``, the candidates (:func:`candidates.candidates`, the default ``top_k`` and
``shape_margin``) and the cascade's stage of each (:func:`candidates.cascade`, the default gates), with
the index exact and with the same index through a faiss IVF (:meth:`FeatureIndex.with_ivf`, its
background votes recomputed).  Prints, per search: leaks whose asset is a candidate, that asset's
stage, the innocents' candidates by stage, and seconds of the descriptor search per suspect.
``TRIAGE_SEARCH=ivf`` takes the IVF search alone.  Each suspect's triage is kept in
``triage_ivf.json``; ``python bench/triage_ivf.py topk`` applies every ``top_k`` from 1 to 6 to the IVF's
triage and prints, per ``top_k``, where each leak's asset lands and the innocents' candidates by stage.
``TRIAGE_CODEC=SQ8`` (any faiss scalar quantizer) sets the IVF's codes and keeps ``triage_ivf-SQ8.json``;
``TRIAGE_KEYPOINTS=2000`` sets :data:`features.INDEX_KEYPOINTS` (assets' and suspects' descriptors) and keeps
``triage_ivf-k2000.json`` (``-SQ8-k2000`` with both); ``python bench/triage_ivf.py codecs SQfp16 k2000``
compares two such runs suspect by suspect.  ``python bench/triage_ivf.py scales`` keeps each suspect's votes at
every query scale apart (``triage_scales.json``); ``scales-summary`` then applies every set of scales.
``scales sparse`` and ``scales-summary sparse`` do the same for thinned crops of every asset, which the leak
benchmark lacks.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
WORK = ROOT / "bench" / "results" / "leaks"


def _info(index, points, twin_shape):
    t0 = time.perf_counter()
    voted = index.rank(points, top_k=len(index.keys))
    seconds = time.perf_counter() - t0
    shaped = dict(zip(index.keys, index.shape_distances(points)))
    order = sorted(index.keys, key=lambda k: shaped[k])
    twins = index.twins([k for k, _ in voted[:10]], twin_shape)
    return {"ranking": order, "distances": [float(shaped[k]) for k in order],
            "index_ranking": [k for k, _ in voted], "index_votes": [v for _, v in voted], "twins": twins}, seconds


def _tally(res):
    """Each leak's own asset by stage, the innocents' mean candidates by stage, and the leaks whose asset was not picked.

    ``res``: suspect name -> {"kind", "asset", "picked", "stage"}.
    """
    own, stages, lost = Counter(), Counter(), []
    innocents = [r for r in res.values() if r["kind"] != "leak"]
    for name, r in sorted(res.items()):
        if r["kind"] != "leak":
            stages.update(str(s) for s in r["stage"].values())
        elif r["asset"] in r["picked"]:
            own[r["stage"].get(r["asset"], "not a candidate")] += 1
        else:
            own["not a candidate"] += 1
            lost.append(name)
    return own, {s: n / len(innocents) for s, n in stages.items()}, lost


def main():
    import pyarrow.parquet as pq

    from pipeline import features
    from pipeline.config import cascade_gates, load_config
    from pipeline.io.pointcloud import read_points
    from pipeline.orchestrate.candidates import candidates, cascade

    features.IVF_CODEC = os.environ.get("TRIAGE_CODEC", features.IVF_CODEC)
    features.INDEX_KEYPOINTS = int(os.environ.get("TRIAGE_KEYPOINTS", features.INDEX_KEYPOINTS))
    cfg = load_config(None)
    gates = cascade_gates(cfg)
    top_k, margin = cfg["scan"]["top_k"], cfg["scan"]["shape_margin"]
    rows = pq.read_table(WORK / "catalog.parquet").to_pylist()
    base = WORK
    clouds = {r["asset_key"]: read_points(Path(r["path"]) if Path(r["path"]).is_absolute() else base / r["path"]).points
              for r in rows}
    exact = features.build_index(clouds, ivf=False)
    ivf = exact.with_ivf()
    ivf.prior = features.background_votes(ivf)
    print(f"{len(clouds)} assets, {exact.n_rows} rows, {ivf.ivf.nlist} cells", flush=True)
    truth = json.loads((WORK / "truth.json").read_text())
    out = {}
    searches = [s for s in (("exact", exact), ("ivf", ivf)) if os.environ.get("TRIAGE_SEARCH", s[0]) == s[0]]
    for n, name in enumerate(sorted(truth)):
        kind, asset = truth[name][0], truth[name][1]
        points = read_points(WORK / "suspects" / f"{name}.ply").points
        for label, index in searches:
            info, seconds = _info(index, points, gates[3])
            picked = candidates(info, set(index.keys), top_k, margin)
            stage = cascade(info, picked, *gates[:3])
            out.setdefault(label, {})[name] = {
                "kind": kind, "asset": asset, "picked": picked, "stage": stage, "seconds": seconds, "info": info,
                "shape_rank": info["ranking"].index(asset) if asset in info["ranking"] else None,
                "vote_rank": info["index_ranking"].index(asset) if asset in info["index_ranking"] else None}
        if n % 20 == 0:
            print(n, name, flush=True)
    (WORK / _kept()).write_text(json.dumps(out, default=float))
    for label, res in out.items():
        own, stages, _ = _tally(res)
        secs = sorted(r["seconds"] for r in res.values())
        print(f"{label}: leaks {sum(own.values())}, own asset's stage {dict(own)}; innocents, candidates by stage "
              f"{stages}; search s median {secs[len(secs) // 2]:.2f}, max {secs[-1]:.2f}")
    if len(out) < 2:
        return
    differ = [n for n in out["exact"] if out["exact"][n]["stage"] != out["ivf"][n]["stage"]]
    print("suspects whose candidates or stages differ:", len(differ))
    for n in differ:
        print(" ", n, truth[n], out["exact"][n]["stage"], out["ivf"][n]["stage"])


def _kept():
    """The triage's file: ``triage_ivf.json``, or ``triage_ivf-LABEL.json`` under ``TRIAGE_CODEC`` (the
    label) and ``TRIAGE_KEYPOINTS`` (the label's ``-k`` part)."""
    parts = [os.environ.get("TRIAGE_CODEC", "")]
    if "TRIAGE_KEYPOINTS" in os.environ:
        parts.append(f"k{os.environ['TRIAGE_KEYPOINTS']}")
    label = "-".join(p for p in parts if p)
    return f"triage_ivf-{label}.json" if label else "triage_ivf.json"


def topk():
    """Where each leak's asset lands, and what the innocents cost, at every ``top_k`` (the IVF's triage)."""
    from pipeline.config import cascade_gates, load_config
    from pipeline.orchestrate.candidates import candidates, cascade

    cfg = load_config(None)
    gates, margin = cascade_gates(cfg), cfg["scan"]["shape_margin"]
    res = json.loads((WORK / "triage_ivf.json").read_text())["ivf"]
    keys = set(a for r in res.values() for a in r["info"]["ranking"])
    print("| top_k | leaks: own asset deep / quick / not a candidate | innocents: candidates, of them deep |")
    print("|---:|---|---|")
    for k in range(1, 7):
        picked = {name: candidates(r["info"], keys, k, margin) for name, r in res.items()}
        own, stages, lost = _tally({name: dict(r, picked=picked[name], stage=cascade(r["info"], picked[name], *gates[:3]))
                                    for name, r in res.items()})
        print(f"| {k} | {own['deep']} / {own['quick']} / {own['not a candidate']} "
              f"| {sum(stages.values()):.2f}, {stages.get('deep', 0.0):.2f} |  {' '.join(lost)}")


def codecs(first, second):
    """Two kept triages (labels of ``TRIAGE_CODEC`` / ``TRIAGE_KEYPOINTS`` runs, ``default`` for
    ``triage_ivf.json``) side by side: every suspect's candidates and their stages,
    each leak's own asset's place in the vote ranking, and the search's seconds."""
    runs = [json.loads((WORK / (f"triage_ivf-{c}.json" if c != "default" else "triage_ivf.json")).read_text())["ivf"]
            for c in (first, second)]
    truth = json.loads((WORK / "truth.json").read_text())
    for codec, res in zip((first, second), runs):
        own, stages, lost = _tally(res)
        secs = np.sort([r["seconds"] for r in res.values()])
        print(f"{codec}: own asset's stage {dict(own)}, innocents' candidates by stage "
              f"{ {k: round(v, 2) for k, v in stages.items()} }, search s median {np.median(secs):.2f}, "
              f"95th pct {secs[int(0.95 * (len(secs) - 1))]:.2f}; not a candidate: {' '.join(lost)}")
    differ = [n for n in sorted(truth) if runs[0][n]["stage"] != runs[1][n]["stage"]]
    print(f"suspects whose candidates or stages differ: {len(differ)} of {len(truth)}")
    for n in differ:
        print(" ", n, truth[n][:2], runs[0][n]["stage"], runs[1][n]["stage"])
    moved = [(n, runs[0][n]["vote_rank"], runs[1][n]["vote_rank"]) for n in sorted(truth)
             if truth[n][0] == "leak" and runs[0][n]["vote_rank"] != runs[1][n]["vote_rank"]]
    print(f"leaks whose asset moved in the vote ranking: {len(moved)}", *(f"{n} {a}->{b}" for n, a, b in moved))


def scales(sparse=False):
    """Each suspect's votes at every query scale apart, and its seconds per scale (``triage_scales.json``):
    the IVF index as :func:`main` builds it, the current :data:`features.INDEX_KEYPOINTS`.  ``sparse``:
    the suspects are :func:`_sparse_crops` of the catalogue's assets instead (``triage_scales-sparse.json``)."""
    import pyarrow.parquet as pq

    from pipeline import features
    from pipeline.config import cascade_gates, load_config
    from pipeline.io.pointcloud import read_points

    twin_shape = cascade_gates(load_config(None))[3]
    rows = pq.read_table(WORK / "catalog.parquet").to_pylist()
    clouds = {r["asset_key"]: read_points(Path(r["path"]) if Path(r["path"]).is_absolute() else WORK / r["path"]).points
              for r in rows}
    index = features.build_index(clouds, ivf=False).with_ivf()
    index.prior = features.background_votes(index)
    prior = index.prior
    out = {"keys": index.keys, "twins": index.twins(index.keys, twin_shape), "suspects": {}}
    truth = json.loads((WORK / "truth.json").read_text())
    suspects = {name: WORK / "suspects" / f"{name}.ply" for name in truth}
    if sparse:
        suspects, truth = _sparse_crops(clouds)
    for n, name in enumerate(sorted(truth)):
        points = suspects[name] if sparse else read_points(suspects[name]).points
        per = []
        for factor in features.QUERY_SCALES:
            t0 = time.perf_counter()
            _, feats = features.describe(points, factor=factor)
            votes = index.votes(feats) / len(feats) - prior if len(feats) else np.full(len(index.keys), -np.inf)
            per.append({"factor": factor, "votes": votes.tolist(), "seconds": time.perf_counter() - t0})
        shaped = index.shape_distances(points)
        order = np.argsort(shaped, kind="stable")
        out["suspects"][name] = {"per_scale": per, "exact": list(index.exact(points)),
                                 "ranking": [index.keys[i] for i in order],
                                 "distances": [float(shaped[i]) for i in order]}
        if n % 20 == 0:
            print(n, name, flush=True)
    if sparse:
        out["truth"] = truth
    (WORK / ("triage_scales-sparse.json" if sparse else "triage_scales.json")).write_text(json.dumps(out, default=float))


SPARSE_CHAINS = {"keep 25 %, crop 0.5": [("removal", 0.25), ("crop", 0.5), ("random_similarity", None)],
                 "keep 10 %, crop 0.5": [("removal", 0.1), ("crop", 0.5), ("random_similarity", None)],
                 "keep 25 %, crop 0.3": [("removal", 0.25), ("crop", 0.3), ("random_similarity", None)]}


def _sparse_crops(clouds):
    """Sparse crops of every asset (:data:`SPARSE_CHAINS`, seeded by the asset's place): the case the
    leak benchmark lacks, a copy both thinned and cut.  Returns points and truth by name."""
    from pipeline import surface

    points, truth = {}, {}
    for i, (key, cloud) in enumerate(sorted(clouds.items())):
        for j, (label, chain) in enumerate(SPARSE_CHAINS.items()):
            name = f"sparse-{i:03d}-{j}"
            points[name] = surface.apply_chain(cloud, chain, rng=[38, i, j])
            truth[name] = ["leak", key, label]
    return points, truth


def scales_summary(sparse=False):
    """For every set of query scales: where each leak's asset lands, the innocents' candidates, and the
    share of the search's seconds the set costs (from ``triage_scales.json``)."""
    from itertools import combinations

    from pipeline.config import cascade_gates, load_config
    from pipeline.orchestrate.candidates import TWIN_LENDERS, candidates, cascade

    cfg = load_config(None)
    gates, top_k, margin = cascade_gates(cfg), cfg["scan"]["top_k"], cfg["scan"]["shape_margin"]
    data = json.loads((WORK / ("triage_scales-sparse.json" if sparse else "triage_scales.json")).read_text())
    truth = data["truth"] if sparse else json.loads((WORK / "truth.json").read_text())
    keys = data["keys"]
    n_scales = len(next(iter(data["suspects"].values()))["per_scale"])
    total = sum(s["seconds"] for r in data["suspects"].values() for s in r["per_scale"])
    print("| scales | leaks: own asset deep / quick / not a candidate | innocents: candidates, of them deep "
          "| share of the search's seconds | leaks whose asset's stage differs from all four |")
    print("|---|---|---|---:|---|")
    full = None
    for size in range(n_scales, 0, -1):
        for chosen in combinations(range(n_scales), size):
            res = {}
            for name, r in data["suspects"].items():
                votes = np.max([r["per_scale"][i]["votes"] for i in chosen], axis=0)
                votes[[keys.index(k) for k in r["exact"]]] = np.inf      # an exact geometry hash comes first
                order = np.argsort(-votes, kind="stable")
                voted = [keys[i] for i in order]
                info = {"ranking": r["ranking"], "distances": r["distances"], "index_ranking": voted,
                        "index_votes": [float(votes[i]) for i in order],
                        "twins": {k: data["twins"][k] for k in voted[:TWIN_LENDERS] if k in data["twins"]}}
                picked = candidates(info, set(keys), top_k, margin)
                res[name] = {"kind": truth[name][0], "asset": truth[name][1], "picked": picked,
                             "stage": cascade(info, picked, *gates[:3])}
            own, stages, lost = _tally(res)
            full = full or res
            def stage(r, asset):
                return r["stage"].get(asset, "not a candidate") if asset in r["picked"] else "not a candidate"

            moved = [n for n in res if truth[n][0] == "leak" and stage(res[n], truth[n][1]) != stage(full[n], truth[n][1])]
            share = sum(r["per_scale"][i]["seconds"] for r in data["suspects"].values() for i in chosen) / total
            first = next(iter(data["suspects"].values()))
            factors = ", ".join(f"{first['per_scale'][i]['factor']:.3g}" for i in chosen)
            print(f"| {factors} | {own['deep']} / {own['quick']} / {own['not a candidate']} "
                  f"| {sum(stages.values()):.2f}, {stages.get('deep', 0.0):.2f} | {share:.2f} | {' '.join(moved)} |")


if __name__ == "__main__":
    if sys.argv[1:2] == ["scales"]:
        scales(sparse=sys.argv[2:3] == ["sparse"])
    elif sys.argv[1:2] == ["scales-summary"]:
        scales_summary(sparse=sys.argv[2:3] == ["sparse"])
    elif sys.argv[1:2] == ["topk"]:
        topk()
    elif sys.argv[1:2] == ["codecs"]:
        codecs(*sys.argv[2:4])
    else:
        main()
