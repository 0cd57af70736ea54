"""Catalogues of assets: from a folder, a glob, or a catalogue file (Parquet or CSV).

A catalogue file has columns ``asset_key`` and ``path`` and optionally
``recipients`` (a list in Parquet, ``;``-separated in CSV).  Relative paths in
a catalogue file are relative to that file.
"""

from __future__ import annotations

import csv
import glob
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from ..kernels.descriptor import d2_descriptor
from .manifest import CATALOG_SCHEMA, write_rows
from .pointcloud import FORMATS, InputError, format_of, read_points, sha256_file

__all__ = ["Asset", "discover_assets", "catalogue_record", "write_catalogue", "read_catalogue",
           "check_recipient", "RECIPIENT_PATTERN"]

# a recipient id is a folder name under output.dir: no separators, no "..", no leading dot
RECIPIENT_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._@+-]{0,127}$"


def check_recipient(name, where):
    """Raise InputError unless ``name`` is a safe recipient id (names ``where`` it came from)."""
    import re

    if not isinstance(name, str) or not re.match(RECIPIENT_PATTERN, name) or ".." in name:
        raise InputError(f"{where}: recipient {name!r} is not a valid id (letters, digits and . _ @ + -, "
                         f"starting with a letter or digit, no '..', at most 128 characters)")
    return name


@dataclass(frozen=True)
class Asset:
    key: str
    path: Path
    recipients: tuple = field(default=())


def discover_assets(source, *, default_recipients=()):
    """Assets named by a folder, a glob pattern, a catalogue file or one point-cloud file.

    Parameters
    ----------
    source : str or Path
    default_recipients : sequence of str
        Recipients of assets that name none themselves.

    Returns
    -------
    list of Asset, sorted by key
    """
    source_text = str(source)
    path = Path(source_text)
    if path.suffix.lower() in (".parquet", ".csv") and path.is_file():
        assets = _from_catalogue_file(path, tuple(default_recipients))
    elif path.is_dir():
        files = [p for p in path.rglob("*") if p.suffix.lower() in FORMATS and p.is_file()
                 and not p.name.startswith(".")]
        assets = [Asset(p.relative_to(path).with_suffix("").as_posix(), p, tuple(default_recipients))
                  for p in files]
    elif path.is_file() and path.suffix.lower() in FORMATS:
        assets = [Asset(path.stem, path, tuple(default_recipients))]     # one file: a catalogue of one
    elif any(ch in source_text for ch in "*?["):
        files = [Path(p) for p in glob.glob(source_text, recursive=True)
                 if Path(p).suffix.lower() in FORMATS]
        assets = [Asset(p.stem, p, tuple(default_recipients)) for p in files]
    else:
        raise InputError(f"{source_text}: not a folder, a glob or a catalogue file (.parquet, .csv)")
    keys = [a.key for a in assets]
    dupes = sorted({k for k in keys if keys.count(k) > 1})
    if dupes:
        raise InputError(f"{source_text}: asset keys are not unique: {dupes[:5]}")
    return sorted(assets, key=lambda a: a.key)


def _from_catalogue_file(path, default_recipients):
    if path.suffix.lower() == ".parquet":
        rows = pq.read_table(path).to_pylist()
    else:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        for row in rows:
            text = row.get("recipients") or ""
            row["recipients"] = [r for r in text.split(";") if r]
    assets = []
    for i, row in enumerate(rows):
        if not row.get("asset_key") or not row.get("path"):
            raise InputError(f"{path}: row {i} lacks asset_key or path")
        key = str(row["asset_key"])
        if Path(key).is_absolute() or ".." in Path(key).parts or "\\" in key or not key.strip():
            raise InputError(f"{path}: row {i}: asset key {key!r} would leave the output folder (absolute, "
                             f"'..' or a backslash)")
        # a row the catalogue build could not read stays in: the run fails it as a row
        file = Path(row["path"])
        file = file if file.is_absolute() else path.parent / file
        recipients = tuple(row.get("recipients") or ()) or default_recipients
        assets.append(Asset(key, file, recipients))
    return assets


def catalogue_record(asset):
    """Catalogue row of one asset (a failed row, with the error, if unreadable)."""
    row = {"asset_key": asset.key, "path": str(asset.path), "recipients": list(asset.recipients)}
    try:
        cloud = read_points(asset.path)
    except InputError as exc:
        return {**row, "status": "failed", "error": str(exc)}
    pts = cloud.points
    centred = pts - pts.mean(axis=0)
    return {
        **row,
        "sha256": sha256_file(asset.path),
        "bytes": asset.path.stat().st_size,
        "format": format_of(asset.path),
        "n_points": int(len(pts)),
        "bbox_min": pts.min(axis=0).tolist(),
        "bbox_max": pts.max(axis=0).tolist(),
        "descriptor": d2_descriptor(centred).tolist(),
        "status": "ok",
        "error": None,
    }


def write_catalogue(rows, out):
    """Write catalogue rows to Parquet, atomically; paths become relative to the file."""
    out = Path(out)
    if out.suffix.lower() != ".parquet":
        raise InputError(f"{out}: the catalogue is written as Parquet (.parquet)")
    base = out.resolve().parent
    rows = [{**r, "path": os.path.relpath(Path(r["path"]).resolve(), base)} for r in rows]
    return write_rows(out, rows, CATALOG_SCHEMA)


def read_catalogue(path):
    """Catalogue rows with descriptors as arrays."""
    rows = pq.read_table(path).to_pylist()
    for row in rows:
        if row.get("descriptor") is not None:
            row["descriptor"] = np.asarray(row["descriptor"])
    return rows
