"""Write a job store with the code of 5a744fe (params + tiling columns): the fixture of
test_service_store_migration.py (run with that tree first on the path)."""
import sqlite3, sys
from service.db.jobstore import Store

path = sys.argv[1]
s = Store(path)
t = s.ensure_tenant("farm")
b, _ = s.insert_block(tenant_id=t["id"], sha256="ab" * 32, path="/srv/blocks/ab.laz", filename="north.laz", size_bytes=1, info={})
s.create_job(tenant_id=t["id"], block_id=b["id"], params={"segment": {"max_crown_radius": 2.0}}, tiling={"tile_size": 20.0, "buffer": 4.0})
j2 = s.create_job(tenant_id=t["id"], block_id=b["id"], params={}, tiling=None)
s.claim_next_job(); j = s.claim_next_job()
s.finish_job(j2["id"], "failed", error="north.laz: no trees found in 100 points")
s.create_schedule(tenant_id=t["id"], inbox="/in/a", cron="0 1 * * *", params={"trunks": {"min_tree_height": 1.5}},
                  tiling={"tile_size": 30.0, "buffer": None}, next_run_at=None)
s.create_schedule(tenant_id=t["id"], inbox="/in/b", cron="0 2 * * *", params={}, tiling=None, next_run_at=None)
s.close()
con = sqlite3.connect(path)
con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
con.execute("PRAGMA journal_mode=DELETE")
con.execute("VACUUM")
con.close()
