"""A finished job's report and maps: the self-contained HTML page a grower reads
(:mod:`~service.reports.report`), the map data the job page and the report draw
(:mod:`~service.reports.mapdata`), the static map image (:mod:`~service.reports.mapimage`),
and the subsample of the block's points they share (:mod:`~service.reports.sampling`).

Used by the service's routes and by ``orchard process``; nothing here needs an HTTP
framework.
"""
