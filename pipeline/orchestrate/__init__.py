"""The catalogue job as a Dask graph: plan per asset, one task per cluster, assemble and write."""
