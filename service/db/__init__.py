"""The job store in SQLite: the database (:mod:`~service.db.database`), one module per
table family, the :class:`~service.db.jobstore.Store` that combines them, and the
landing of uploaded block files (:mod:`~service.db.block_files`)."""
