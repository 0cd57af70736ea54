"""Files: point-cloud formats, secrets and Parquet manifests. The only package that touches files."""
