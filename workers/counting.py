"""A block's points and voxels counted per cell by the cluster's workers, each reading
its own ranges of the file, for the memory budget's choice of tiles
(:func:`workers.jobspec.auto_tiled`). The sample is the one
:func:`pipeline.reading.sample_density` gives counting every point in this process."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable

from pipeline.blockinfo import BlockInfo
from pipeline.budget import DensitySample
from pipeline.reading import CHUNK_POINTS, count_range, sample_density, sample_from_ranges
from workers.dispatch import gather


def count_block(info: BlockInfo, voxel_size: float | None, *, client=None,
                cancel: threading.Event | None = None,
                progress: Callable[[int, int], None] | None = None) -> DensitySample:
    """The density sample of the block ``info``: one task per range of ``CHUNK_POINTS``
    on ``client``'s workers (they must see the input path; one task for a file that
    cannot be entered in the middle, a LAZ of variable-size chunks), or counted here
    without a client, or from a COPC block's hierarchy.

    The tasks are awaited as a job's are (:func:`workers.dispatch.gather`): ``cancel``
    set stops them; ``progress(ranges counted, ranges)`` as each is (on the cluster
    only, and for more than one range).

    Raises
    ------
    InputError
        The point data is truncated or corrupt.
    JobCancelled, ClusterLost
    """
    if client is None or info.copc:  # a COPC block is counted from its hierarchy (little is read)
        return sample_density(info.path, info=info, voxel_size=voxel_size)
    token = uuid.uuid4().hex
    if not info.seekable:  # one worker counts it all in one pass: never the submitting process
        future = client.submit(sample_density, info.path, info=info, voxel_size=voxel_size, key=f"count-all-{token}",
                               pure=False)
        return gather(client, [future], cancel, None, None)[0]  # one task: no steps to show
    futures = [
        client.submit(count_range, info.path, start, CHUNK_POINTS, info=info, voxel_size=voxel_size,
                      key=f"count-range-{start}-{token}", pure=False)
        for start in range(0, info.n_points, CHUNK_POINTS)
    ]
    return sample_from_ranges(info, gather(client, futures, cancel, None, progress if len(futures) > 1 else None))
