"""The demo catalogue: procedural, seeded shapes in several formats, and the demo run.

No real scans are copied into the project: shapes are generated (bumpy
blobs, tori, terrains, shells) with seeded, asymmetric bumps so that
registration has no symmetry to trip on.
"""

from __future__ import annotations

import numpy as np

__all__ = ["procedural_shape", "SHAPES", "write_demo_catalogue"]


def _bumps(directions, rng, n_terms=6, amplitude=0.12):
    """Smooth asymmetric radial modulation of unit directions, (n,) float."""
    out = np.zeros(len(directions))
    for _ in range(n_terms):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        freq = rng.uniform(1.0, 4.0)
        phase = rng.uniform(0, 2 * np.pi)
        out += rng.uniform(0.3, 1.0) * np.sin(freq * directions @ axis * np.pi + phase)
    return 1.0 + amplitude * out / n_terms * 2


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _blob(rng, n):
    d = _unit(rng, n)
    return d * _bumps(d, rng)[:, None] * rng.uniform(0.6, 1.4, 3)


def _torus(rng, n):
    u, v = rng.uniform(0, 2 * np.pi, (2, n))
    big, small = 1.0, rng.uniform(0.25, 0.4)
    ring = np.column_stack([np.cos(u), np.sin(u), np.zeros(n)])
    tube = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0, 0, 1.0])
    pts = big * ring + small * tube
    return pts * _bumps(pts / np.linalg.norm(pts, axis=1, keepdims=True), rng, amplitude=0.06)[:, None]


def _terrain(rng, n):
    xy = rng.uniform(-1, 1, (n, 2))
    z = np.zeros(n)
    for _ in range(5):
        k = rng.normal(size=2) * 3
        z += rng.uniform(0.03, 0.12) * np.sin(xy @ k + rng.uniform(0, 6.3))
    z += 0.2 * np.exp(-((xy - rng.uniform(-0.5, 0.5, 2)) ** 2).sum(axis=1) * 4)
    return np.column_stack([xy * [1.0, 0.7], z])


def _shell(rng, n):
    d = _unit(rng, n)
    d = d[d[:, 2] > -0.4][: n]
    while len(d) < n:
        more = _unit(rng, n)
        d = np.vstack([d, more[more[:, 2] > -0.4]])[:n]
    return d * _bumps(d, rng, amplitude=0.08)[:, None] * [1.2, 1.0, 0.7]


SHAPES = {"blob": _blob, "torus": _torus, "terrain": _terrain, "shell": _shell}


def procedural_shape(kind, n, *, seed=0):
    """A seeded procedural surface sample.

    Parameters
    ----------
    kind : {"blob", "torus", "terrain", "shell"}
    n : int
    seed : int

    Returns
    -------
    (n, 3) float
    """
    if kind not in SHAPES:
        raise ValueError(f"kind={kind!r} is not one of {sorted(SHAPES)}")
    return SHAPES[kind](np.random.default_rng(seed), n)


# asset name -> (shape, points, seed, format)
DEMO_ASSETS = {
    "blob-a": ("blob", 9000, 1, "ply"),
    "blob-b": ("blob", 12000, 2, "pcd"),
    "torus-a": ("torus", 10000, 3, "ply"),
    "terrain-a": ("terrain", 9000, 4, "las"),
    "shell-a": ("shell", 8000, 5, "xyz"),
    "blob-c": ("blob", 8000, 6, "ply-ascii"),
    "torus-b": ("torus", 9000, 7, "pts"),
    "terrain-b": ("terrain", 11000, 8, "ply"),
    "blob-d": ("blob", 9000, 9, "glb"),
}


def write_demo_catalogue(folder, *, assets=None, scale=100.0):
    """Write the demo assets into ``folder`` (skipping files already there).

    Returns
    -------
    list of pathlib.Path
    """
    from .io.pointcloud import write_array

    paths = []
    for name, (kind, n, seed, fmt) in (assets or DEMO_ASSETS).items():
        points = procedural_shape(kind, n, seed=seed) * scale
        write = _write_glb_mesh if fmt == "glb" else write_array
        paths.append(write(folder, name, points, fmt))
    return paths


def _write_glb_mesh(folder, name, points, fmt="glb"):
    """A blob as a GLB mesh: triangles of the hull of its directions (a blob is star-shaped)."""
    from pathlib import Path

    from scipy.spatial import ConvexHull

    from .io.gltf import glb_from_mesh
    from .io.pointcloud import atomic_write_bytes

    path = Path(folder) / f"{name}.{fmt}"
    if not path.exists():
        directions = points / np.linalg.norm(points, axis=1, keepdims=True)
        atomic_write_bytes(path, glb_from_mesh(points, ConvexHull(directions).simplices))
    return path


DEMO_SECRET_NOTE = (
    "# DEMO ONLY - this key is public, in the pointmark repository. Never watermark real assets with it.\n"
)


def run_demo(folder, config_path):
    """``make demo``: generate, catalogue, watermark on Dask, detect one copy, summarise."""
    from pathlib import Path

    from . import config as config_mod
    from .io.catalog import catalogue_record, discover_assets, write_catalogue
    from .io.pointcloud import atomic_write_bytes, read_points, write_array
    from .io.secrets import load_secret
    from .kernels import attacks
    from .orchestrate.detect import detect_from_ledger
    from .orchestrate.run import plan_job, run_job

    folder = Path(folder)
    assets_dir = folder / "assets"
    write_demo_catalogue(assets_dir)
    key_file = folder / "DEMO-ONLY.key"
    if not key_file.exists():
        atomic_write_bytes(key_file, b"pointmark-demo-secret-DO-NOT-USE-IN-PRODUCTION\n")
    cfg = config_mod.load_config(config_path)
    catalogue = folder / "catalog.parquet"
    rows = [catalogue_record(a) for a in discover_assets(assets_dir)]
    write_catalogue(rows, catalogue)
    print(f"demo catalogue: {len(rows)} procedural assets in {assets_dir} -> {catalogue}")
    print(f"demo key file: {key_file} (DEMO ONLY: a public key, never use it for real assets)")

    secret = load_secret(cfg["key"]["secret_file"])
    job = plan_job(cfg, secret)
    print(f"run {job.run_id}: {len(job.assets)} assets x {len(cfg['recipients'])} recipients, "
          f"{sum(len(a.items) for a in job.todo)} copies to issue on Dask")
    for item in job.todo:
        if item.rule:
            print(f"  {item.key}: {item.rule}")
    counts = run_job(job, cfg)
    print(f"done: {counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} skipped")

    rows = job.ledger.rows(status=None)
    ok = [r for r in rows if r["status"] == "ok"]
    print(f"ledger ({job.manifests}/copies, read with pyarrow.dataset): {len(rows)} rows, {len(ok)} issued copies")
    for row in ok:
        print(f"  {row['asset_key']:<10} {row['recipient']:<10} generation {row['generation']}  "
              f"{row['n_points']:>6} points  RMSE {100 * row['rmse_rel_diag']:.4f} %, to the surface "
              f"{100 * row['surface_rmse_rel_diag']:.4f} % of diag")

    pick = ok[1]
    leak = folder / "leaked" / f"{pick['recipient']}-{Path(pick['output_path']).stem}.ply"
    points = read_points(pick["output_path"]).points
    write_array(leak.parent, leak.stem, attacks.apply_chain(points, [("random_similarity", None), ("shuffle", None)], 7),
                "ply", keep_existing=False)
    result = detect_from_ledger(leak, job.manifests, secret, config_mod.detect_params(cfg),
                                top_k=cfg["scan"]["top_k"], shape_margin=cfg["scan"]["shape_margin"],
                                gates=config_mod.cascade_gates(cfg))
    named = ", ".join(f"{a['recipient']} (score {a['score']:.1f}, p = {a['p_value']:.2g})" for a in result["accused"])
    print(f"detect {leak} (rotated, rescaled, shuffled) --ledger {job.manifests}: {result['verdict']}: "
          f"{named or 'nobody'}; issued to {pick['recipient']}")
    right = [a["recipient"] for a in result["accused"]] == [pick["recipient"]]
    return 0 if counts["failed"] == 0 and right and _leak_scan(folder, cfg, secret, ok) else 1


# three leaks found in the wild: (asset, recipient, attack chain, what happened to it)
LEAKS = [("blob-b", "press-c", [("crop", 0.5), ("random_similarity", None)], "cropped to half, rotated and rescaled"),
         ("shell-a", "market-b", [("noise", 0.003)], "with noise of 0.3 % added"),
         ("blob-a", "studio-a", [("random_similarity", None), ("clutter", 3.0)],
          "rotated, rescaled and placed in a scene of three times its points"),
         ("blob-d", "market-b", [("random_similarity", None), ("quantize", 12)],
          "a GLB copy rotated, rescaled and quantised to 12 bits")]


def _leak_scan(folder, cfg, secret, issued):
    """Leak three issued copies, scan the folder, print the verdicts and where the evidence is."""
    from pathlib import Path

    from .io.pointcloud import read_points, write_array
    from .kernels import attacks
    from .orchestrate.scan import read_scan, run_scan

    suspects = folder / "suspects"
    truth = {}
    for n, (asset, recipient, chain, what) in enumerate(LEAKS):
        row = next(r for r in issued if (r["asset_key"], r["recipient"]) == (asset, recipient))
        name = f"found-{n + 1}"
        points = read_points(row["output_path"]).points
        write_array(suspects, name, attacks.apply_chain(points, chain + [("shuffle", None)], 100 + n), "ply",
                    keep_existing=False)
        truth[name] = (row["asset_key"], row["recipient"], what)
    scan_cfg = {**cfg, "scan": {**cfg["scan"], "suspects": str(suspects), "catalogue": cfg["catalog"]["source"],
                                "out": str(Path(cfg["output"]["manifests"]).parent / "scan")}}
    status = run_scan(scan_cfg, secret, force=True)
    latest = {}
    for r in sorted(read_scan(scan_cfg["scan"]["out"]), key=lambda r: r["scanned_at"]):
        latest[Path(r["suspect_path"]).stem] = r
    right, missed = 0, []
    for name, (asset, recipient, what) in truth.items():
        r = latest[name]
        ok = r["verdict"] == "match" and (r["candidate_asset"], r["recipient"]) == (asset, recipient)
        right += ok
        if not ok:
            missed.append(name)
        print(f"  {name}.ply ({recipient}'s copy of {asset}, {what}): {r['verdict']}"
              + (f", {r['recipient']} named, score {r['score']:.1f} over threshold {r['threshold']:.1f}, "
                 f"p = {r['p_value']:.2g}" if r["verdict"] == "match" else ""))
    framed = [n for n in truth if latest[n]["recipient"] not in (None, truth[n][1])]
    print(f"leak scan: {right}/{len(truth)} leaks attributed, {len(framed)} innocent recipients named; evidence report "
          f"{Path(scan_cfg['scan']['out']) / 'report.md'}")
    return status in (0, 1) and not missed
