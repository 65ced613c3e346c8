"""The worker processes that the compose image and the local topology start get the
embedded cluster's allocator settings, with dask's other pre-spawn settings kept."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import dask
import pytest

from workers.cluster import WORKER_MALLOC_ENV

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("script", ["entrypoint.sh", "local-topology.sh"])
def test_the_scripts_give_dask_workers_the_embedded_cluster_s_allocator(script):
    text = (ROOT / "docker" / script).read_text()
    literal = re.search(r'^\s*worker_environ="(.*)"$', text, re.M).group(1)
    # what dask makes of DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON, as its own defaults are
    given = {k: str(v) for k, v in ast.literal_eval(literal).items()}
    defaults = dask.config.get("distributed.nanny.pre-spawn-environ")
    assert given == {**{k: str(v) for k, v in defaults.items()}, **WORKER_MALLOC_ENV}
    assert 'export DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON="${DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON:-$worker_environ}"' in text
