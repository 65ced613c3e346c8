"""Orchestration: turn a block into tiles and tasks and run them on dask."""
