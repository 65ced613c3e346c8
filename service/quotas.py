"""Per-tenant quotas set by the operator: stored bytes and queued jobs.

A tenant (farm) without a quota row, or with a limit left unset, is unlimited. The
store checks a limit inside the transaction that would go past it (a block recorded,
a job queued), so requests at the same moment cannot both slip under it; the edges
(API, inbox scans, command line) only word the `QuotaExceeded` they receive.

Stored bytes are the sizes of the tenant's uploaded and captured blocks (each block
once, whatever the number of its jobs); job results are not counted.
"""

from __future__ import annotations

from pipeline.errors import OrchardError

GB = 1_000_000_000  #: a quota's gigabyte [bytes] (decimal, as disks are sold)


def gigabytes(n_bytes: int | float) -> str:
    """``n_bytes`` as decimal gigabytes for messages ("1.25 GB")."""
    return f"{n_bytes / GB:.2f} GB"


class QuotaExceeded(OrchardError):
    """A request would take a tenant past one of its quotas.

    Attributes
    ----------
    tenant : str
        The tenant's name.
    resource : str
        ``"storage"`` or ``"queued jobs"``.
    limit, used, requested : int
        The quota, what the tenant holds now and what the request adds (bytes for
        storage, jobs for the queue).
    """

    def __init__(self, *, tenant: str, resource: str, limit: int, used: int, requested: int, message: str) -> None:
        super().__init__(message)
        self.tenant, self.resource = tenant, resource
        self.limit, self.used, self.requested = limit, used, requested


class StorageQuotaExceeded(QuotaExceeded):
    """A block would take the tenant's stored bytes past its storage quota."""

    def __init__(self, *, tenant: str, limit: int, used: int, requested: int) -> None:
        super().__init__(
            tenant=tenant, resource="storage", limit=limit, used=used, requested=requested,
            message=(f"tenant {tenant!r} is at its storage quota: it stores {gigabytes(used)} of its "
                     f"{gigabytes(limit)} and this file is {gigabytes(requested)}; nothing of it was kept. "
                     "Ask the service's operator to raise the quota"),
        )


class QueueQuotaExceeded(QuotaExceeded):
    """A job would take the tenant's queued jobs past its limit."""

    def __init__(self, *, tenant: str, limit: int, used: int, requested: int = 1) -> None:
        super().__init__(
            tenant=tenant, resource="queued jobs", limit=limit, used=used, requested=requested,
            message=(f"tenant {tenant!r} has {used} job(s) queued, its limit of {limit}; wait until some have "
                     "started (or cancel some) before queuing more"),
        )
