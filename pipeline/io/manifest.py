"""Parquet manifests: one fixed pyarrow schema, one file per asset, written atomically.

The embedding manifest records what was issued (never the secret: key ids and
fingerprints only).  All files of a folder read back as one table through
``pyarrow.dataset``.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from .pointcloud import atomic_write_bytes

__all__ = ["SCHEMA_VERSION", "EMBED_SCHEMA", "CATALOG_SCHEMA", "write_rows", "read_rows",
           "read_dataset", "manifest_path"]

SCHEMA_VERSION = 1

EMBED_SCHEMA = pa.schema([
    ("schema_version", pa.int16()),
    ("run_id", pa.string()),
    ("asset_key", pa.string()),
    ("source_path", pa.string()),
    ("source_sha256", pa.string()),
    ("output_path", pa.string()),
    ("output_sha256", pa.string()),
    ("recipient", pa.string()),
    ("key_id", pa.string()),
    ("key_fingerprint", pa.string()),
    ("payload", pa.string()),
    ("n_points", pa.int64()),
    ("n_bits", pa.int32()),
    ("chip_rate", pa.int32()),
    ("beta", pa.float64()),
    ("valence", pa.float64()),
    ("n_clusters", pa.int32()),
    ("cluster_size", pa.int32()),
    ("on_touch", pa.string()),
    ("cover", pa.bool_()),
    ("chip_layout", pa.string()),
    ("first_coefficient", pa.int32()),
    ("crc_bits", pa.int32()),
    ("displacement", pa.string()),
    ("seeds_json", pa.string()),
    ("cluster_seeds", pa.list_(pa.int64())),
    ("cluster_sizes", pa.list_(pa.int64())),
    ("cluster_radii", pa.list_(pa.float64())),
    ("rmse_rel_diag", pa.float64()),
    ("hausdorff_rel_diag", pa.float64()),
    ("surface_rmse_rel_diag", pa.float64()),
    ("seconds_plan", pa.float64()),
    ("seconds_clusters", pa.float64()),
    ("seconds_write", pa.float64()),
    ("status", pa.string()),
    ("error", pa.string()),
    ("tool_version", pa.string()),
    ("created_at", pa.timestamp("ms", tz="UTC")),
])

CATALOG_SCHEMA = pa.schema([
    ("schema_version", pa.int16()),
    ("asset_key", pa.string()),
    ("path", pa.string()),
    ("recipients", pa.list_(pa.string())),
    ("sha256", pa.string()),
    ("bytes", pa.int64()),
    ("format", pa.string()),
    ("n_points", pa.int64()),
    ("bbox_min", pa.list_(pa.float64())),
    ("bbox_max", pa.list_(pa.float64())),
    ("descriptor", pa.list_(pa.float64())),
    ("status", pa.string()),
    ("error", pa.string()),
])


def manifest_path(folder, asset_key):
    """Manifest file of one asset: ``folder/<asset_key with / as __>.parquet``."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", asset_key.replace("/", "__"))
    return Path(folder) / f"{safe}.parquet"


def write_rows(path, rows, schema):
    """Write rows (dicts) as one Parquet file, atomically.

    Missing columns are null; ``schema_version`` is filled in.
    """
    rows = [{**{name: None for name in schema.names}, **row, "schema_version": SCHEMA_VERSION}
            for row in rows]
    table = pa.Table.from_pylist(rows, schema=schema)
    buf = io.BytesIO()
    pq.write_table(table, buf)
    return atomic_write_bytes(path, buf.getvalue())


def read_rows(path):
    """Rows of one manifest file as dicts, or [] when it is missing or unreadable."""
    try:
        return pq.read_table(path).to_pylist()
    except (OSError, pa.ArrowInvalid):
        return []


def read_dataset(folder, schema):
    """All manifest files of a folder as one pyarrow Table."""
    files = sorted(Path(folder).glob("*.parquet"))
    if not files:
        return schema.empty_table()
    return ds.dataset([str(f) for f in files], schema=schema, format="parquet").to_table()
