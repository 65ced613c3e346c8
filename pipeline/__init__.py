"""Pure per-block kernels: numpy arrays in, numpy arrays out.

Imports numpy and scipy (and laspy/pyarrow only in :mod:`pipeline.io`); never dask,
SQLite, FastAPI or environment variables. See docs/method.md for the method.
"""
