#!/usr/bin/env bash
# Entry point of the orchard image: one image, three roles.
#
#   api        orchard serve (settings from ORCHARD_* variables, see docker/README.md)
#   scheduler  dask scheduler on DASK_SCHEDULER_PORT (8786), dashboard on DASK_DASHBOARD_PORT (8787)
#   worker     dask worker joined to ORCHARD_SCHEDULER, one process of ORCHARD_WORKER_THREADS threads
#   health R   exit 0 when role R answers its health endpoint (used by compose health checks)
#   anything else is run as a command, e.g. `orchard tokens create --tenant farm`.
#
# Extra arguments after the role are passed to the underlying command.
set -euo pipefail

role="${1:-api}"
if [[ $# -gt 0 ]]; then shift; fi

scheduler_port="${DASK_SCHEDULER_PORT:-8786}"
dashboard_port="${DASK_DASHBOARD_PORT:-8787}"
worker_health_port="${DASK_WORKER_DASHBOARD_PORT:-8788}"

probe() {  # probe URL: exit 0 if it answers 200 within 5 s
    python - "$1" <<'PY'
import sys, urllib.request
try:
    with urllib.request.urlopen(sys.argv[1], timeout=5) as r:
        sys.exit(0 if r.status == 200 else 1)
except Exception as exc:  # noqa: BLE001
    print(f"unhealthy: {sys.argv[1]}: {exc}", file=sys.stderr)
    sys.exit(1)
PY
}

case "$role" in
    api)
        mkdir -p "${ORCHARD_DATA_DIR:-/data}"
        exec orchard serve "$@"
        ;;
    scheduler)
        exec dask scheduler \
            --host 0.0.0.0 --port "$scheduler_port" \
            --dashboard-address ":${dashboard_port}" "$@"
        ;;
    worker)
        : "${ORCHARD_SCHEDULER:?set ORCHARD_SCHEDULER=tcp://HOST:PORT for a worker}"
        # dask's nanny starts each worker with MALLOC_TRIM_THRESHOLD_=65536, which maps and
        # page-faults every array above 128 KiB afresh: the embedded cluster's allocator
        # settings instead (workers.cluster.WORKER_MALLOC_ENV), dask's others kept
        worker_environ="{'MALLOC_MMAP_THRESHOLD_': '16777216', 'MALLOC_TRIM_THRESHOLD_': '33554432', 'OMP_NUM_THREADS': 1, 'MKL_NUM_THREADS': 1, 'OPENBLAS_NUM_THREADS': 1}"
        export DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON="${DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON:-$worker_environ}"
        # --preload: the modules of orchard's tasks imported as the worker starts, not in
        # its first tasks (workers/preload.py)
        exec dask worker "$ORCHARD_SCHEDULER" \
            --preload workers.preload \
            --nworkers 1 \
            --nthreads "${ORCHARD_WORKER_THREADS:-1}" \
            --memory-limit "${ORCHARD_WORKER_MEMORY:-2GiB}" \
            --local-directory "${ORCHARD_WORKER_SCRATCH:-/tmp/dask-worker}" \
            --dashboard-address ":${worker_health_port}" "$@"
        ;;
    health)
        case "${1:-api}" in
            api) probe "http://127.0.0.1:${ORCHARD_PORT:-8000}/healthz" ;;
            scheduler) probe "http://127.0.0.1:${dashboard_port}/health" ;;
            worker) probe "http://127.0.0.1:${worker_health_port}/health" ;;
            *) echo "health: unknown role '$1' (api, scheduler, worker)" >&2; exit 2 ;;
        esac
        ;;
    *)
        exec "$role" "$@"
        ;;
esac
