"""Small Parquet files with a fixed schema, written atomically: catalogues and scan results.

What was issued lives in the ledger (:mod:`pipeline.io.ledger`).
"""

from __future__ import annotations

import io

import pyarrow as pa
import pyarrow.parquet as pq

from .pointcloud import atomic_write_bytes

__all__ = ["SCHEMA_VERSION", "CATALOG_SCHEMA", "write_rows", "read_rows"]

SCHEMA_VERSION = 1

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
