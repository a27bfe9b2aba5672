"""Multi-view datasets: collection, chunked storage, clip indexing."""
