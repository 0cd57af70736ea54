"""The YAML configuration: one JSON Schema holds the keys, defaults and checks.

The schema is exported to ``configs/schema.json`` (``pointmark schema``) for
the Snakefile and for editors.  A config is read, overridden with
``--set NAME=VALUE`` (a key's own name, or its dotted path when the name is
ambiguous), filled with defaults and validated; unknown keys are rejected
with their path.  Secrets are not config: only a key id and a key file path.
"""

from __future__ import annotations

import copy
import json
import math
import re
import sys
from dataclasses import dataclass, fields
from pathlib import Path

import yaml

from .io.catalog import RECIPIENT_PATTERN, check_recipient
from .kernels import coding

__all__ = ["ConfigError", "SCHEMA", "load_config", "watermark_params", "detect_params",
           "schema_json", "WatermarkParams", "DetectParams", "check_code", "marking_rule", "SURVEY_FORMATS"]


class ConfigError(ValueError):
    """A config that cannot be used (the message names the key and the fix)."""


# a Dask scheduler address: a known protocol and host:port (inproc: any local name)
ADDRESS_PATTERN = (r"^(?:(?:tcp|tls|ws|wss)://(?:[A-Za-z0-9](?:[A-Za-z0-9.-]{0,252})|\[[0-9A-Fa-f:.]{2,45}\])"
                   r":[0-9]{1,5}|inproc://[A-Za-z0-9._/-]{1,200})$")
# bytes as dask.utils.parse_bytes reads them ("auto": Dask's share of the machine)
MEMORY_PATTERN = r"^(?:auto|[0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)? ?(?:[kKmMgGtTpP][iI]?)?[bB]?)$"


AUTO_PATTERN = r"^auto$"
# a key id goes into the ledger and onto every line about the key: printable, one line
KEY_ID_PATTERN = r"^[^\x00-\x1f\x7f]{1,128}$"
_PATTERN_HELP = {
    KEY_ID_PATTERN: "is not a key id: 1 to 128 printable characters on one line",
    ADDRESS_PATTERN: "is not a scheduler address: tcp://HOST:PORT (or tls://, ws://, wss://, inproc://)",
    AUTO_PATTERN: "is not a number, null or auto",
    MEMORY_PATTERN: "is not a memory size: auto, or bytes as Dask reads them (4GB, 512 MiB, 2e9)",
    RECIPIENT_PATTERN: "is not a valid recipient id (letters, digits and . _ @ + -, starting with a letter or "
                       "digit, at most 128 characters)",
}


def _p(kind, default, description, **extra):
    prop = {"description": description, "default": default}
    if isinstance(kind, tuple):
        prop["type"] = list(kind)      # a union of JSON types
    elif isinstance(kind, list):
        prop["enum"] = kind
    elif kind is not None:
        prop["type"] = kind
    prop.update(extra)
    return prop


def _section(description, props, required=()):
    return {"type": "object", "description": description, "additionalProperties": False,
            "properties": props, "default": {}, "required": list(required)}


_SEEDS = {
    "description": "Seed points: null (farthest-point sampling), point indices, or [x, y, z] coordinates.",
    "default": None,
    "oneOf": [
        {"type": "null"},
        {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 2**53}, "minItems": 1},
        {"type": "array", "items": {"type": "array", "items": {"type": "number", "minimum": -1e12, "maximum": 1e12},
                                    "minItems": 3, "maxItems": 3}, "minItems": 1},
    ],
}

WATERMARK = _section("Embedding parameters (paper, section 2.2).", {
    "n_bits": _p("integer", 32, "Payload bits m.", minimum=1, maximum=256),
    "chip_rate": _p("integer", 10, "Chip rate c: copies of each bit.", minimum=1, maximum=1000),
    "beta": _p("number", 0.00115, "Amplitude ratio: alpha = beta * largest bbox side.  The default, "
               "0.002 / sqrt(3), marks along the normals at the paper's distance to the surface (its 0.002 "
               "in xyz).", exclusiveMinimum=0, maximum=0.1),
    "valence": _p("number", 12, "Average valence N_n of the radius mesh.", exclusiveMinimum=0,
                  maximum=200),
    "n_clusters": _p("integer", 5, "Number of clusters grown from seeds; with cover, the clusters whose "
                     "distortion budget the covering clusters share (cover_amplitude).", minimum=1,
                     maximum=100_000),
    "cluster_size": _p("integer", 4000, "Size limit of each cluster.", minimum=16,
                       maximum=10_000_000),
    "seeds": _SEEDS,
    "on_touch": _p(["stop", "skip"], "skip",
                   "A growing cluster that meets another: stop (the paper's rule) or pass around it."),
    "cover": _p("boolean", True, "Cover the whole model with clusters of cluster_size, so a crop anywhere keeps "
                "whole clusters (at the paper's distance to the surface: cover_amplitude); false grows only "
                "n_clusters clusters from seeds (the paper)."),
    "cover_amplitude": _p(["paper", "full"], "paper",
                          "With cover on a model-amplitude asset (no tile_points): paper scales every "
                          "cluster's alpha by sqrt(min(1, n_clusters / clusters planned)), so the copy moves "
                          "by the root mean square of the paper's n_clusters clusters (its distance to the "
                          "surface); full keeps alpha in every cluster (more robust, farther from the surface)."),
    "chip_layout": _p(["consecutive", "interleaved"], "interleaved",
                      "Chips of a bit on consecutive coefficients (paper) or spread by the key."),
    "first_coefficient": _p("integer", 0, "Index of the first modulated coefficient.", minimum=0,
                            maximum=1_000_000),
    "crc_bits": _p("integer", 0, "CRC bits appended to the payload (0, 8 or 16).", enum=[0, 8, 16]),
    "displacement": _p(["xyz", "normal"], "normal",
                       "xyz: the paper's displacement; normal: its part along the normals, at the "
                       "same RMSE and peak."),
    "amplitude": _p(["auto", "model", "cluster"], "auto",
                    "phi in alpha = beta * phi: the largest bbox side of the whole model (the paper) or of "
                    "each cluster (large scenes: the motion follows the local extent, not the tile's); "
                    "auto: cluster for survey data (LAS/LAZ), model otherwise."),
    "max_displacement": _p(("number", "null", "string"), "auto",
                           "Cap, in the asset's units, on any point's motion; a cluster whose largest motion "
                           "exceeds it is scaled down as a whole.  null: no cap; auto: survey_cap for survey "
                           "data (LAS/LAZ, in the file's own units), no cap otherwise.",
                           minimum=sys.float_info.min, pattern=AUTO_PATTERN),  # no subnormal cap
    "survey_cap": _p("number", 0.01, "Survey data (LAS/LAZ) with max_displacement auto: the cap in metres "
                     "(converted to the file's units from its coordinate system; metres when it names none).",
                     minimum=1e-6, maximum=1000),
    "tile_points": _p(("integer", "null"), None,
                      "Large assets (LiDAR tiles, scanned scenes): plan clusters cell by cell over a grid of "
                      "square cells holding about this many points, each covered by clusters of cluster_size, "
                      "so planning time and memory are linear in the points; normals come from each "
                      "cluster's own points.  Needs cover: true and no seeds.  null: the whole asset at once.",
                      minimum=1000, maximum=1_000_000_000),
    "code": _p(["repetition", "convolutional", "tailbiting", "tailbiting-half"], "tailbiting",
               "Channel code of the payload: repetition (the paper: each bit on c chips), "
               "convolutional (rate 1/2, K = 7, terminated), tailbiting (rate 1/3, K = 9, "
               "tail-biting) or tailbiting-half (rate 1/2, K = 9, tail-biting): the same m x c chips "
               "over the coded word, soft max-log-MAP decoding; for 32 bits convolutional and "
               "tailbiting need chip_rate >= 3, tailbiting-half chip_rate >= 2 (on the range scan at "
               "c 2 it decoded no more often than tailbiting at c 3 at the same distance: "
               "bench/RESULTS.md)."),
    "band_noise": _p(("number", "null"), 0.01,
                     "Size the spectral band of each asset for this noise (fraction of phi, as the "
                     "noise attack of ROBUSTNESS.md): the chip rate drops below chip_rate, down to what "
                     "the code needs, until the band's highest coefficient keeps band_gain of its "
                     "amplitude once noise of this size has moved the points across the surface; beta "
                     "rises by sqrt(chip_rate / the asset's), so each copy moves as far.  Only dense "
                     "scans change (at band_gain 0.6 and clusters of 4,000: noise over 1.75 median point "
                     "spacings).  0.01: the heaviest noise of "
                     "ROBUSTNESS.md.  null: every asset uses chip_rate (the paper).",
                     exclusiveMinimum=0, maximum=1),
    "band_gain": _p("number", 0.6, "Share of its amplitude the band's highest coefficient keeps at band_noise.",
                    exclusiveMinimum=0, exclusiveMaximum=1),
})

DETECTION = _section("Detection (paper, section 2.2, Extraction).", {
    "registration": _p(["none", "paper", "robust", "global"], "robust",
                       "none; paper: covariance frames; robust: frame hypotheses + ICP with scale "
                       "(the global step competes when under 80 % of the suspect fits); global: FPFH "
                       "correspondences, RANSAC with scale, trimmed ICP (parts, scenes, outliers)."),
    "correspondence": _p(["paper", "spectral"], "spectral",
                         "paper: nearest point under d_r; spectral: least-squares fit of coefficients."),
    "p_threshold": _p("number", 1e-6, "Report 'watermarked' when p_value < p_threshold.",
                      exclusiveMinimum=0, exclusiveMaximum=1),
    "iterations": _p("integer", 2, "Least-squares refits (spectral).", minimum=1, maximum=20),
    "ridge": _p("number", 1.0, "Relative ridge of the least-squares fit (spectral).", minimum=0,
                maximum=1e6),
    "tangential_gate": _p("number", 0.25,
                          "Noisy suspects: tangential misfit of matches closer than this many spacings.",
                          minimum=0, maximum=1000),
    "ratio_gate": _p("number", 0.5,
                     "Clean suspects: tangential misfit of matches nearer than this times the "
                     "second-nearest distance.", minimum=0, maximum=1),
    "gate_switch": _p("number", 0.4,
                      "Noise across the surface, in median spacings, above which the fixed gate "
                      "replaces the ratio gate (0: always fixed).", minimum=0, maximum=1000),
    "outlier_trim": _p(("number", "null"), 10.0,
                       "Spectral fit: leave out matches whose misfit along the normal exceeds this many "
                       "root-median-square misfits of their cluster and more than the mark can move the "
                       "point (junk near the surface); null keeps every match, as the paper's fit does.",
                       minimum=1, maximum=1e6),
    "ransac_iterations": _p("integer", 20000,
                            "RANSAC samples per scale hypothesis of the feature-based global step "
                            "(robust and global registration).", minimum=10, maximum=10_000_000),
    "search_rotations": _p("integer", 1000,
                           "Rotations tried by the exhaustive search that registers a part laid loosely on "
                           "a smooth shape, where features mislead (robust registration).",
                           minimum=1, maximum=100_000),
    "search_poses": _p("integer", 48,
                       "Best poses of that search refined by ICP.", minimum=1, maximum=10_000),
    "search_screen": _p("boolean", True,
                        "Before that search, a coarse one of its own (a 32^3 grid; 1-3 s against 8-10 s) "
                        "must lay the part on the original somewhere; where none does, the search is "
                        "skipped (robust registration).  Calibrated on the leak benchmark."),
    "epsilon": _p("number", 1e-6,
                  "Largest probability of accusing any innocent recipient, per suspect: a recipient is "
                  "named only when its fingerprint score clears the threshold this sets for the number "
                  "of recipients checked.", exclusiveMinimum=0, exclusiveMaximum=1),
})

KEY = _section("Key identity; the secret itself comes from POINTMARK_SECRET or secret_file.", {
    "id": _p(("string", "null"), None, "Key id (public name of the key): printable, at most 128 characters.",
             minLength=1, maxLength=128, pattern=KEY_ID_PATTERN),
    "secret_file": _p(("string", "null"), None, "Path of a file holding the master secret."),
})

CATALOG = _section("The assets to watermark.", {
    "source": _p(("string", "null"), None,
                 "A folder, a glob pattern, a catalogue file (.parquet or .csv), or one point-cloud file."),
})

OUTPUT = _section("Where results go; relative paths are relative to the working directory.", {
    "dir": _p("string", "out/marked", "Watermarked copies: DIR/RECIPIENT/ASSET_KEY.EXT."),
    "manifests": _p("string", "out/manifests",
                    "The issuance ledger: an append-only Parquet dataset (copies/part-*.parquet), "
                    "one row per issued copy, never rewritten."),
    "bases": _p(("string", "null"), None,
                "The basis store (clusters, spectral bases, normals by content hash and parameters); "
                "null: MANIFESTS/bases."),
    "keep_originals": _p("boolean", True,
                         "Keep each original's bytes in the basis store (BASES/originals/SHA256.EXT), so the "
                         "copies issued from them stay attributable after the file is edited, moved or deleted; "
                         "costs the catalogue's size once per version of an original."),
})

DASK = _section("The Dask cluster that runs the graph.", {
    "address": _p(("string", "null"), None,
                  "Scheduler address (tcp://HOST:PORT, tls://, ws://, wss:// or inproc://) of an existing "
                  "cluster; null: Dask's own scheduler-address (DASK_SCHEDULER_ADDRESS) when set, else a new "
                  "LocalCluster.", pattern=ADDRESS_PATTERN),
    "n_workers": _p(("integer", "null"), None, "LocalCluster worker processes (null: CPU count).",
                    minimum=1, maximum=1024),
    "memory_limit": _p(("string", "integer"), "auto", "Memory limit per LocalCluster worker: auto, or bytes "
                       "as Dask reads them (4GB, 512 MiB, 2e9; 0: no limit).", pattern=MEMORY_PATTERN,
                       minimum=0),
    "progress": _p(["auto", "bar", "lines", "none"], "auto",
                   "auto: a live bar on a terminal, periodic lines otherwise."),
})

WORKFLOW = _section("Settings read only by the Snakefile.", {
    "assets": _p(("string", "null"), None, "Folder of asset files the catalogue rule records."),
    "catalogue": _p("string", "out/catalog.parquet", "Catalogue file the workflow builds and embeds from."),
    "shards": _p("integer", 1, "Embedding shards (parallel snakemake jobs).", minimum=1, maximum=10_000),
    "stamps": _p("string", "out/stamps", "Folder of the rules' completion files and logs."),
})

_METHODS = {
    "description": "Method variants: paper (xyz displacement, covariance registration, nearest-point "
                   "resampling), robust (the config's watermark and detection sections) and "
                   "robust-xyz (robust detection of the paper's xyz displacement).",
    "type": "array", "items": {"enum": ["paper", "robust-xyz", "robust"]}, "minItems": 1,
    "default": ["paper", "robust"],
}

EVALUATE = _section("The robustness evaluation (pointmark evaluate).", {
    "out": _p("string", "out/evaluate", "Folder of results.parquet, the plots and summary.md."),
    "repetitions": _p("integer", 1, "Seeds per (model, attack, parameters, method).", minimum=1,
                      maximum=100_000),
    "methods": _METHODS,
    "experiments": {
        "description": "Each: models, attack chains ('+' joins steps, e.g. similarity+removal:0.139), "
                       "parameter sets (watermark overrides), and an optional mesh for simplify.",
        "type": "array", "default": [],
        "items": {"type": "object", "additionalProperties": False, "required": ["name", "models", "attacks"],
                  "properties": {
                      "name": {"type": "string"},
                      "models": {"type": "array", "items": {"type": "string"}, "minItems": 1},
                      "attacks": {"type": "array", "items": {"type": "string"}, "minItems": 1},
                      "parameters": {"type": "array", "default": [{}],
                                     "items": {"type": "object", "additionalProperties": False,
                                               "properties": WATERMARK["properties"]}},
                      "repetitions": {"type": "integer", "minimum": 1, "maximum": 100_000},
                      "methods": _METHODS,
                      "collusion": {"type": "array", "minItems": 1, "description":
                                    "Fingerprint trials instead of message trials: single, average:K, "
                                    "interleave:K (K colluders), unmarked, other-key (every recipient innocent).",
                                    "items": {"type": "string",
                                              "pattern": "^(single|unmarked|other-key|(average|interleave):[1-9][0-9]*)$"}},
                      "recipients": {"type": "integer", "minimum": 1, "maximum": 1_000_000, "default": 1000,
                                     "description": "Recipients issued per asset in fingerprint trials."},
                  }},
    },
    "false_positive_keys": _p("integer", 1000, "Wrong keys tried on each model (0: skip).", minimum=0,
                               maximum=10_000_000),
})

SCAN = _section("Leak-detection scans (pointmark scan).", {
    "suspects": _p(("string", "null"), None, "Folder or glob of suspect files."),
    "catalogue": _p(("string", "null"), None, "Catalogue file (pointmark catalog build) of the originals."),
    "manifests": _p(("string", "null"), None,
                    "Embedding manifest folder (issued payloads); default output.manifests."),
    "out": _p("string", "out/scan", "Detection manifests: one Parquet file per suspect."),
    "top_k": _p("integer", 5, "Candidate assets checked per suspect from each ranking (local-descriptor "
                "votes, shape distribution); on the leak benchmark 3 left the leaked asset out for 5 of 217 "
                "leaks, 5 for 1, at 8.5 asset checks per innocent suspect against 5.2.", minimum=1,
                maximum=1000),
    "shape_margin": _p("number", 1.6, "Assets whose shape-distribution distance is within this factor of "
                       "the nearest are also checked (near-identical assets), up to twice top_k from that "
                       "ranking.", minimum=1.0, maximum=1000),
    "follow": _p(("number", "null"), None,
                 "Keep the scan open for files that appear in scan.suspects while it runs: each is taken "
                 "once its size and time hold for 2 s, and the scan ends after this many seconds without "
                 "a new one.  null: the files there when it starts.", minimum=0, maximum=86400),
    "deep_votes": _p(("number", "null"), 0.03,
                     "The scan's cascade (docs/method.md, Leak scans): a candidate may go on to the deep "
                     "registration steps (global RANSAC, the rotation search: 10 to 100 times the cost of the "
                     "quick ones) when its share of the suspect's descriptor votes, less its background share, "
                     "reaches this (its own or a twin's, twin_shape), or when its shape distance is within "
                     "deep_shape.  Calibrated on the leak benchmark's 217 leaks (bench/RESULTS.md, \"The cascade "
                     "lost two leaks\").  null: every candidate may.",
                     minimum=-1, maximum=1),
    "deep_shape": _p(("number", "null"), 0.06,
                     "The scan's cascade: shape-distribution distance (the nearest of the suspect's views, "
                     "whole, without outliers, object by object, to the asset's, whole or cut) within which a "
                     "candidate may go on to the deep steps whatever its votes.  At 0.05 the cascade lost a "
                     "half crop of a shell with noise (0.053 shape, 0.026 votes).  null: every candidate may.",
                     minimum=0, maximum=1000),
    "twin_shape": _p(("number", "null"), 0.03,
                     "The scan's cascade: assets whose whole views lie within this shape-distribution distance "
                     "of each other are one shape sampled otherwise (a bunny at 8,171 and at 1,889 points: "
                     "0.029); the descriptor votes they split count for each of them at deep_votes.  Without it "
                     "the cascade lost one leak of the benchmark's 217 (a 30 % crop of the 1,889-point bunny, "
                     "0.001 of the votes, its 8,171-point twin 0.169).  null: no votes are lent.",
                     minimum=0, maximum=1000),
    "quick_shape": _p(("number", "null"), None,
                      "The scan's cascade: a candidate that may not go deep gets the quick registration steps "
                      "(principal frames, ICP, the suspect's separate objects) when its shape distance is "
                      "within this, and is scored if they settle it; the others are not registered.  What the "
                      "cascade stops is never scored, and its recipients still count in the threshold.  "
                      "null: every candidate gets the quick steps.", minimum=0, maximum=1000),
    "max_bit_errors": _p("integer", 3, "A decoded payload within this many bits of an issued one "
                         "identifies its recipient.", minimum=0,
                         maximum=256),
})

RECIPIENTS = {
    "description": "Recipient ids; each gets its own fingerprint and output file per asset.  An asset "
                   "whose catalogue file names recipients gets those and these (both, never one "
                   "dropped); an asset with none anywhere gets 'default'.",
    "type": "array", "items": {"type": "string", "pattern": RECIPIENT_PATTERN, "not": {"pattern": "[.][.]"}},
    "uniqueItems": True, "default": [],
}

SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://pointmark.invalid/config.schema.json",
    "title": "pointmark configuration",
    "type": "object",
    "additionalProperties": False,
    "properties": {"watermark": WATERMARK, "detection": DETECTION, "key": KEY,
                   "catalog": CATALOG, "recipients": RECIPIENTS, "output": OUTPUT, "dask": DASK,
                   "workflow": WORKFLOW, "evaluate": EVALUATE,
                   "scan": SCAN},
}


class _Loader(yaml.SafeLoader):
    """SafeLoader reading ``1e-9`` as a number (YAML 1.2) and refusing a key given twice."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue     # "<<: *base" then a key of its own overrides the base: allowed
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:
                    continue     # an unhashable key: SafeConstructor says so
                if first is not None:
                    raise yaml.constructor.ConstructorError(
                        "while reading a mapping", node.start_mark,
                        f"the key {_short(key)} is given twice (first on line {first + 1})", key_node.start_mark)
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


# YAML 1.1 wants a dot in a float ("1.0e-9"); YAML 1.2 and JSON do not ("1e-9")
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"""^(?:
     [-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X), list("-+0123456789."))


def _yaml_load(text):
    return yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader)


def register_section(name, section):
    """Add a top-level section to the schema (used by the catalogue modules)."""
    SCHEMA["properties"][name] = section


def schema_json():
    """The schema as JSON text (what ``configs/schema.json`` holds)."""
    return json.dumps(SCHEMA, indent=2, sort_keys=False) + "\n"


def _defaults(schema):
    out = {}
    for name, prop in schema.get("properties", {}).items():
        if prop.get("type") == "object" and "properties" in prop:
            out[name] = _defaults(prop)
        else:
            out[name] = copy.deepcopy(prop.get("default"))
    return out


def _merge(base, top):
    for k, v in top.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v
    return base


def _leaf_paths(schema, prefix=()):
    for name, prop in schema.get("properties", {}).items():
        if prop.get("type") == "object" and "properties" in prop:
            yield from _leaf_paths(prop, prefix + (name,))
        else:
            yield prefix + (name,)


def _apply_set(cfg, assignment):
    if "=" not in assignment:    # not echoed: it may be a secret typed in the wrong place
        raise ConfigError("--set: expected NAME=VALUE (the text given has no '=')")
    name, raw = assignment.split("=", 1)
    paths = [p for p in _leaf_paths(SCHEMA) if ".".join(p) == name or p[-1] == name]
    exact = [p for p in paths if ".".join(p) == name]
    paths = exact or paths
    if not paths:
        raise ConfigError(f"--set {name}: no such config key")
    if len(paths) > 1:
        options = ", ".join(".".join(p) for p in paths)
        raise ConfigError(f"--set {name}: ambiguous, use one of {options}")
    node = cfg
    for part in paths[0][:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"--set {name}: the config's {part!r} is not a mapping of keys")
    value = "the value" if paths[0][0] == "key" else f"the value {_short(raw)}"
    try:
        node[paths[0][-1]] = _yaml_load(raw)
    except yaml.YAMLError as exc:
        raise ConfigError(f"--set {name}: {value} is not valid YAML: {_yaml_problem(exc)}") from None


def load_config(path=None, overrides=()):
    """Read, override, fill and validate a config.

    Parameters
    ----------
    path : str or Path, optional
        YAML file; none gives the defaults.
    overrides : iterable of str
        ``NAME=VALUE`` assignments.

    Returns
    -------
    dict
    """
    user = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: " + ("not a regular file (a folder, FIFO or device)" if path.exists()
                                              else "config file not found"))
        if path.stat().st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{path}: {path.stat().st_size} bytes; a config is at most {MAX_CONFIG_BYTES} "
                              f"bytes (is this a config file?)")
        try:
            user = _yaml_load(path.read_bytes().decode("utf-8")) or {}
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{path}: not a UTF-8 text file (byte {exc.start})") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML: {_yaml_problem(exc)}") from None
        except RecursionError:
            raise ConfigError(f"{path}: not valid YAML: nested too deeply") from None
        if not isinstance(user, dict):
            raise ConfigError(f"{path}: the config must be a mapping of sections")
    for assignment in overrides:
        _apply_set(user, assignment)
    user = _integral(user, SCHEMA)
    validate(user, source=str(path) if path else "config")
    cfg = _merge(_defaults(SCHEMA), user)
    validate(cfg, source=str(path) if path else "config")
    return cfg


def validate(cfg, source="config"):
    """Raise :class:`ConfigError` naming the first invalid key."""
    _check_values(cfg, source)
    _check_recipients(cfg, source)
    errors = sorted(_validator().iter_errors(cfg),
                    key=lambda e: [(0, p, "") if isinstance(p, int) else (1, 0, str(p))
                                   for p in e.absolute_path])
    if errors:
        err = _branch_error(errors[0])
        where = ".".join(str(p) for p in err.absolute_path) or "(top level)"
        raise ConfigError(f"{source}: {where}: {_explain(err, where)}")
    _check_dask(cfg.get("dask"), source)
    try:
        if isinstance(cfg.get("watermark"), dict):
            check_code(watermark_params(cfg))
    except ValueError as exc:
        raise ConfigError(f"{source}: watermark.code: {exc}") from None
    mark = cfg.get("watermark") or {}
    if mark.get("tile_points") is not None:
        problem = ("tiles choose their own seeds; set seeds to null" if mark.get("seeds") is not None else
                   "tiles are covered by clusters; set cover to true" if not mark.get("cover", False) else
                   "a cell must hold at least one cluster; raise it to cluster_size or more"
                   if mark["tile_points"] < mark.get("cluster_size", 4000) else None)
        if problem:
            raise ConfigError(f"{source}: watermark.tile_points: {problem}")


# YAML aliases can make a small file expand to a huge (or endless) tree.
_MAX_VALUES = 100_000
# a config is a page of settings: a larger file is refused before it is parsed
MAX_CONFIG_BYTES = 1 << 20
# the longest string value (a path, a name)
MAX_STRING = 4096


def _validator():
    """Draft 2020-12, where a float is never an integer (1e300 is not a cluster count) and a
    pattern's ``$`` is the end of the text (Python's also matches before a final newline)."""
    import jsonschema

    base = jsonschema.Draft202012Validator
    checker = base.TYPE_CHECKER.redefine(
        "integer", lambda _, v: isinstance(v, int) and not isinstance(v, bool))

    def pattern(validator, regex, instance, schema):
        if not isinstance(instance, str):
            return
        found = re.search(regex, instance)
        if found is None or (regex.endswith("$") and found.end() != len(instance)):
            yield jsonschema.ValidationError(f"{_short(instance)} {_PATTERN_HELP.get(regex, f'does not match {regex!r}')}")

    return jsonschema.validators.extend(base, {"pattern": pattern}, type_checker=checker)(SCHEMA)


def _integral(value, schema):
    """``value`` with integer-valued floats made ints where ``schema`` wants an integer (6.0 -> 6)."""
    kinds = schema.get("type")
    kinds = [kinds] if isinstance(kinds, str) else kinds or []
    if isinstance(value, float) and "integer" in kinds and "number" not in kinds:
        return int(value) if value.is_integer() and abs(value) <= 2**53 else value
    if isinstance(value, dict) and isinstance(schema.get("properties"), dict):
        return {k: _integral(v, schema["properties"].get(k, {})) for k, v in value.items()}
    if isinstance(value, list) and isinstance(schema.get("items"), dict):
        return [_integral(v, schema["items"]) for v in value]
    for branch in schema.get("oneOf", ()):
        if _shape_fits(value, branch):
            return _integral(value, branch)
    return value


def _shape_fits(value, schema):
    """Whether ``value`` has the JSON shape of ``schema`` (null, array of numbers, array of arrays)."""
    kind = schema.get("type")
    if kind == "null":
        return value is None
    if kind != "array" or not isinstance(value, list):
        return False
    nested = schema.get("items", {}).get("type") == "array"
    return all(isinstance(v, list) == nested for v in value)


def _branch_error(err):
    """For a ``oneOf`` miss (seeds), the error of the branch the value's shape chose."""
    while err.validator == "oneOf" and err.context:
        branches = err.schema["oneOf"]
        chosen = [e for e in err.context if _shape_fits(err.instance, branches[e.schema_path[0]])]
        if not chosen:
            break
        err = chosen[0]
    return err


def _check_recipients(cfg, source):
    """Recipient ids, with the message of :func:`check_recipient` (before the schema's)."""
    names = cfg.get("recipients")
    for i, name in enumerate(names if isinstance(names, list) else ()):
        try:
            check_recipient(name, f"{source}: recipients.{i}")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None


def _check_dask(dask, source):
    """What the patterns cannot say: a port is at most 65535."""
    address = (dask or {}).get("address")
    if isinstance(address, str) and not address.startswith("inproc://"):
        port = int(address.rsplit(":", 1)[1])
        if not 0 < port < 65536:
            raise ConfigError(f"{source}: dask.address: port {port} is not in 1..65535")


def _check_values(cfg, source):
    """Keys are strings, every number is finite, the tree is finite and not too large."""
    count = 0
    stack = [(cfg, (), frozenset())]
    while stack:
        node, where, above = stack.pop()
        count += 1
        if count > _MAX_VALUES:
            raise ConfigError(f"{source}: more than {_MAX_VALUES} values (YAML aliases expanding?)")
        key = ".".join(str(p) for p in where) or "(top level)"
        if isinstance(node, float) and not math.isfinite(node):
            shown = "the value" if where[:1] == ("key",) else repr(node)    # a secret may be pasted under key
            raise ConfigError(f"{source}: {key}: {shown} is not a finite number")
        if isinstance(node, str) and "\0" in node:
            raise ConfigError(f"{source}: {key}: the text holds a NUL byte (no path or name may)")
        if isinstance(node, str) and len(node) > MAX_STRING:
            raise ConfigError(f"{source}: {key}: {len(node)} characters; at most {MAX_STRING}")
        if isinstance(node, (dict, list)):
            if id(node) in above:
                raise ConfigError(f"{source}: {key}: a YAML alias refers to itself")
            inside = above | {id(node)}
            if isinstance(node, dict):
                for k, v in node.items():
                    if not isinstance(k, str):
                        name = "" if where[:1] == ("key",) else f" {_short(k)}"
                        raise ConfigError(f"{source}: {key}: the key{name} is not a string")
                    stack.append((v, where + (k,), inside))
            else:
                stack.extend((v, where + (i,), inside) for i, v in enumerate(node))


def _yaml_problem(exc):
    """One line from a PyYAML error: where and what."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc)
    context = getattr(exc, "context", None)
    text = " ".join(str(problem).split())
    if context:
        text += f" ({' '.join(str(context).split())})"
    if mark is not None:
        text = f"line {mark.line + 1}, column {mark.column + 1}: {text}"
    return text


def _explain(err, where):
    """The schema's message, its value shortened; under ``key`` (a secret may be pasted there) not shown."""
    hidden = where.split(".")[0] == "key"
    if err.validator == "additionalProperties":
        extra = sorted(set(err.instance) - set(err.schema.get("properties", {})))
        known = ", ".join(sorted(err.schema.get("properties", {})))
        names = (f"{len(extra)} (names not shown)" if hidden else
                 ", ".join(k if k.isprintable() and len(k) <= 40 else _short(k, 40) for k in extra))
        return f"unknown key(s) {names}; known keys: {known}"
    shown, message = repr(err.instance), err.message
    if message.startswith(shown):
        return ("the value (not shown)" if hidden else _short(err.instance)) + message[len(shown):]
    if hidden:
        return f"the value (not shown) fails the schema's {err.validator!r} check"
    return message if len(message) <= 300 else message[:297] + "..."


def _short(value, limit=60):
    """``repr(value)``, cut to about ``limit`` characters (escaped: no control characters)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 5]}...{text[-2:]}"


# ----------------------------------------------------------------------------- typed parameters

def _schema_default(section, name):
    value = copy.deepcopy(section["properties"][name]["default"])
    return tuple(value) if isinstance(value, list) else value


_W = {k: _schema_default(WATERMARK, k) for k in WATERMARK["properties"]}
_D = {k: _schema_default(DETECTION, k) for k in DETECTION["properties"]}
# what "auto" means for an asset that is not survey data
_NOT_SURVEY = {"amplitude": "model", "max_displacement": None}
SURVEY_FORMATS = ("las", "laz")
_UNIT_NAMES = {None: "m", 1.0: "m", 0.3048: "ft", 1200 / 3937: "US ft"}


@dataclass(frozen=True)
class WatermarkParams:
    """Parameters shared by embedding and detection (names follow the paper).

    Every default is the schema's (:data:`WATERMARK`), with ``auto`` resolved
    for an asset that is not survey data; :func:`watermark_params` resolves it
    for a given asset.
    """

    n_bits: int = _W["n_bits"]                  # m, payload bits (before the CRC)
    chip_rate: int = _W["chip_rate"]            # c
    beta: float = _W["beta"]                    # amplitude ratio; alpha = beta * phi
    valence: float = _W["valence"]              # N_n, average valence of the radius mesh
    n_clusters: int = _W["n_clusters"]
    cluster_size: int = _W["cluster_size"]
    seeds: tuple | None = _W["seeds"]           # seed indices, or seed coordinates ((x, y, z), ...)
    on_touch: str = _W["on_touch"]              # "stop" (the paper's literal rule) or "skip"
    cover: bool = _W["cover"]                   # grow clusters over the whole model
    cover_amplitude: str = _W["cover_amplitude"]  # "paper": covering clusters share n_clusters' budget
    chip_layout: str = _W["chip_layout"]        # "consecutive" (paper) or "interleaved"
    first_coefficient: int = _W["first_coefficient"]
    crc_bits: int = _W["crc_bits"]              # 0 (paper), 8 or 16
    displacement: str = _W["displacement"]      # "xyz" (paper) or "normal": the same RMSE, along the normals
    amplitude: str = _NOT_SURVEY["amplitude"]   # phi of the whole model (paper) or of each cluster
    max_displacement: float | None = _NOT_SURVEY["max_displacement"]   # cap on any point's motion
    code: str = _W["code"]                      # "repetition" (paper), "convolutional", "tailbiting(-half)"
    tile_points: int | None = _W["tile_points"]  # large assets: clusters planned cell by cell
    band_noise: float | None = _W["band_noise"]  # size each asset's band for this noise (None: chip_rate)
    band_gain: float = _W["band_gain"]          # what the band's last coefficient keeps at band_noise

    def __post_init__(self):
        if self.amplitude == "auto" or self.max_displacement == "auto":
            raise ValueError("WatermarkParams: amplitude and max_displacement must be resolved "
                             "(config.watermark_params resolves auto for an asset)")

    @property
    def shares_budget(self):
        """Clusters covering a model-amplitude asset that spend the paper's budget (``cover_amplitude``)."""
        return (self.cover and self.cover_amplitude == "paper" and self.tile_points is None
                and self.amplitude == "model")

    @property
    def total_bits(self):
        return self.n_bits + self.crc_bits

    @property
    def n_coefficients(self):
        return self.first_coefficient + self.total_bits * self.chip_rate


@dataclass(frozen=True)
class DetectParams:
    """Detection choices: the paper's steps or the robust ones (defaults: the schema's :data:`DETECTION`)."""

    registration: str = _D["registration"]        # "none", "paper", "robust" or "global"
    correspondence: str = _D["correspondence"]    # "paper" (nearest point under d_r) or "spectral"
    p_threshold: float = _D["p_threshold"]        # "watermarked" when p_value < p_threshold
    iterations: int = _D["iterations"]            # least-squares refits
    ridge: float = _D["ridge"]                    # relative ridge of the least-squares fit
    tangential_gate: float = _D["tangential_gate"]
    ratio_gate: float = _D["ratio_gate"]
    gate_switch: float = _D["gate_switch"]
    epsilon: float = _D["epsilon"]                # probability of accusing any innocent, per suspect
    outlier_trim: float | None = _D["outlier_trim"]
    ransac_iterations: int = _D["ransac_iterations"]   # the registration's effort on a suspect that is
    search_rotations: int = _D["search_rotations"]     # not a whole copy: the global step's samples, the
    search_poses: int = _D["search_poses"]             # rotation search's rotations and refined poses
    search_screen: bool = _D["search_screen"]          # a coarse search first; none lies on: no search


def check_code(params, error=ValueError):
    """Raise ``error`` when the chips of ``params`` cannot carry the coded word."""
    symbols = coding.coded_length(params.total_bits, params.code)
    if params.total_bits * params.chip_rate < symbols:
        raise error(f"code {params.code}: {params.total_bits} bits x chip rate {params.chip_rate} = "
                    f"{params.total_bits * params.chip_rate} chips cannot carry its {symbols} coded symbols; "
                    f"raise chip_rate to at least {coding.least_chip_rate(params.total_bits, params.code)}")


def watermark_params(cfg, units=None):
    """WatermarkParams from a validated config, ``auto`` resolved for one asset.

    Parameters
    ----------
    cfg : dict
    units : pipeline.io.pointcloud.Units, optional
        The asset's format, unit and rounding; LAS/LAZ are survey data, whose
        cap is ``survey_cap`` metres in the file's units, less its rounding.
        None: an asset that is not survey data.
    """
    values = {**_W, **cfg["watermark"]}      # a user's section is checked before it is filled
    survey_cap = values.pop("survey_cap")
    seeds = values.get("seeds")
    values["seeds"] = None if seeds is None else tuple(
        tuple(s) if isinstance(s, list) else s for s in seeds)
    survey = units is not None and units.format in SURVEY_FORMATS
    if values["amplitude"] == "auto":
        values["amplitude"] = "cluster" if survey else _NOT_SURVEY["amplitude"]
    if values["max_displacement"] == "auto":
        values["max_displacement"] = _survey_cap(survey_cap, units) if survey else _NOT_SURVEY["max_displacement"]
    return WatermarkParams(**values)


def _survey_cap(survey_cap, units):
    """The cap in the file's units: less its rounding, so the written copy keeps the bound, unless that
    leaves less than one step of its coordinates (a centimetre-scale file): then the bound holds before
    the rounding."""
    if units.geographic:
        raise ValueError("geographic coordinates (degrees): the survey rule's 1 cm cap needs a linear unit; "
                         "reproject, or set watermark.max_displacement (in the file's units) and amplitude")
    cap = survey_cap / (units.unit_m or 1.0)
    return cap - units.rounding if cap - units.rounding >= units.step else cap


def marking_rule(cfg, units=None):
    """One line saying how ``auto`` amplitude and cap were resolved for survey data; None otherwise."""
    mark = cfg["watermark"]
    if units is None or units.format not in SURVEY_FORMATS or "auto" not in (mark["amplitude"],
                                                                            mark["max_displacement"]):
        return None
    params = watermark_params(cfg, units)
    unit = _UNIT_NAMES.get(units.unit_m, "file units")
    within = params.max_displacement + units.rounding <= mark["survey_cap"] / (units.unit_m or 1.0) + 1e-12
    cap = (f"max_displacement {params.max_displacement:g} (config)" if mark["max_displacement"] != "auto" else
           f"no point moved more than {mark['survey_cap'] * 100:g} cm "
           + (f"(a cap of {params.max_displacement:.4g} {unit}, the file's rounding included" if within else
              f"before rounding to the file's {units.step:g} {unit} step (at most "
              f"{params.max_displacement + units.rounding:.4g} {unit} in the file")
           + f"{'' if units.unit_m else '; the file names no unit: metres assumed'})")
    return (f"survey rule ({units.format.upper()}): amplitude per {params.amplitude}, {cap}; "
            f"set watermark.amplitude and max_displacement to override")


def detect_params(cfg):
    """DetectParams from a validated config."""
    return DetectParams(**cfg["detection"])


def cascade_gates(cfg):
    """(deep_votes, deep_shape, quick_shape, twin_shape) of a validated config: the scan's cascade (scan, detect --ledger)."""
    sc = cfg["scan"]
    return sc["deep_votes"], sc["deep_shape"], sc["quick_shape"], sc["twin_shape"]


def dataclass_keys():
    """Field names of the parameter dataclasses, to check the schema against them."""
    return ({f.name for f in fields(WatermarkParams)}, {f.name for f in fields(DetectParams)})
