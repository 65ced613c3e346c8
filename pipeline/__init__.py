"""Pure per-block kernels: numpy arrays in, numpy arrays out.

Imports numpy and scipy (and laspy/pyarrow/pyproj only in its IO modules: ``lasheader``,
``blockinfo``, ``crs``, ``reading``, ``laswriting``, ``parquet``); never dask, SQLite,
FastAPI or environment variables. See docs/method.md for the method.
"""
