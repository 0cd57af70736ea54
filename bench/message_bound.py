"""The coded message after noise: the detector against an oracle that knows every point's match (issue 39, item 2).

``python bench/message_bound.py [NOISE ...]`` (default 1 %, one core).  ``BOUND_MODELS``
(comma-separated stems) and ``BOUND_SEEDS`` (a count) narrow the run; ``BOUND_SET``
(``NAME=VALUE`` overrides joined by ``;``, as ``--set`` takes them) changes the
configuration, e.g. ``watermark.chip_rate=3;watermark.beta=0.0021`` (the lowest
96 coefficients at the default's distance to the surface); each row records
the overrides and the copy's MRMS.
For every non-LiDAR scan of ``../shared/data/models`` with at least 10,000
points, the default configuration (normal displacement, beta 0.00115,
tail-biting code, clusters covering the asset at the paper's distance)
embeds the evaluation's message once; each seed (``SEEDS``) adds uniform noise of
``NOISE`` phi per coordinate (``ROBUSTNESS.md``) and reads the message twice:

- ``detector``: the copy shuffled and read as ``pointmark evaluate`` reads it
  (registration, then the least-squares fit of ``estimate_differences``);
- ``oracle``: every noisy point paired with the original point it came from,
  the same displacement model (original + n n^T E X) fitted to those pairs by
  least squares, the same decoder.

The oracle's errors bound what any estimate of the coefficient differences
can reach from this embedding at this distance: where it fails, the mark's
energy against the noise is the limit; where it decodes and the detector
does not, the correspondence step is.  Rows go to
``bench/results/message_bound/rows.jsonl`` (resumable); a table is printed.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data")) / "models"
WORK = ROOT / "bench" / "results" / "message_bound"
MODELS = ["bunny_zipper_faceref_34834", "bunny_rangescan_bun000_40256", "nikolov_birdbath_18793",
          "nikolov_blackvase_17337", "kitten_12623", "nikolov_owl_12442", "pcl_tum_rabbit_10429"]
SEEDS = 8
SECRET = b"message-bound-bench-secret-0001"


def oracle_deltas(moved, reference, normals, specs, bases, ridge):
    """Per cluster, the (K, 3) X of original + n n^T E X fitted to the known pairs by least squares.

    With the detector's ridge (``ridge`` times the mean diagonal of the normal
    equations): motion along the normals alone leaves some of X unobserved.

    Parameters
    ----------
    moved : (n, 3) float, the noisy copy in the original's order and frame
    reference, normals : (n, 3) float
    specs : cluster specs (``members``: (n_c,) int)
    bases : list of (n_c, K) float
    ridge : float

    Returns
    -------
    list of (K, 3) float
    """
    out = []
    for spec, e in zip(specs, bases):
        n = normals[spec.members]
        design = (e[:, :, None] * n[:, None, :]).reshape(len(e), -1)           # (n_c, 3K)
        misfit = np.einsum("ij,ij->i", moved[spec.members] - reference[spec.members], n)
        gram = design.T @ design
        gram[np.diag_indices_from(gram)] += ridge * float(np.mean(np.diag(gram)))
        x = np.linalg.solve(gram, design.T @ misfit)
        out.append(x.reshape(e.shape[1], 3))
    return out


def run(noises):
    from pipeline import config, surface
    from pipeline.kernels import keys
    from pipeline.io.pointcloud import read_points
    from pipeline.orchestrate import evaluate
    from pipeline.watermark import band_for, decode, distortion, embed_with_bases, estimate_differences

    WORK.mkdir(parents=True, exist_ok=True)
    rows_path = WORK / "rows.jsonl"
    done = {(r["model"], r["noise"], r["seed"], tuple(r.get("sets", ()))) for r in map(json.loads, rows_path.open())} \
        if rows_path.exists() else set()
    sets = [s for s in os.environ.get("BOUND_SET", "").split(";") if s]
    cfg = config.load_config(None, sets)
    base_params, dparams = config.watermark_params(cfg), config.detect_params(cfg)
    material = keys.derive_key_material(SECRET, "evaluation")
    bits = evaluate._message_bits(base_params)
    for model in os.environ.get("BOUND_MODELS", ",".join(MODELS)).split(","):
        path = DATA / f"{model}.ply"
        points = read_points(path).points
        params = band_for(base_params, points)          # the asset's band when band_noise is set
        handle = evaluate.prepare_bases(path, evaluate._basis_params(params, params.n_coefficients), WORK / "bases")
        ref = evaluate._stored_reference(handle, points, params)
        centred = points - ref.centre
        marked = embed_with_bases(centred, ref.specs, ref.bases, material, bits, params, ref.phi)
        mrms = distortion(centred, marked)["mrms_rel_diag"]
        for noise in noises:
            for seed in range(int(os.environ.get("BOUND_SEEDS", SEEDS))):
                if (model, noise, seed, tuple(sets)) in done:
                    continue
                noisy = surface.apply_chain(marked, [("noise", noise)], rng=seed)     # order kept
                shuffled = noisy[np.random.default_rng(seed).permutation(len(noisy))]
                estimate = estimate_differences(shuffled, centred, ref.specs, ref.bases, dparams, params,
                                                **ref.detection_aids())
                read = decode(estimate, ref.specs, material, params, dparams)
                oracle = {**estimate, "support": [len(s.members) for s in ref.specs],
                          "deltas": oracle_deltas(noisy, centred, ref.model_normals, ref.specs, ref.bases, dparams.ridge)}
                known = decode(oracle, ref.specs, material, params, dparams)
                row = {"model": model, "noise": noise, "seed": seed, "sets": sets, "mrms_rel_diag": mrms,
                       "chip_rate": params.chip_rate,
                       "clusters": len(ref.specs),
                       "detector_errors": int((np.asarray(read["bits"]) != bits).sum()),
                       "detector_min_score": float(np.min(np.abs(read["bit_scores"]))),
                       "oracle_errors": int((np.asarray(known["bits"]) != bits).sum()),
                       "oracle_min_score": float(np.min(np.abs(known["bit_scores"]))),
                       "fitness": read["registration"]["fitness"]}
                with rows_path.open("a") as f:
                    f.write(json.dumps(row) + "\n")
                print(row, flush=True)
    summary(rows_path)


def summary(rows_path):
    rows = [json.loads(line) for line in rows_path.open()]
    print("| model | overrides | noise | clusters | detector: 0 errors / seeds, median errors | oracle: 0 errors / seeds, "
          "median errors |\n|---|---|---|---:|---|---|")
    for key in sorted({(r["model"], ";".join(r.get("sets", ())), r["noise"]) for r in rows}):
        cell = [r for r in rows if (r["model"], ";".join(r.get("sets", ())), r["noise"]) == key]
        det = [r["detector_errors"] for r in cell]
        orc = [r["oracle_errors"] for r in cell]
        print(f"| {key[0]} | {key[1] or 'none'} | {key[2]:.2%} | {cell[0]['clusters']} | {sum(e == 0 for e in det)}/{len(det)}, "
              f"{np.median(det):g} | {sum(e == 0 for e in orc)}/{len(orc)}, {np.median(orc):g} |")


if __name__ == "__main__":
    run([float(a) for a in sys.argv[1:]] or [0.01])
