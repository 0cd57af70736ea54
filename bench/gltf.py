"""glTF leak benchmark (issue 40): GLB copies through the tools marketplaces re-pack them with.

``python bench/gltf.py [OUT]`` (about 10 minutes on 2 cores; needs node and
``make setup``'s npm tools).  A catalogue of two GLB assets, the textured
DamagedHelmet and the owl scan of ``../shared/data/models`` meshed by ball
pivoting (its own points as vertices), is issued to three recipients.  Each
copy is leaked through every file attack of :mod:`pipeline.io.gltf_tools`
(recipients in turn), the leaks are scanned with ``pointmark scan`` and
each verdict's score is set against the threshold.  Writes
``OUT/summary.md`` (default ``bench/results/gltf``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data"))

from pipeline import config  # noqa: E402
from pipeline.io import gltf_tools  # noqa: E402
from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue  # noqa: E402
from pipeline.io.gltf import glb_from_mesh  # noqa: E402
from pipeline.io.pointcloud import atomic_write_bytes, read_points  # noqa: E402
from pipeline.orchestrate.progress import Progress  # noqa: E402
from pipeline.orchestrate.run import plan_job, run_job  # noqa: E402
from pipeline.orchestrate.scan import read_scan  # noqa: E402

RECIPIENTS = ["alice", "bob", "carol"]
SECRET = "gltf-benchmark-secret-5150"
# leak name -> chain of (file attack, strength)
ATTACKS = {
    "optimize": [("gltf-optimize", None)],
    "draco14": [("gltf-draco", 14)],
    "draco11": [("gltf-draco", 11)],
    "draco8": [("gltf-draco", 8)],
    "quantize": [("gltf-quantize", None)],
    "meshopt": [("gltf-meshopt", None)],
    "weld": [("gltf-weld", None)],
    "reorder": [("gltf-reorder", None)],
    "simplify50": [("gltf-simplify", 0.5)],
    "simplify10": [("gltf-simplify", 0.1)],
    "draco11+simplify50": [("gltf-draco", 11), ("gltf-simplify", 0.5)],
    "ply": [("gltf-ply", None)],
    "obj": [("gltf-obj", None)],
}


def meshed_scan(path, target):
    """A points-only PLY scan as a GLB mesh: ball-pivoting triangles over its own points."""
    import open3d as o3d

    points = read_points(path).points
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals()
    spacing = float(np.mean(cloud.compute_nearest_neighbor_distance()))
    radii = o3d.utility.DoubleVector([1.5 * spacing, 3 * spacing, 6 * spacing])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    atomic_write_bytes(target, glb_from_mesh(points, np.asarray(mesh.triangles)))
    return target


def build(tmp, assets, watermark, *, serial=False, dask=None):
    """Catalogue ``assets`` {name: GLB path} in ``tmp``, issue copies; returns the scan config's path.

    ``serial`` embeds in this process, without a Dask cluster (a test's few copies); ``dask``
    overrides the config's dask section (a test's cluster of its own).
    """
    (tmp / "assets").mkdir(parents=True, exist_ok=True)
    for name, path in assets.items():
        target = tmp / "assets" / f"{name}.glb"
        if not target.exists():             # a copy: links out of the catalogue folder are not read
            atomic_write_bytes(target, Path(path).read_bytes())
    rows = [catalogue_record(a) for a in discover_assets(tmp / "assets", default_recipients=RECIPIENTS)]
    write_catalogue(rows, tmp / "catalog.parquet")
    cfg_dict = {
        "catalog": {"source": str(tmp / "catalog.parquet")}, "recipients": RECIPIENTS,
        "output": {"dir": str(tmp / "marked"), "manifests": str(tmp / "manifests")},
        "key": {"id": "gltf-key", "secret_file": str(tmp / "key")},
        "watermark": watermark,
        "scan": {"suspects": str(tmp / "suspects"), "catalogue": str(tmp / "catalog.parquet"),
                 "out": str(tmp / "scan"), "top_k": 2},
        "dask": {"n_workers": 2, "progress": "none", **(dask or {})},
    }
    (tmp / "key").write_text(SECRET)
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg_dict))
    cfg = config.load_config(tmp / "scan.yaml")
    job = plan_job(cfg, SECRET.encode())
    counts = run_job(job, cfg, serial=serial, progress=Progress())
    if counts["failed"]:
        raise RuntimeError(f"the catalogue run failed for {counts['failed']} copies")
    return tmp / "scan.yaml"


def leak(tmp, assets, attacks):
    """Each asset's copies through each attack chain, recipients in turn; {suspect stem: (asset, recipient)}."""
    truth = {}
    (tmp / "suspects").mkdir(exist_ok=True)
    for a, name in enumerate(assets):
        for k, (label, chain) in enumerate(attacks.items()):
            recipient = RECIPIENTS[(a + k) % len(RECIPIENTS)]
            source = tmp / "marked" / recipient / f"{name}.glb"
            stem = f"{name}-{label}-{recipient}"
            for step, (attack, strength) in enumerate(chain):
                target = tmp / "work" / f"{stem}-{step}{gltf_tools.attack_suffix(attack)}"
                target.parent.mkdir(exist_ok=True)
                source = gltf_tools.file_attack(source, target, attack, strength)
            os.replace(source, tmp / "suspects" / f"{stem}{source.suffix}")
            truth[stem] = (name, recipient)
    return truth


def scan(tmp, cfg_path, truth, *, in_process=False):
    """Run ``pointmark scan``; one row per leak: verdict, who is named, score and threshold.

    ``in_process`` calls the command line's ``main`` here (a test: its imports are already loaded).
    """
    if in_process:
        from pipeline.cli import main as pointmark

        pointmark(["scan", str(cfg_path)])
    else:
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        subprocess.run([sys.executable, "-m", "pipeline.cli", "scan", str(cfg_path)], cwd=tmp, env=env,
                       capture_output=True, text=True, timeout=3600, check=False)
    latest = {Path(r["suspect_path"]).stem: r for r in sorted(read_scan(tmp / "scan"),
                                                              key=lambda r: r["scanned_at"])}
    rows = []
    for stem, (asset, recipient) in truth.items():
        r = latest[stem]
        rows.append({"suspect": stem, "asset": asset, "recipient": recipient, "verdict": r["verdict"],
                     "named": r["recipient"], "score": r["score"], "threshold": r["threshold"],
                     "right": r["verdict"] == "match" and (r["candidate_asset"], r["recipient"]) == (asset, recipient)})
    return rows


def summary(rows):
    lines = ["| leak | recipient | verdict | named | score | threshold |", "|---|---|---|---|---|---|"]
    for r in rows:
        score = "-" if r["score"] is None else f"{r['score']:.1f}"
        threshold = "-" if r["threshold"] is None else f"{r['threshold']:.1f}"
        lines.append(f"| {r['suspect']} | {r['recipient']} | {r['verdict']} | {r['named']} | {score} | {threshold} |")
    lines.append(f"\n{sum(r['right'] for r in rows)}/{len(rows)} leaks attributed to the right recipient")
    return "\n".join(lines) + "\n"


def main(out):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    owl = out / "owl.glb"
    if not owl.exists():
        meshed_scan(DATA / "models" / "nikolov_owl_12442.ply", owl)
    assets = {"helmet": DATA / "gltf" / "DamagedHelmet.glb", "owl": owl}
    cfg_path = build(out / "run", assets, {"n_clusters": 3, "cluster_size": 2500})
    rows = scan(out / "run", cfg_path, leak(out / "run", assets, ATTACKS))
    text = summary(rows) + f"\n{time.perf_counter() - t0:.0f} s\n"
    (out / "summary.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else ROOT / "bench" / "results" / "gltf")
