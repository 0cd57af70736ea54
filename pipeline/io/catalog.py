"""Catalogues of assets: from a folder, a glob, or a catalogue file (Parquet or CSV).

A catalogue file has columns ``asset_key`` and ``path`` and optionally
``recipients`` (a list in Parquet, ``;``-separated in CSV).  Relative paths in
a catalogue file are relative to that file.
"""

from __future__ import annotations

import csv
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..kernels.descriptor import d2_descriptor
from .manifest import CATALOG_SCHEMA, write_rows
from .pointcloud import FORMATS, InputError, format_of, read_points, sha256_file

__all__ = ["Asset", "discover_assets", "catalogue_record", "write_catalogue", "read_catalogue",
           "check_recipient", "RECIPIENT_PATTERN", "glob_root", "list_suspects", "check_catalogue_out"]

LEAVES_FOLDER = "symlink leaves the catalogue folder (not read)"

# a recipient id is a folder name under output.dir: no separators, no "..", no leading dot
RECIPIENT_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._@+-]{0,127}$"


def check_recipient(name, where):
    """Raise InputError unless ``name`` is a safe recipient id (names ``where`` it came from)."""
    import re

    if not isinstance(name, str) or not re.fullmatch(RECIPIENT_PATTERN, name) or ".." in name:   # not "a\n"
        raise InputError(f"{where}: recipient {_short(name)} is not a valid id (letters, digits and . _ @ + -, "
                         f"starting with a letter or digit, no '..', at most 128 characters)")
    return name


def _short(value, limit=60):
    """``repr(value)``, cut to about ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 5]}...{text[-2:]}"


@dataclass(frozen=True)
class Asset:
    key: str
    path: Path
    recipients: tuple = field(default=())
    error: str | None = None       # why the file is refused unread (a link out of the folder)


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
    if "\0" in source_text:
        raise InputError(f"{source_text!r}: a path holds no NUL byte")
    if path.suffix.lower() in (".parquet", ".csv") and path.is_file():
        assets = _from_catalogue_file(path, tuple(default_recipients))
    elif path.is_dir():
        files = [p for p in path.rglob("*") if p.suffix.lower() in FORMATS and p.is_file()
                 and not p.name.startswith(".")]
        inside = os.path.realpath(path)
        assets = [Asset(p.relative_to(path).with_suffix("").as_posix(), p, tuple(default_recipients),
                        None if _within(p, inside) else f"{p}: {LEAVES_FOLDER}") for p in files]
    elif path.is_file() and path.suffix.lower() in FORMATS:
        assets = [Asset(path.stem, path, tuple(default_recipients))]     # one file: a catalogue of one
    elif any(ch in source_text for ch in "*?["):
        root, files = _glob(source_text)
        inside = os.path.realpath(root)
        assets = [Asset(p.stem, p, tuple(default_recipients), None if _within(p, inside) else f"{p}: {LEAVES_FOLDER}")
                  for p in files if p.suffix.lower() in FORMATS and not p.name.startswith(".")
                  and (p.is_file() or p.is_symlink())]
    elif not path.exists() and not path.is_symlink():
        raise InputError(f"{source_text}: no such catalogue file or folder")
    else:
        raise InputError(f"{source_text}: not a folder, a glob or a catalogue file (.parquet, .csv)")
    if not assets and any(ch in source_text for ch in "*?["):
        raise InputError(f"{source_text}: the glob matches no point-cloud file")
    keys = [a.key for a in assets]
    dupes = sorted({k for k in keys if keys.count(k) > 1})
    if dupes:
        raise InputError(f"{source_text}: asset keys are not unique: {dupes[:5]}")
    return sorted(assets, key=lambda a: a.key)


def glob_root(pattern):
    """The folder above a glob pattern's first wildcard (``.`` when it starts with one)."""
    parts = Path(pattern).parts
    magic = next((i for i, part in enumerate(parts) if any(ch in part for ch in "*?[")), len(parts))
    return Path(*parts[:magic]) if magic else Path(".")


def _glob(pattern):
    """(the folder above the first wildcard, the paths matched): pathlib's ``**`` follows no link to a
    folder (glob.glob's does, so a link loop or /proc/*/root never ends)."""
    root = glob_root(pattern)
    rest = Path(pattern).parts[len(root.parts):]
    if rest and rest[-1] == "**":            # pathlib's "**" alone names folders: every file below them
        rest = (*rest, "*")
    return root, (sorted(root.glob(str(Path(*rest)))) if root.is_dir() else [])


def _within(path, inside):
    """Whether ``path``, its links followed, lies in the folder ``inside`` (a real path)."""
    return os.path.commonpath([os.path.realpath(path), inside]) == inside


def _from_catalogue_file(path, default_recipients):
    rows = _parquet_rows(path) if path.suffix.lower() == ".parquet" else _csv_rows(path)
    assets = []
    for i, row in enumerate(rows):
        if not isinstance(row, dict) or not row.get("asset_key") or not row.get("path"):
            raise InputError(f"{path}: row {i} lacks asset_key or path")
        if not isinstance(row["path"], str) or "\0" in row["path"]:
            raise InputError(f"{path}: row {i}: path is not a text path")
        if not isinstance(row["asset_key"], (str, int)) or isinstance(row["asset_key"], bool):
            raise InputError(f"{path}: row {i}: asset_key is not text")
        names = row.get("recipients")
        if names is not None and (not isinstance(names, list) or not all(isinstance(r, str) for r in names)):
            # a string here would be read letter by letter: 'alice' as a, l, i, c, e
            raise InputError(f"{path}: row {i}: recipients is not a list of names "
                             f"(got {type(names).__name__}); in Parquet a list<string> column")
        for r in names or ():
            check_recipient(r, f"{path}: row {i}")
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


def _parquet_rows(path):
    """Rows of a Parquet catalogue; a file that is not one is refused with one line."""
    try:
        return pq.read_table(path).to_pylist()
    except (pa.ArrowException, OSError, ValueError) as exc:
        text = " ".join(str(exc).split())[:120]
        raise InputError(f"{path}: not a readable Parquet catalogue ({text})") from None


def _csv_rows(path):
    """Rows of a UTF-8 CSV catalogue, recipients split at ';'."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.DictReader(f))
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a UTF-8 CSV catalogue (byte {exc.start})") from None
    except csv.Error as exc:
        raise InputError(f"{path}: not a readable CSV catalogue ({' '.join(str(exc).split())[:120]})") from None
    for i, row in enumerate(rows):
        if None in row:
            raise InputError(f"{path}: row {i}: more fields than the header names")
        text = row.get("recipients") or ""
        row["recipients"] = [r for r in text.split(";") if r]
    return rows


def check_catalogue_out(out):
    """Refuse a catalogue output path before any asset is read (a folder, not .parquet, unwritable)."""
    out = Path(out)
    if out.is_dir():
        raise InputError(f"{out}: is a folder; give the catalogue file's name")
    if out.suffix.lower() != ".parquet":
        raise InputError(f"{out}: the catalogue is written as Parquet (.parquet)")
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{out}: the folder {parent} is not writable")
    return out


def catalogue_record(asset):
    """Catalogue row of one asset (a failed row, with the error, if unreadable or refused unread)."""
    row = {"asset_key": asset.key, "path": str(asset.path), "recipients": list(asset.recipients)}
    if asset.error:
        return {**row, "status": "failed", "error": asset.error}
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
    """Catalogue rows with descriptors as arrays.

    Raises
    ------
    InputError
        The file is missing or not a catalogue written by ``pointmark catalog build``.
    """
    if not Path(path).is_file():
        raise InputError(f"{path}: no such catalogue file (write one with pointmark catalog build)")
    try:
        rows = pq.read_table(path, schema=CATALOG_SCHEMA).to_pylist()
    except (OSError, pa.ArrowException, ValueError, TypeError) as exc:
        raise InputError(f"{path}: not a catalogue file written by pointmark catalog build "
                         f"({type(exc).__name__})") from None
    for row in rows:
        if row.get("descriptor") is not None:
            row["descriptor"] = np.asarray(row["descriptor"])
    return rows


def list_suspects(source):
    """Every suspect file a folder (recursively), a glob or one file names, and why any is refused.

    Suspects are told apart by path (and later by sha256), never by stem:
    ``x.xyz`` and ``x.obj`` are two suspects.  Nothing is opened or read
    here: a FIFO, a device, a socket, a folder a glob matched, an empty
    file, a broken link, a link to a folder, and a symbolic link whose
    target lies outside the suspects folder (a key file, ``/etc/passwd``)
    are returned with the reason they are refused.

    Parameters
    ----------
    source : str or Path
        A folder, a glob pattern or one point-cloud file.

    Returns
    -------
    suspects : list of (Path, str or None)
        Each point-cloud file (by suffix) and its refusal, None when it may
        be read; sorted by path.
    others : list of Path
        Files of other formats and hidden files (not suspects), so a caller
        can say so.
    """
    text = str(source)
    path = Path(text)
    if path.is_dir():
        root, found = path, []
        for folder, dirs, files in os.walk(path):    # links to folders are not followed; hidden ones are walked
            found += [Path(folder) / n for n in files + [d for d in dirs if os.path.islink(Path(folder) / d)]]
    elif any(ch in text for ch in "*?["):
        root, found = _glob(text)
    elif path.suffix.lower() in FORMATS and (path.exists() or path.is_symlink()):
        root, found = path.parent, [path]
    else:
        raise InputError(f"{text}: not a folder, a glob or a point-cloud file ({', '.join(sorted(FORMATS))})")
    # hidden files (a writer's temporary ".NAME.XXXX.tmp.ply") are no suspects yet: said, not scanned
    scanned = [p for p in found if p.suffix.lower() in FORMATS and not p.name.startswith(".")]
    suspects = sorted((p, _refusal(p, root)) for p in scanned)
    others = sorted(set(found) - set(scanned))
    return suspects, others


def _refusal(path, root):
    """Why ``path`` must not be read as a suspect (None: it may), from its metadata alone."""
    try:
        inside = os.path.realpath(root)
        if os.path.commonpath([os.path.realpath(path), inside]) != inside:
            return "a symbolic link that leads out of the suspects folder (not read)"
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a broken symbolic link" if os.path.islink(path) else "missing"
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    kinds = {stat.S_ISFIFO: "a FIFO", stat.S_ISCHR: "a character device", stat.S_ISBLK: "a block device",
             stat.S_ISSOCK: "a socket", stat.S_ISDIR: "a folder"}
    kind = next((name for test, name in kinds.items() if test(mode)), None)
    if kind is not None:
        return f"{kind}, not a regular file (not read)"
    if os.stat(path).st_size == 0:
        return "an empty file (0 bytes)"
    return None
