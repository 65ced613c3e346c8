"""The block counted for the memory budget by the cluster's workers, each its own ranges
of the file: the same sample as the count in one process."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

import workers.cellranges as cellranges
import workers.counting as counting
from pipeline.blockinfo import read_info
from pipeline.reading import sample_density
from workers.counting import count_block
from workers.jobspec import JobCancelled


@pytest.fixture(scope="module")
def block(sparse_block):
    return read_info(str(sparse_block))


@pytest.fixture
def client(dask_client):
    return dask_client


def _ranges_counted(client, prefix: str = "count-range") -> int:
    """How many tasks of ``prefix`` (count-range) the (shared) cluster has finished so far."""
    return client.run_on_scheduler(
        lambda dask_scheduler: dask_scheduler.task_prefixes[prefix].state_counts["memory"]
        if prefix in dask_scheduler.task_prefixes else 0)


def test_the_workers_count_what_one_process_counts(block, client, monkeypatch):
    run = 7_000
    monkeypatch.setattr(counting, "CHUNK_POINTS", run)  # several ranges on a small block
    assert block.seekable and block.n_points > 4 * run
    here = sample_density(block.path, info=block, voxel_size=0.1, chunk_points=run)
    before = _ranges_counted(client)
    there = count_block(block, 0.1, client=client)
    assert there.exact and np.array_equal(there.counts, here.counts) and np.array_equal(there.nodes, here.nodes)
    assert _ranges_counted(client) - before >= 4  # counted by tasks, not here


def test_without_a_cluster_the_block_is_counted_here_and_with_one_by_a_task_even_unseekable(block, client, monkeypatch):
    calls = []
    monkeypatch.setattr(counting, "sample_density", lambda *a, **k: calls.append(k) or sample_density(*a, **k))
    monkeypatch.setattr(counting, "CHUNK_POINTS", 7_000)
    here = count_block(block, 0.1)
    assert len(calls) == 1
    monkeypatch.undo()
    keys = []
    submit = client.submit
    monkeypatch.setattr(client, "submit", lambda fn, *a, **k: keys.append(k["key"]) or submit(fn, *a, **k))
    # a LAZ of variable-size chunks: one task reads it all in one pass, not the submitting process
    there = count_block(dataclasses.replace(block, seekable=False), 0.1, client=client)
    assert len(keys) == 1 and keys[0].startswith("count-all-")
    assert np.array_equal(here.counts, there.counts) and np.array_equal(here.nodes, there.nodes)


def test_a_cancel_stops_the_count(block, client, monkeypatch):
    monkeypatch.setattr(counting, "CHUNK_POINTS", 7_000)
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(JobCancelled):
        count_block(block, 0.1, client=client, cancel=cancel)


def test_a_job_given_a_cluster_counts_its_block_there(block, client, monkeypatch, tmp_path):
    # the service's runner hands run_job its cluster: the block is counted by tasks, and
    # never in the submitting process
    import workers.jobspec as jobspec
    from pipeline.budget import FIXED_BYTES, block_bytes
    from pipeline.jobparams import JobParams
    from pipeline.params import PipelineParams
    from workers.runoptions import RunOptions
    from workers.job import run_job

    def not_here(*a, **k):
        raise AssertionError("counted in the submitting process")

    need = block_bytes(sample_density(block.path, info=block, voxel_size=0.1))
    monkeypatch.setattr(counting, "CHUNK_POINTS", 7_000)
    monkeypatch.setattr(counting, "sample_density", not_here)
    monkeypatch.setattr(jobspec, "sample_density", not_here)
    budget = (FIXED_BYTES + 0.6 * (need - FIXED_BYTES)) / 1e9  # the whole block does not fit
    spec = jobspec.JobSpec(block.path, str(tmp_path / "out"), job=JobParams(pipeline=PipelineParams.model_validate(
        {"segment": {"max_crown_radius": 3.0}})), run=RunOptions(worker_memory=budget))
    monkeypatch.setattr(cellranges, "CHUNK_POINTS", 7_000)
    from workers.workstore import WorkStore

    written = []
    put = WorkStore.put_array
    monkeypatch.setattr(WorkStore, "put_array", lambda self, key, arr: written.append(key) or put(self, key, arr))
    before = _ranges_counted(client, "split-range")
    outcome = run_job(spec, client=client)
    assert outcome.n_tiles > 1 and outcome.n_points == block.n_points and outcome.n_trees > 0
    # no buffered tile written by the split: tiles gather their points (the ground pass keeps what it gathered)
    assert not [k for k in written if k.startswith("tiles/0") and not k.endswith("/records.npy")]
    # counted by the tasks that split it (workers.cellranges)
    assert _ranges_counted(client, "split-range") - before >= 4
