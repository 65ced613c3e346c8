"""The report map's sample of a block: every stride-th point of the file, the same
points whoever reads them (the tiler, a job in memory, the report from the files)."""

from __future__ import annotations

#: points of a report's map at most: every stride-th point of the block (:func:`sample_stride`)
REPORT_POINTS = 150_000


def sample_stride(n_points: int, max_points: int = REPORT_POINTS) -> int:
    """Every how-many-th point a sample of at most ``max_points`` of ``n_points`` takes
    (the first, then every stride-th): ceil(n_points / max_points), at least 1."""
    return max(1, -(-int(n_points) // max_points))


def first_sampled(start: int, stride: int) -> int:
    """Offset, in a run of points starting at the file's point ``start``, of the run's
    first point on the sample of every ``stride``-th point of the file (those whose index
    is a multiple of ``stride``): every reader of the sample picks the same points."""
    return (-int(start)) % int(stride)
