"""Checks that a job's outputs can never touch its inputs, made before anything is written.

A run writes marked copies (``output.dir``), the ledger (``output.manifests``)
and the basis store with its kept originals (``output.bases``); a scan writes
``scan.out``.  None of them may contain a catalogue asset, lie inside a
catalogue or suspects folder, or contain one: a marked copy would replace an
original, or the next run would take the copies as new assets.
"""

from __future__ import annotations

import os
from pathlib import Path

from .catalog import glob_root
from .pointcloud import InputError

__all__ = ["source_folders", "check_apart", "check_disjoint", "check_output_folder", "copy_path", "pending_path"]

# a file name of more than this many bytes, or a path of more than this many, is refused
NAME_MAX = 255
PATH_MAX = 4000


def _resolved(path):
    return Path(os.path.abspath(os.path.realpath(os.fspath(path))))


def source_folders(source):
    """The folders a catalogue (or suspects) source reads as a whole: the folder, or a glob's fixed part.

    A catalogue file or one file names its files, never a folder: an output
    beside them is not read back (:func:`check_apart` still refuses one that
    holds an asset).

    Parameters
    ----------
    source : str or Path
        A folder, a glob, a catalogue file or one file.

    Returns
    -------
    list of Path, resolved
    """
    text = str(source)
    path = Path(text)
    if path.is_dir():
        return [_resolved(path)]
    if any(ch in text for ch in "*?[") and not path.exists():
        return [_resolved(glob_root(text))]
    return []


def _inside(a, b):
    """True if ``a`` is ``b`` or lies below it (both resolved)."""
    return a == b or b in a.parents


def check_output_folder(key, folder):
    """Refuse an output folder that is a file, has an over-long name, or holds a NUL byte.

    Parameters
    ----------
    key : str
        The config key, for the message.
    folder : str or Path
    """
    text = os.fspath(folder)
    if "\0" in text:
        raise InputError(f"config: {key}: the path holds a NUL byte")
    raw = os.fsencode(text)
    if len(raw) > PATH_MAX or any(len(part) > NAME_MAX for part in raw.split(b"/")):
        raise InputError(f"config: {key}: the path is too long ({len(raw)} bytes; at most {NAME_MAX} a name, "
                         f"{PATH_MAX} in all)")
    path = Path(text)
    for above in [path, *path.parents]:
        if above.exists() or above.is_symlink():
            if not above.is_dir():
                raise InputError(f"config: {key}: {above} is a file, not a folder")
            break


def check_apart(outputs, inputs, asset_paths=()):
    """Refuse outputs that contain an asset, lie inside an input folder, or contain one.

    Parameters
    ----------
    outputs : list of (str, path)
        (config key, folder) of each output.
    inputs : list of (str, path)
        (what it is, folder) of each input folder.
    asset_paths : iterable of path
        Every asset of the catalogue.
    """
    for key, folder in outputs:
        check_output_folder(key, folder)
    resolved_out = [(key, _resolved(folder)) for key, folder in outputs]
    for key, out in resolved_out:
        for what, folder in inputs:
            src = _resolved(folder)
            if _inside(out, src):
                raise InputError(f"config: {key}: {out} lies inside the {what} {src}: its outputs would be "
                                 f"read as inputs; choose a folder outside it")
            if _inside(src, out):
                raise InputError(f"config: {key}: {out} contains the {what} {src}; choose a folder outside it")
        for asset in asset_paths:
            if _inside(_resolved(asset), out):
                raise InputError(f"config: {key}: {out} contains the catalogue asset {asset}; an output "
                                 f"could replace an original: choose a folder outside the catalogue")


def check_disjoint(first, others):
    """Refuse an output folder that is, holds or lies inside another output of the job.

    Parameters
    ----------
    first : (str, path)
        (config key, folder): issued copies, or a scan's results.
    others : list of (str, path)
        The job's other outputs (the ledger, the basis store, ...).
    """
    key, folder = first
    mine = _resolved(folder)
    for other_key, other in others:
        theirs = _resolved(other)
        if _inside(mine, theirs) or _inside(theirs, mine):
            raise InputError(f"config: {key}: {mine} overlaps {other_key} ({theirs}); keep each output in a "
                             f"folder of its own")


def copy_path(out_dir, recipient, asset_key, generation, suffix):
    """Where a recipient's copy of one generation of an asset goes; distinct for distinct inputs.

    Generation 1 is ``KEY.EXT`` and generation n ``KEY.gN.EXT``; a key that
    itself ends in ``.g`` and digits gets its ``.g1`` spelt out, so no
    (key, generation) pair names another's file.
    """
    tail = asset_key.rsplit("/", 1)[-1]
    _, dot, last = tail.rpartition(".g")
    ambiguous = bool(dot) and last.isdigit() and last.isascii()
    name = asset_key if generation == 1 and not ambiguous else f"{asset_key}.g{int(generation)}"
    return Path(out_dir) / recipient / f"{name}{suffix}"


def pending_path(final):
    """The name a copy is written under until its ledger row is durable."""
    final = Path(final)
    return final.with_name(f".{final.stem}.pending{final.suffix}")
