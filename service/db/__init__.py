"""The job store in SQLite: the database (:mod:`~service.db.database`), one part per
concept (tenants and tokens, quotas, blocks, jobs, orchard blocks and captures,
schedules, webhooks), the :class:`~service.db.jobstore.Store` that holds the parts,
and the landing of uploaded block files (:mod:`~service.db.block_files`)."""
