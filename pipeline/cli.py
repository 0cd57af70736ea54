"""The ``pointmark`` command line.

Exit status: 0 success, 2 bad input (file, config, secret, payload); other
codes are documented per command.  Errors print one line naming the file and
the problem; nothing is written on error.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

from . import threads

threads.pin()   # before NumPy loads BLAS: one thread per process, as on the workers

import numpy as np  # noqa: E402

from . import __version__, allocator, config as config_mod
from .io.basis_store import BasisStore
from .io.gltf_tools import ToolError
from .io.ledger import Ledger, LedgerError
from .io.pointcloud import InputError, check_distinct, check_output, read_points, sha256_file, write_points
from .io.secrets import SecretError, check_key_id, load_secret
from .kernels import keys, modulation
from .orchestrate.reference import build_reference
from .watermark import (ReferenceMismatch, WatermarkError, band_for, detect_reference, distortion, embed_reference,
                        params_record)

log = logging.getLogger("pointmark")

USAGE_ERRORS = (InputError, SecretError, config_mod.ConfigError, ReferenceMismatch, LedgerError, ToolError)


def _common(p):
    p.add_argument("--config", help="YAML config (see configs/)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE",
                   help="override a config key by its name, e.g. --set beta=0.004")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def _positive(text):
    """An argparse type: an integer of at least 1."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of at least 1")
    return int(text)


def _key_args(p):
    p.add_argument("--key-id", required=True, help="id of the watermark key")
    p.add_argument("--secret-file", help="file holding the master secret (else $POINTMARK_SECRET)")


def build_parser():
    parser = argparse.ArgumentParser(prog="pointmark", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"pointmark {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("embed", help="watermark one point-cloud file")
    p.add_argument("original")
    p.add_argument("output")
    _key_args(p)
    p.add_argument("--message", required=True, help="payload as HEX, most significant bit first")
    _common(p)
    p.set_defaults(func=cmd_embed)

    p = sub.add_parser("detect", help="which issued copy a suspect is (--ledger), or decode a message "
                                      "(--original with --key-id)")
    p.add_argument("suspect")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--ledger", help="issuance ledger folder (output.manifests of the run): parameters, "
                                        "originals and recipients come from it, no config needed")
    where.add_argument("--original", help="the original file, to decode an arbitrary message (paper mode)")
    p.add_argument("--asset", help="with --ledger: check only this asset key")
    p.add_argument("--bases", help="basis store folder (with --ledger: default LEDGER/bases; with --original: "
                                   "none, the reference is rebuilt; given, it is kept there and checked)")
    p.add_argument("--top-k", type=_positive, help="with --ledger: candidates checked from each ranking of the "
                                          "scan's search, descriptor votes and shape views (default scan.top_k)")
    p.add_argument("--key-id", help="with --original: id of the watermark key")
    p.add_argument("--secret-file", help="file holding the master secret (else $POINTMARK_SECRET)")
    p.add_argument("--expect", help="with --original: issued payload as HEX: also report bit errors against it")
    _common(p)
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("run", help="watermark a catalogue (the main job); exit 1 if any asset failed")
    p.add_argument("config_file")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--secret-file", help="file holding the master secret (else key.secret_file or $POINTMARK_SECRET)")
    p.add_argument("--force", action="store_true",
                   help="also rewrite issued copies whose file is missing (the ledger is never rewritten)")
    p.add_argument("--dry-run", action="store_true", help="print the plan, write nothing")
    p.add_argument("--serial", action="store_true", help="plain loop in this process, no Dask")
    p.add_argument("--shard", help="I/N: only every N-th asset from the I-th (0-based)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("catalog", help="catalogue files")
    csub = p.add_subparsers(dest="catalog_command", required=True)
    b = csub.add_parser("build", help="record sha256, size, format, points, bbox and shape descriptor")
    b.add_argument("source", help="folder or glob of point-cloud files")
    b.add_argument("--out", required=True, help="catalogue Parquet file to write")
    b.add_argument("--recipients", default="", help="comma-separated recipients for every asset")
    b.set_defaults(func=cmd_catalog_build)

    p = sub.add_parser("ledger", help="the issuance ledger")
    lsub = p.add_subparsers(dest="ledger_command", required=True)
    s = lsub.add_parser("seal", help="MAC the rows written before rows carried one (once, after upgrading)")
    s.add_argument("ledger", help="the ledger folder (output.manifests)")
    s.add_argument("--secret-file", help="file holding the master secret (else $POINTMARK_SECRET)")
    s.set_defaults(func=cmd_ledger_seal)

    p = sub.add_parser("demo", help="generate the demo catalogue, watermark it, detect, summarise")
    p.add_argument("--dir", default="catalog/demo", help="where the demo catalogue is generated")
    p.add_argument("--config", default="configs/demo.yaml")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("attack", help="apply an attack or a chain of attacks to a file")
    p.add_argument("input")
    p.add_argument("output")
    p.add_argument("--attack", dest="attacks", action="append", required=True, metavar="NAME[:STRENGTH]",
                   help="e.g. similarity, noise:0.5%%, removal:0.139, crop:0.3, resample:5000, simplify:5000")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_attack)

    p = sub.add_parser("evaluate", help="robustness grid on Dask: Parquet results, plots, summary")
    p.add_argument("config_file")
    p.add_argument("--only", action="append", default=[], metavar="EXPERIMENT",
                   help="run only the experiments of this name (repeatable)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--secret-file")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("scan", help="which asset and recipient suspect files came from "
                                    "(exit 0 no match, 1 match, 2 bad config, 3 failures)")
    p.add_argument("config_file")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--secret-file")
    p.add_argument("--force", action="store_true", help="rescan suspects already scanned")
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser("schema", help="print the config JSON Schema")
    p.set_defaults(func=cmd_schema)

    p = sub.add_parser("validate", help="check a config file")
    p.add_argument("config_file")
    p.set_defaults(func=cmd_validate)
    return parser


def _secret(args, cfg, key_id=None, where="--key-id"):
    """The master secret; a key id that holds it (or a part of it) is refused here, before any work."""
    secret = load_secret(args.secret_file or cfg["key"]["secret_file"])
    if key_id is not None:
        check_key_id(key_id, secret, where)
    return secret


def _emit(args, result, lines):
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for line in lines:
            print(line)


def cmd_embed(args):
    check_output(args.original, args.output)
    cfg = config_mod.load_config(args.config, args.sets)
    params = config_mod.watermark_params(cfg)
    secret = _secret(args, cfg, args.key_id)
    try:
        bits = modulation.hex_to_bits(args.message, params.n_bits)
    except ValueError as exc:
        raise InputError(f"--message: {exc}") from None
    t0 = time.perf_counter()
    cloud = read_points(args.original, distinct=True)
    check_distinct(args.original, cloud.points)
    params = _asset_params(cfg, cloud)
    material = keys.derive_key_material(secret, args.key_id)
    try:
        ref = build_reference(cloud.points, params)
        marked = embed_reference(cloud.points, ref, material, bits, params)
    except WatermarkError as exc:
        raise InputError(f"{args.original}: {exc}") from None
    clusters = ref.records()
    stored = _publish(cloud, marked, Path(args.output))  # the coordinates rounded to the output's precision
    result = {
        "output": str(args.output),
        "original": str(args.original),
        "n_points": int(len(cloud.points)),
        "n_bits": params.n_bits,
        "message": modulation.bits_to_hex(bits),
        "key_id": args.key_id,
        "clusters": clusters,
        "reference": ref.digests(),
        "distortion": distortion(cloud.points, stored),
        "params": params_record(params),
        "marking_rule": config_mod.marking_rule(cfg, cloud.units()),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    d = result["distortion"]
    _emit(args, result, [
        f"wrote {args.output}: {result['n_points']} points, {len(clusters)} clusters, "
        f"{params.n_bits} bits",
        *([result["marking_rule"]] if result["marking_rule"] else []),
        f"distortion: RMSE {100 * d['rmse_rel_diag']:.4f} % of diag, "
        f"Hausdorff {100 * d['hausdorff_rel_diag']:.4f} %, "
        f"to the surface {100 * d['surface_rmse_rel_diag']:.4f} % (MRMS both ways "
        f"{100 * d['mrms_rel_diag']:.4f} %, surface Hausdorff {100 * d['surface_hausdorff_rel_diag']:.4f} %), "
        f"normal deviation {d['normal_deviation_deg']:.3f} deg, MSDM {d['msdm']:.3f}",
    ])
    return 0


def _asset_params(cfg, cloud):
    """The config's parameters for this file (auto resolved for survey data); exit 2 naming it when none fit."""
    try:
        return band_for(config_mod.watermark_params(cfg, cloud.units()), cloud.points)
    except ValueError as exc:
        raise InputError(f"{cloud.path}: {exc}") from None


def _publish(cloud, marked, out):
    """Write the copy under a pending name, check what it holds, then rename it to ``out``.

    A copy the file's precision leaves (nearly) unmarked is removed and
    refused, as in the catalogue run (:func:`~pipeline.orchestrate.tasks.realized_ratio`).

    Returns
    -------
    (n, 3) float
        The coordinates the written file holds.
    """
    from .orchestrate.tasks import realized_ratio

    pending = out.with_name(f".{out.stem}.pending{out.suffix}")
    write_points(cloud, marked, pending)
    try:
        stored = read_points(pending).points
        realized_ratio(cloud.points, marked, stored, out)
    except InputError as exc:
        pending.unlink(missing_ok=True)
        raise InputError(f"{exc} (the file just written cannot be read back; removed)") from None
    except WatermarkError as exc:
        pending.unlink(missing_ok=True)
        raise InputError(str(exc)) from None
    except BaseException:
        pending.unlink(missing_ok=True)
        raise
    os.replace(pending, out)
    return stored


def cmd_detect(args):
    allocator.keep_freed_memory()   # the registration's temporaries, allocated and freed thousands of times
    if args.ledger:
        return cmd_detect_ledger(args)
    if not args.key_id:
        raise config_mod.ConfigError("detect --original: --key-id is required")
    cfg = config_mod.load_config(args.config, args.sets)
    params = config_mod.watermark_params(cfg)
    secret = _secret(args, cfg, args.key_id)
    expect = None
    if args.expect:
        try:
            expect = modulation.hex_to_bits(args.expect, params.n_bits)
        except ValueError as exc:
            raise InputError(f"--expect: {exc}") from None
    t0 = time.perf_counter()
    suspect = read_points(args.suspect)
    original = read_points(args.original)
    params = _asset_params(cfg, original)
    material = keys.derive_key_material(secret, args.key_id)
    store = BasisStore(args.bases) if args.bases else None
    key = store.key(sha256_file(args.original), params) if store else None
    try:
        ref = build_reference(original.points, params, store, key)
        result = detect_reference(suspect.points, original.points, ref, material, params,
                                  config_mod.detect_params(cfg))
    except WatermarkError as exc:
        raise InputError(f"{args.original}: {exc}") from None
    result.update(suspect=str(args.suspect), original=str(args.original), key_id=args.key_id,
                  seconds=round(time.perf_counter() - t0, 3))
    if expect is not None:
        result["bit_errors"] = int((np.asarray(result["bits"]) != expect).sum())
    verdict = "WATERMARKED" if result["detected"] else "not watermarked"
    lines = [f"{args.suspect}: {verdict} (key {args.key_id}, p = {result['p_value']:.3g})"]
    if result["detected"]:
        lines.append(f"payload: {result['message']}")
    _emit(args, result, lines)
    return 0


def cmd_detect_ledger(args):
    from .orchestrate.detect import detect_from_ledger

    cfg = config_mod.load_config(args.config, args.sets)
    secret = _secret(args, cfg)
    result = detect_from_ledger(args.suspect, args.ledger, secret, config_mod.detect_params(cfg),
                                asset=args.asset, store=args.bases,
                                top_k=args.top_k or cfg["scan"]["top_k"], shape_margin=cfg["scan"]["shape_margin"],
                                gates=config_mod.cascade_gates(cfg))
    lines = [f"{args.suspect}: {result['verdict'].upper()} ({result['n_candidates_checked']} of "
             f"{len(result['candidates'])} candidate asset(s) checked, up to the first match; threshold "
             f"{result['threshold']:.2f} for {result['n_checked']} recipients)"]
    for a in result["accused"]:
        gens = ", ".join(f"generation {g}" for g, _ in a["copies"])
        lines.append(f"  accused: {a['recipient']} (asset {a['asset_key']}, key {a['key_id']}, {gens}): "
                     f"score {a['score']:.1f}, corrected p = {a['p_value']:.3g}, margin {a['margin']:.1f} "
                     f"over the best innocent")
    if not result["accused"] and result["best_score"] is not None:
        lines.append(f"  best score {result['best_score']:.2f} (p = {result['p_value']:.3g}): nobody accused")
    if result.get("n_unchecked"):
        lines.append(f"  unchecked: {result['unchecked']} (the secret given cannot open them)")
    _emit(args, result, lines)
    return 0


def cmd_attack(args):
    from .io.pointcloud import format_of, write_array
    from .kernels.attacks import chain_size
    from .surface import apply_chain, parse_attack

    # An attack writes bare coordinates, in the output's own format: a format
    # change (LAS to PLY, say) is itself an attack, so only the path is checked.
    check_output(args.input, args.output, same_format=False)
    try:
        chain = [parse_attack(a) for a in args.attacks]
    except ValueError as exc:
        raise InputError(f"--attack: {exc}") from None
    cloud = read_points(args.input)
    out = Path(args.output)
    if out.exists() and out.resolve() == cloud.path.resolve():
        raise InputError(f"{out}: refusing to overwrite the input")
    try:
        chain_size(chain, len(cloud.points))      # before anything is allocated for the result
    except ValueError as exc:
        raise InputError(f"--attack: {exc}") from None
    try:
        attacked = apply_chain(cloud.points, chain, rng=args.seed, faces=cloud.faces())
    except ValueError as exc:
        raise InputError(f"{args.input}: {exc}") from None
    write_array(out.parent, out.stem, attacked, format_of(out), keep_existing=False)
    print(f"wrote {out}: {len(attacked)} points ({len(cloud.points)} before)")
    return 0


def cmd_evaluate(args):
    from .orchestrate.evaluate import run_evaluation

    cfg = config_mod.load_config(args.config_file, args.sets)
    if args.only:
        names = {e["name"] for e in cfg["evaluate"]["experiments"]}
        unknown = sorted(set(args.only) - names)
        if unknown:
            raise config_mod.ConfigError(f"{args.config_file}: --only {unknown[0]}: no such experiment "
                                         f"(there are: {', '.join(sorted(names))})")
        cfg["evaluate"]["experiments"] = [e for e in cfg["evaluate"]["experiments"] if e["name"] in args.only]
    secret = _secret(args, cfg, cfg["key"]["id"], "key.id")
    return run_evaluation(cfg, secret)


def cmd_scan(args):
    from .orchestrate.scan import run_scan

    cfg = config_mod.load_config(args.config_file, args.sets)
    return run_scan(cfg, _secret(args, cfg), force=args.force)


def cmd_schema(args):
    sys.stdout.write(config_mod.schema_json())
    return 0


def cmd_validate(args):
    config_mod.load_config(args.config_file)
    print(f"{args.config_file}: valid")
    return 0


def _shard(text):
    if text is None:
        return None
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise config_mod.ConfigError(f"--shard {text!r}: expected I/N, e.g. 0/4") from None
    if not 0 <= i < n:
        raise config_mod.ConfigError(f"--shard {text!r}: need 0 <= I < N")
    return i, n


def cmd_run(args):
    from .orchestrate.run import plan_job, run_job

    cfg = config_mod.load_config(args.config_file, args.sets)
    secret = _secret(args, cfg, cfg["key"]["id"], "key.id")
    job = plan_job(cfg, secret, force=args.force, shard=_shard(args.shard), create=not args.dry_run)
    new = sum(len(a.items) for a in job.assets if not a.error)
    print(f"run {job.run_id}: {len(job.assets)} assets, {new} copies to issue, "
          f"{sum(a.issued for a in job.assets)} already issued; key {job.key_id} ({job.key_fingerprint}); "
          f"ledger {job.manifests}")
    for item in job.assets:
        for line in (item.rule, item.note) if item.items else ():
            if line:
                print(f"  {item.key}: {line}")
    if args.dry_run:
        for item in job.assets:
            if item.error:
                print(f"  {item.key}: {item.error}")
                continue
            names = ", ".join(r for r, _ in item.items) or "nothing new"
            missing = f"; {len(item.missing)} issued file(s) missing (--force rewrites them)" if item.missing else ""
            print(f"  {item.key}: generation {item.generation}, {item.issued} issued; to issue: {names}{missing}")
        return 0
    counts = run_job(job, cfg, serial=args.serial)
    print(f"done: {counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} with nothing new; "
          f"ledger in {job.manifests}")
    return 1 if counts["failed"] else 0


def cmd_catalog_build(args):
    from .io.catalog import catalogue_record, check_catalogue_out, check_recipient, discover_assets, \
        write_catalogue

    recipients = tuple(check_recipient(r, "--recipients") for r in args.recipients.split(",") if r)
    if len(set(recipients)) < len(recipients):
        raise InputError("--recipients: a recipient is named twice")
    check_catalogue_out(args.out)             # before any file is read
    assets = discover_assets(args.source, default_recipients=recipients)
    rows = [catalogue_record(a) for a in assets]
    write_catalogue(rows, args.out)
    failed = [r for r in rows if r["status"] != "ok"]
    print(f"wrote {args.out}: {len(rows)} assets, {len(failed)} unreadable")
    for r in failed:
        print(f"  failed: {r['error']}", file=sys.stderr)
    return 1 if failed else 0


def cmd_ledger_seal(args):
    """Seal a ledger's rows that predate row MACs; only the secret's holder can, and vouches for them."""
    ledger = Ledger(args.ledger)
    if not ledger.parts():
        raise InputError(f"{args.ledger}: no ledger part files here (is it output.manifests of a run?)")
    n = ledger.seal(load_secret(args.secret_file))
    print(f"{args.ledger}: sealed {n} row(s) that carried no MAC" if n else f"{args.ledger}: every row carries a MAC")
    return 0


def cmd_demo(args):
    from .demo import run_demo

    return run_demo(args.dir, args.config)


def main(argv=None):
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        return args.func(args)
    except USAGE_ERRORS as exc:
        print(f"pointmark: error: {_one_line(str(exc))}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a permission refused while writing
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"pointmark: error: {where}{_one_line(exc.strerror or str(exc))}", file=sys.stderr)
        return 2


def _one_line(text):
    """A message on one line (a YAML or library message may span several)."""
    return "; ".join(line.strip() for line in text.splitlines() if line.strip())


if __name__ == "__main__":
    sys.exit(main())
