"""The job store: one object over the SQLite database that the service's threads and
processes share (see :mod:`service.db.database`).

Lookups that take a tenant never return another tenant's record: they raise
`NotFoundError` instead.
"""

from __future__ import annotations

from service.db.accounts import Accounts
from service.db.blocks import Blocks
from service.db.inbox_schedules import InboxSchedules
from service.db.webhooks import Webhooks


class Store(Accounts, Blocks, InboxSchedules, Webhooks):
    """SQLite job store under ``path`` (created if missing): tenants and tokens, quotas,
    blocks, jobs, schedules and webhooks."""
