"""The PGVD map-merging method: pure functions on numpy arrays, no network, no clocks."""
