import os

import pytest

_ALLOCATOR_KEYS = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_")


@pytest.fixture(autouse=True)
def _allocator_environment_restored():
    """dask's nanny writes its pre-spawn settings into this process's environment, where
    they would override the next cluster's (an inherited value wins): undo that after each test."""
    before = {k: os.environ.get(k) for k in _ALLOCATOR_KEYS}
    yield
    for key, value in before.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value
