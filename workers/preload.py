"""The preload of dask workers that run orchard jobs: ``dask worker ADDR --preload workers.preload``.

A fresh worker imported the pipeline (scipy's csgraph, spatial and ndimage, pyarrow,
laspy...) in its first tasks: importing ``workers.tasks`` as the first ground task
arrived took 0.55-0.58 CPU-s and 2.1-2.4 s wall on this machine (docs/performance.md),
an idle gap between a job's stages. Imported when the worker starts, before it
registers with the scheduler, the modules are there when the first job's tasks arrive.
The embedded cluster's workers load it too (:data:`workers.cluster.EMBEDDED_PRELOADS`).
"""

from __future__ import annotations

import importlib

#: What a job's tasks import: ``workers.job`` holds the merge task and imports every
#: other task's module (counting, splitting, ground, tiles, outputs); fsspec is imported
#: where a work store is opened, dask's numpy serialisation with the first array.
TASK_MODULES = ("workers.job", "fsspec", "distributed.protocol.numpy")


def dask_setup(worker=None) -> None:
    """Import :data:`TASK_MODULES` (dask calls it as the worker starts)."""
    for name in TASK_MODULES:
        importlib.import_module(name)
