"""Candidates: which catalogue assets a suspect may be a copy of, best first.

A suspect is read once and ranked two ways (:func:`triage`): by shape
distribution against every asset's views, and by votes of local descriptors
over the catalogue index (:func:`build_index`, kept per catalogue version).
:func:`candidates` interleaves the two rankings; :func:`planned_recipients`
counts every recipient the checks of those candidates could accuse, so the
threshold is corrected for all of them whichever check stops the search.
:func:`cascade` decides how far each check may go; once a check lays the
suspect whole on one original, :func:`after_whole` stages the rest again,
with what earlier copies laid whole on it witnessed (:func:`holdings`,
kept by :func:`witness`).
"""

from __future__ import annotations

import hashlib
import io
import json
import sys
import time
import zipfile
from collections import OrderedDict
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..allocator import keep_freed_memory
from ..io.basis_store import find_file, find_files, map_faiss, read_file, read_holdings, record_holding, write_file
from ..io.pointcloud import InputError, read_points, sha256_file
from ..kernels.descriptor import d2_descriptor, descriptor_distance
from ..kernels.registration import POSES_FIT

__all__ = ["triage", "candidates", "cascade", "after_whole", "votes_without", "whole_may_stop", "witness_settings",
           "whole_original", "holding_of", "held_by", "holdings", "witness", "build_index", "load_index",
           "planned_recipients", "INDEX_FORMAT", "MIN_POINTS", "HOLD_FIT"]


TWIN_LENDERS = 10    # the assets with the most votes, whose twins (same shape, other sampling) share them

_INDEXES: "OrderedDict[str, object]" = OrderedDict()    # sha256 of an index file -> its FeatureIndex


def load_index(path, sha256=None):
    """The :class:`~pipeline.features.FeatureIndex` in ``path``, kept per process by its bytes' sha256.

    A long-lived worker scans night after night: an index rebuilt at the same path is read again.
    Given the ``sha256`` a scan recorded once, a process that holds that index reads nothing; one
    that does not reads the file and refuses bytes with another hash.
    """
    from ..features import FeatureIndex

    if sha256 in _INDEXES:
        _INDEXES.move_to_end(sha256)
        return _INDEXES[sha256]
    data = read_file(path)
    key = hashlib.sha256(data).hexdigest()
    if sha256 is not None and key != sha256:
        raise ValueError(f"{path}: the candidate index changed since the scan began (sha256 differs)")
    if key in _INDEXES:
        _INDEXES.move_to_end(key)
    else:
        _INDEXES[key] = FeatureIndex.load(io.BytesIO(data), _ivf_part(path, mapped=True))
        while len(_INDEXES) > 2:
            _INDEXES.popitem(last=False)
    return _INDEXES[key]


def _ivf_part(path, mapped):
    """``open_ivf`` of :meth:`~pipeline.features.FeatureIndex.load` for the index at ``path``: its faiss
    part (``.ivf`` beside it), checked against the sha256 the index recorded, memory-mapped or read."""
    part = Path(path).with_suffix(".ivf")

    def open_ivf(sha256):
        try:
            found = sha256_file(part)
        except OSError as exc:
            raise ValueError(f"{part}: the candidate index's faiss part cannot be read: {exc.strerror or exc}") from None
        if found != sha256:
            raise ValueError(f"{part}: the candidate index's faiss part differs from what the index recorded "
                             f"(sha256)")
        return map_faiss(part) if mapped else read_file(part)

    return open_ivf


MIN_POINTS = 16     # under this a suspect's shape and marks cannot be measured: failed, never ranked


def triage(suspect_path, descriptors, index_path, index_sha256=None, twin_shape=None):
    """Read a suspect, hash it, rank every catalogue asset two ways.

    ``ranking``: by shape distribution (D2), the suspect's views (it whole,
    without outliers, each separate object) against each asset's (whole,
    cut as a crop cuts it, and without outliers), right for whole copies,
    scenes, outliers and crops; ``index_ranking``: by votes of local descriptors (FPFH) over the
    catalogue index, right for parts of an asset and assets inside a scene;
    ``whole_distances``: the same ranking's distances to each asset's whole
    view alone; ``index_votes``: each one's share of the suspect's descriptors less its
    background share (inf for an exact geometry hash); ``twins``: for the
    :data:`TWIN_LENDERS` assets with the most votes, the assets whose whole
    view lies within ``twin_shape`` of theirs (:meth:`FeatureIndex.twins`;
    None: none), which :func:`cascade` lends their votes.
    """
    t0 = time.perf_counter()
    keep_freed_memory()     # the descriptors' temporaries, allocated and freed per scale
    points = read_points(suspect_path).points
    if len(points) < MIN_POINTS:
        raise InputError(f"{suspect_path}: {len(points)} point(s): too few to hold a watermark (at least {MIN_POINTS})")
    names = list(descriptors)
    shaped, whole_shaped, voted, twins = {}, {}, [], {}
    if index_path:
        index = load_index(index_path, index_sha256)
        near, near_whole = index.shape_distances(points, whole=True)
        shaped, whole_shaped = dict(zip(index.keys, near)), dict(zip(index.keys, near_whole))
        voted = index.rank(points, top_k=len(names))
        if twin_shape is not None:
            twins = index.twins([k for k, _ in voted[:TWIN_LENDERS]], twin_shape)
    # assets the index lacks (unreadable when it was built) keep the catalogue's whole-asset D2
    missing = [k for k in names if k not in shaped]
    if missing:
        whole = np.atleast_1d(descriptor_distance(d2_descriptor(points - points.mean(axis=0)),
                                                  np.array([descriptors[k] for k in missing])))
        shaped.update(zip(missing, whole))
        whole_shaped.update(zip(missing, whole))
    dist = np.array([shaped[k] for k in names])
    order = np.argsort(dist, kind="stable")
    return {"path": str(suspect_path), "sha256": sha256_file(suspect_path), "n_points": len(points),
            "ranking": [names[i] for i in order], "distances": [float(dist[i]) for i in order],
            "whole_distances": [float(whole_shaped[names[i]]) for i in order],
            "index_ranking": [k for k, _ in voted], "index_votes": [v for _, v in voted], "twins": twins,
            "seconds": time.perf_counter() - t0}


def candidates(info, view, top_k, shape_margin):
    """Candidates among the assets in view, alternating between the rankings (best of each first).

    The top-K of each ranking, and also, up to 2K from the shape ranking,
    the assets whose shape distance is within ``shape_margin`` times the nearest
    in view (near-identical assets tie there).
    """
    by_votes = [a for a in info["index_ranking"] if a in view][:top_k]
    shaped = [(a, d) for a, d in zip(info["ranking"], info["distances"]) if a in view]
    by_shape = [a for i, (a, d) in enumerate(shaped)
                if i < top_k or (i < 2 * top_k and d <= shape_margin * shaped[0][1])]
    pick = [a for pair in zip(by_shape, by_votes) for a in pair]
    pick += by_shape[len(by_votes):] + by_votes[len(by_shape):]
    return list(dict.fromkeys(pick))


def cascade(info, picked, deep_votes, deep_shape, quick_shape):
    """How far each candidate's check may go: the scan's cascade, decided from the triage alone.

    The quick registration steps (:func:`pipeline.watermark.register`)
    settle whole copies, sparse ones and scenes holding the asset whole; the
    deep ones (global RANSAC, the rotation search, 10 to 100 times the cost)
    place what is left, a part of the asset or the asset in junk.  A leak
    shows in its triage either way: a crop's local descriptors vote for its
    asset, a crop or a copy in junk has a view (cut, dense, object by
    object) near the asset's in shape distribution.  So a candidate goes
    "deep" when its vote share (less its background share), or that of an
    asset of the same shape sampled otherwise (the triage's ``twins``: the
    ratio test splits their votes), reaches ``deep_votes``, or its shape
    distance is at most ``deep_shape``; else
    "quick" (the quick steps only; if they leave it undecided it is not
    scored) when its shape distance is at most ``quick_shape``; else it is
    not registered at all (None).  A candidate without votes or a shape
    distance (not indexed, no index) goes deep.  The thresholds are
    calibrated on the leak benchmark (``bench/cascade.py``); what a stage
    stops is never scored, and its recipients still count in the threshold.

    Parameters
    ----------
    info : dict, from :func:`triage`
    picked : list of str, asset keys (from :func:`candidates`)
    deep_votes, deep_shape, quick_shape : float or None
        ``scan.deep_votes``, ``scan.deep_shape`` and ``scan.quick_shape``;
        None in ``deep_votes`` (or ``deep_shape``): every candidate may go
        deep; None in ``quick_shape``: every candidate gets the quick steps.

    Returns
    -------
    dict of asset key -> "deep", "quick" or None
    """
    votes = dict(zip(info.get("index_ranking", []), info.get("index_votes", [])))
    shape = dict(zip(info.get("ranking", []), info.get("distances", [])))
    lent = {}
    for lender, near in info.get("twins", {}).items():
        for a, _ in near:
            lent[a] = max(lent.get(a, -np.inf), votes[lender])
    out = {}
    for a in picked:
        v, d = max(votes.get(a, float("inf")), lent.get(a, -np.inf)), shape.get(a, 0.0)
        if deep_votes is None or deep_shape is None or v >= deep_votes or d <= deep_shape:
            out[a] = "deep"
        elif quick_shape is None or d <= quick_shape:
            out[a] = "quick"
        else:
            out[a] = None
    return out


def votes_without(suspect_path, index_path, index_sha256, whole, twin_shape=None):
    """Each asset's share of the suspect's descriptor votes with ``whole`` left out of the index.

    A suspect laid whole on ``whole``'s original splits its votes between that
    original and any asset holding the same surface (Lowe's ratio test):
    with ``whole`` left out, such an asset draws them (:meth:`FeatureIndex.rank`).
    Assets that hold it alike split them again; as in :func:`triage` and
    :func:`cascade`, each of the :data:`TWIN_LENDERS` assets with the most
    votes lends them to its twins (whole views within ``twin_shape``; None:
    none).  With one asset left the votes tell nothing (it draws every one,
    the background's too): None, as for an index that lacks ``whole``.

    Returns
    -------
    dict
        ``votes`` (asset key -> share less its background share, or None)
        and ``seconds`` (this ranking's, the candidate search's too).
    """
    t0 = time.perf_counter()
    keep_freed_memory()
    index = load_index(index_path, index_sha256)
    votes = None
    if whole in index.keys and len(index.keys) >= 3:
        ranked = index.rank(read_points(suspect_path).points, len(index.keys), without=whole)
        votes = dict(ranked)
        if twin_shape is not None:
            for lender, near in index.twins([k for k, _ in ranked[:TWIN_LENDERS]], twin_shape).items():
                for a, _ in near:
                    if a != whole:
                        votes[a] = max(votes[a], votes[lender])
    return {"votes": votes, "seconds": time.perf_counter() - t0}


def after_whole(info, stages, whole, deep_votes, deep_shape, without, held=None):
    """The cascade once a check laid the suspect whole on the original of ``whole``
    (:func:`pipeline.watermark.laid_whole`): an unmarked original, a copy
    under another key, nothing beside it.

    Such a suspect holds nothing but ``whole``'s surface, and another asset
    can hold it only where that asset holds the same surface.  In this order:

    - a twin of ``whole`` (the triage's ``twins``: the same shape sampled
      otherwise, nothing more) may be it whole, which the quick steps
      settle: the quick steps only;
    - one that an earlier copy laid whole on the same original was
      registered on, deep, and lay on nowhere (``held`` False, from
      :func:`held_by`) is not registered; one it lay on (``held`` True)
      keeps its stage;
    - one whose votes reach ``deep_votes`` once ``whole`` is left out of
      the index (``without``, from :func:`votes_without`) keeps its stage:
      an asset that holds the suspect as a part of more (a scene asset
      holding an object asset, cut down to the object) draws the votes the
      object took;
    - so does one within ``deep_shape`` of the suspect by a view cut from
      it, or its dense view, but not by its whole view: a part of it is
      shaped like the suspect;
    - one within ``deep_shape`` by its whole view may be it whole: the
      quick steps only;
    - the others are not registered (None).

    Their recipients still count in the threshold.

    Parameters
    ----------
    info : dict, from :func:`triage`
    stages : dict of asset key -> "deep", "quick" or None
        The remaining candidates' stages (from :func:`cascade`).
    whole : str
        The asset whose original the suspect was laid on whole.
    deep_votes, deep_shape : float or None
        ``scan.deep_votes`` and ``scan.deep_shape``; None keeps every stage.
    without : dict of asset key -> float, or None
        :func:`votes_without` ({} where it was not needed: every candidate
        witnessed); None (no index, or it lacks ``whole``, or holds fewer
        than three assets, or the ranking failed) keeps every stage that
        ``held`` does not decide, twins' too.
    held : dict of asset key -> bool or None, optional
        :func:`held_by` of the witnesses recorded for ``whole`` and each
        candidate; absent or None: no witness.

    Returns
    -------
    dict of asset key -> "deep", "quick" or None
    """
    if deep_votes is None or deep_shape is None:
        return dict(stages)
    held = held or {}
    shape = dict(zip(info.get("ranking", []), info.get("distances", [])))
    whole_shape = dict(zip(info.get("ranking", []), info.get("whole_distances", info.get("distances", []))))
    twins = {a for a, _ in info.get("twins", {}).get(whole, [])} if without is not None else set()
    out = {}
    for a, s in stages.items():
        near, near_whole = shape.get(a, 0.0) <= deep_shape, whole_shape.get(a, 0.0) <= deep_shape
        if a in twins:
            out[a] = s and "quick"
        elif held.get(a) is not None:
            out[a] = s if held[a] else None
        elif without is None or without.get(a, float("inf")) >= deep_votes or (near and not near_whole):
            out[a] = s          # not ranked or not indexed: as the cascade, it goes on as it was
        elif near:
            out[a] = s and "quick"
        else:
            out[a] = None
    return out


HOLD_FIT = POSES_FIT  # least share of a copy laid whole on one original near another, for that one to hold it
                      # (where the registration record measures ``lies_on`` at all)
HOLDING_FORMAT = 1    # what a witness record means; a new format starts the records afresh
SAMPLING_TIE = 1.25   # a witness about as sparse as a suspect: its spacing at least the suspect's / this


def witness_settings(detect_params):
    """Hex digest of the registration settings a witness depends on (and of :data:`HOLDING_FORMAT`).

    Parameters
    ----------
    detect_params : DetectParams

    Returns
    -------
    str or None
        None where witnesses are not kept: a registration other than the
        robust cascade's.
    """
    if detect_params.registration != "robust":
        return None
    fields = {k: getattr(detect_params, k) for k in ("registration", "ransac_iterations", "search_rotations",
                                                       "search_poses")}
    if detect_params.search_screen:     # what a deep step finds depends on it (off: the digest as before it)
        fields["search_screen"] = True
    return hashlib.sha256(json.dumps({**fields, "format": HOLDING_FORMAT}, sort_keys=True).encode()).hexdigest()


def whole_original(check):
    """The original a check laid the suspect whole on (:func:`pipeline.orchestrate.attribute.laid_whole`).

    Parameters
    ----------
    check : dict, from :func:`pipeline.orchestrate.attribute.check_asset`

    Returns
    -------
    dict or None
        ``asset_key``, ``sha256`` (the original's bytes) and ``sampling``
        (the suspect's median spacing over the original's, at that pose);
        None where no registration laid it whole.
    """
    for g in check["groups"]:
        if g["registration"].get("whole"):
            return {"asset_key": check["asset_key"], "sha256": g["original_sha256"],
                    "sampling": g["registration"].get("sampling")}
    return None


def holding_of(check, deep):
    """What one check of another asset, made after the suspect was laid whole on an original, witnesses.

    Parameters
    ----------
    check : dict, from :func:`pipeline.orchestrate.attribute.check_asset`
    deep : bool
        Whether the check could run the registration's deep steps.

    Returns
    -------
    dict of str -> bool
        Per original registered (its sha256): True where a registration
        laid at least :data:`HOLD_FIT` of the suspect within 3 spacings of
        it and on its surface (the registration's ``lies_on``; not known
        counts as on): it may hold the surface. False where none did and the
        deep steps were allowed (near it but off its surface, as on a sparse
        original's wide band, counts as off). Originals left unscored
        or not found, and those the quick steps alone placed without
        laying the suspect on them, witness nothing.
    """
    out = {}
    for g in check["groups"]:
        reg = g["registration"]
        on = reg.get("fitness", 0.0) >= HOLD_FIT and reg.get("lies_on") is not False
        if on or deep:
            out[g["original_sha256"]] = out.get(g["original_sha256"], False) or on
    return out


def held_by(records, sampling=None):
    """Whether an original holds another's surface, by the witnesses of the pair (:func:`holding_of`, as kept).

    A sparser copy is judged more leniently: the registration takes its
    overlap at three of the copy's own spacings when choosing a pose, and
    its roughness, over wider neighbourhoods, widens what ``lies_on``
    allows. So a witness that lay on it nowhere speaks only for copies
    about as dense as it, or denser.

    Parameters
    ----------
    records : list of dict, or None
        ``held`` and ``sampling`` (the witness's spacing over the whole
        original's) of each witness; None: a record could not be read.
    sampling : float, optional
        The suspect's, likewise; None: no witness that lay on it nowhere counts.

    Returns
    -------
    bool or None
        True when any witness lay on it; False when one that lay on it
        nowhere is at least ``sampling`` / :data:`SAMPLING_TIE` (and none lay
        on it); None when there is none of either, or one cannot be read.
    """
    if not records:
        return None
    found = [r.get("held") if isinstance(r, dict) else None for r in records]
    if any(h is not True and h is not False for h in found):
        return None
    if any(found):
        return True
    if sampling is None:
        return None
    about = [r.get("sampling") for r in records]
    return False if any(isinstance(w, (int, float)) and w >= sampling / SAMPLING_TIE for w in about) else None


def holdings(store, whole, others, settings):
    """Per candidate asset, whether its originals hold the surface of the original ``whole`` names.

    Parameters
    ----------
    store : str or Path
        The basis store.
    whole : dict, from :func:`whole_original`
    others : dict of asset key -> iterable of str
        The sha256 of each original of the asset that a check would register.
    settings : str or None
        :func:`witness_settings`; None: no witness is read.

    Returns
    -------
    dict of asset key -> bool or None
        True when a witness lay on any of its originals; False when every
        one of them has a witness that lay on it nowhere (:func:`held_by`);
        None otherwise.
    """
    out = {}
    for a, shas in others.items():
        found = [None if settings is None else
                 held_by(read_holdings(store, whole["sha256"], sha, settings), whole["sampling"]) for sha in shas]
        out[a] = True if True in found else (False if found and all(h is False for h in found) else None)
    return out


def witness(store, whole, check, deep, suspect_sha256, settings):
    """Keep what one check witnessed (:func:`holding_of`) of a suspect laid whole on an original.

    A witness that cannot be kept (a store and stand-in that refuse) is
    reported on stderr and dropped: it only spares later checks.

    Parameters
    ----------
    store : str or Path
        The basis store.
    whole : dict, from :func:`whole_original`
    check : dict, from :func:`pipeline.orchestrate.attribute.check_asset`
        A check of another asset, after the whole one.
    deep : bool
        Whether that check could run the deep steps.
    suspect_sha256 : str
    settings : str or None
        :func:`witness_settings`; None: nothing is kept.

    Returns
    -------
    dict of str -> bool
        :func:`holding_of` of the check.
    """
    seen = holding_of(check, deep)
    if settings is None:
        return seen
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    for sha, held in seen.items():
        fits = [g["registration"].get("fitness", 0.0) for g in check["groups"] if g["original_sha256"] == sha]
        record = {"held": held, "fitness": max(fits), "sampling": whole["sampling"], "asset_key": check["asset_key"],
                  "original_sha256": sha, "whole_asset_key": whole["asset_key"], "whole_sha256": whole["sha256"],
                  "witness_sha256": suspect_sha256, "recorded_at": now, "format": HOLDING_FORMAT}
        try:
            record_holding(store, whole["sha256"], sha, settings, suspect_sha256, record)
        except (OSError, InputError) as exc:
            print(f"[pointmark] a witness of {check['asset_key']} was not kept: {exc}", file=sys.stderr, flush=True)
    return seen


def whole_may_stop(stages, deep_votes, deep_shape):
    """Whether :func:`after_whole` can change any of ``stages``: the gates set and a stage left to change."""
    return deep_votes is not None and deep_shape is not None and any(s is not None for s in stages.values())


INDEX_FORMAT = "v8"   # v2: inverted-file cells; v3: whole and cut shape views; v4: and the dense view;
                      # v5: a faiss IVF instead of the inverted file, from features.IVF_MIN rows;
                      # v6: the IVF in its own file beside (.ivf), memory-mapped; each asset's file sha256;
                      # v7: features.ivf_cells cells, found through an HNSW graph;
                      # v8: at most 2,000 descriptors an asset and a suspect's description (was 3,000)


def _loads(index_path):
    try:
        load_index(index_path)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return False
    return True


def build_index(out, cat_version, catalogue_paths):
    """The catalogue's local-descriptor index, built once per catalogue version.

    Kept in ``out`` (a scan's folder, or the basis store for ``detect
    --ledger``), or in its stand-in when ``out`` cannot be written.  A new
    catalogue version grows the newest kept index whose every asset it still
    holds with the same bytes (:meth:`~pipeline.features.FeatureIndex.extend`:
    only the assets added are described); any other change builds it afresh.
    """
    from ..features import build_index as build

    name = f"state/index-{INDEX_FORMAT}-{cat_version}.npz"
    found = [p for p in find_file(out, name) if _loads(p)]      # a damaged one is rebuilt
    if found or not catalogue_paths:
        return str(found[0]) if found else None
    clouds, sources, missing = {}, {}, []
    for key, file in sorted(catalogue_paths.items()):
        try:
            sources[key] = sha256_file(file)
        except OSError:
            missing.append(key)          # its checks fail (and are retried); D2 still ranks it
    base = _grown_from(out, sources)
    for key in sorted(set(sources) - set(base.keys if base else ())):
        try:
            clouds[key] = read_points(catalogue_paths[key]).points
        except InputError:
            missing.append(key)
    if base is None and not clouds:
        return None
    if base is None:
        index = build(clouds)
    else:
        index = base
        if clouds:
            index.extend(clouds)
    index.sources = [sources[k] for k in index.keys]
    if missing:                          # not saved: the next scan builds it whole
        return _save(out, f"state/.index-{cat_version}-partial.npz", index)
    return _save(out, name, index)


def _save(out, name, index):
    """Write an index as its ``.npz`` and, for an IVF, its faiss part beside it (first: a ``.npz`` found
    always has its part); the ``.npz``'s path."""
    npz, ivf = index.to_parts()
    if ivf is not None:
        write_file(out, name[: -len(".npz")] + ".ivf", ivf)
    return str(write_file(out, name, npz))


def _grown_from(out, sources):
    """A fresh copy of the newest kept index whose assets ``sources`` (key -> sha256) all hold, with those
    bytes, and that can grow to all of them (:meth:`~pipeline.features.FeatureIndex.can_grow_to`); None
    when there is none."""
    from ..features import FeatureIndex

    for path in find_files(out, f"state/index-{INDEX_FORMAT}-*.npz"):
        try:
            data = read_file(path)
            held = np.load(io.BytesIO(data))       # its keys and sources first: no faiss part read in vain
            if "sources" not in held.files or any(sources.get(str(k)) != str(h)
                                                  for k, h in zip(held["keys"], held["sources"])):
                continue
            index = FeatureIndex.load(io.BytesIO(data), _ivf_part(path, mapped=False))
        except (OSError, ValueError, KeyError, zipfile.BadZipFile):
            continue
        if index.can_grow_to(len(sources)):
            return index
    return None


def planned_recipients(candidate_rows, materials):
    """Recipients a suspect may be scored against: every (reference, key, generation, recipient) held.

    Parameters
    ----------
    candidate_rows : list of list of dict
        Issued ledger rows of each candidate asset.
    materials : dict key_id -> bytes

    Returns
    -------
    int
        An upper bound on what :func:`check_asset` scores for these candidates.
    """
    return sum(len({(r["reference_key"], r["key_id"], r["generation_id"], r["recipient"])
                    for r in rows if r["key_id"] in materials}) for rows in candidate_rows)
