"""The job store: one object over the SQLite database that the service's threads and
processes share (see :mod:`service.db.database`), in parts by concept.

Every lookup that serves a tenant takes the tenant and never returns another tenant's
record: it raises `NotFoundError` instead (or returns nothing). The few callers that
serve every tenant (the schedule clock, the job runner, the webhook sender, the
operator's command line) use the lookups named ``*_any_tenant``.
"""

from __future__ import annotations

import os

from service.db.accounts import Accounts
from service.db.blocks import Blocks
from service.db.database import Database
from service.db.inbox_schedules import InboxSchedules
from service.db.job_queue import JobQueue
from service.db.orchard_blocks import OrchardBlocks
from service.db.tenant_quotas import TenantQuotas
from service.db.webhooks import Webhooks


class Store:
    """SQLite job store under ``path`` (created if missing), one part per concept:
    ``accounts`` (tenants and tokens), ``quotas``, ``blocks``, ``jobs``,
    ``orchard_blocks`` (and their captures), ``schedules`` and ``webhooks``; ``db`` is
    the database they share."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.db = Database(path)
        self.path = self.db.path
        self.accounts = Accounts(self.db)
        self.quotas = TenantQuotas(self.db)
        self.blocks = Blocks(self.db)
        self.jobs = JobQueue(self.db)
        self.orchard_blocks = OrchardBlocks(self.db)
        self.schedules = InboxSchedules(self.db)
        self.webhooks = Webhooks(self.db)

    def close(self) -> None:
        """Close every thread's connection; a later call opens new ones."""
        self.db.close()
