#!/usr/bin/env bash
# The docker/compose.yaml topology without Docker: a `dask scheduler`, N `dask worker`
# processes and `orchard serve`, each a separate process on 127.0.0.1 (each binds port 0
# and reports the port it got).
#
# Usage:
#   docker/local-topology.sh [--data-dir DIR] [--workers N] [--ready-file FILE] [-- COMMAND ...]
#
# Without COMMAND it runs until Ctrl-C / SIGTERM, then stops everything it started.
# With COMMAND it runs the command once the topology is up (with ORCHARD_URL,
# ORCHARD_SCHEDULER and ORCHARD_DATA_DIR exported), stops everything and exits with
# the command's status. When everything is up it writes FILE (shell `KEY=VALUE`
# lines: addresses, log folder and process ids), the signal a caller can wait for.
#
# Environment: ORCHARD_TOPOLOGY_TIMEOUT (seconds to wait for each role, default 90),
# ORCHARD_WORKER_MEMORY (per-worker memory limit, default 2GiB),
# ORCHARD_WORKER_THREADS (threads per worker, default 1).
set -euo pipefail

data_dir=""
n_workers=2
ready_file=""
command=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        --data-dir) data_dir="$2"; shift 2 ;;
        --workers) n_workers="$2"; shift 2 ;;
        --ready-file) ready_file="$2"; shift 2 ;;
        --) shift; command=("$@"); break ;;
        -h|--help) sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "local-topology: unknown argument '$1' (see --help)" >&2; exit 2 ;;
    esac
done
if ! [[ "$n_workers" =~ ^[1-9][0-9]*$ ]]; then
    echo "local-topology: --workers must be a positive integer, got '$n_workers'" >&2; exit 2
fi
if [[ -z "$data_dir" ]]; then data_dir="$(mktemp -d -t orchard-topology.XXXXXX)"; fi
mkdir -p "$data_dir"
data_dir="$(cd "$data_dir" && pwd)"
log_dir="$data_dir/logs"
mkdir -p "$log_dir"
timeout_s="${ORCHARD_TOPOLOGY_TIMEOUT:-90}"
python_bin="${PYTHON:-python3}"

pids=()
command_pid=""
stopping=0
stop_all() {
    # Stop in reverse order of start: the API first, then workers, then the scheduler.
    [[ $stopping -eq 1 ]] && return
    stopping=1
    # One at a time, each given up to 20 s: the API must be gone before its scheduler
    # is, or the job it is running fails ("lost the connection to the dask scheduler")
    # instead of staying "running" to be re-queued at the next start.
    local i pid deadline
    if [[ -n "$command_pid" ]] && kill -0 "$command_pid" 2>/dev/null; then  # the command, first
        kill -TERM "$command_pid" 2>/dev/null || true
        deadline=$(( SECONDS + 20 ))
        while kill -0 "$command_pid" 2>/dev/null && (( SECONDS < deadline )); do sleep 0.2; done
        kill -KILL "$command_pid" 2>/dev/null || true
    fi
    for (( i=${#pids[@]}-1; i>=0; i-- )); do
        pid="${pids[$i]}"
        kill -TERM -- "-$pid" 2>/dev/null || kill -TERM "$pid" 2>/dev/null || true
        deadline=$(( SECONDS + 20 ))
        while kill -0 -- "-$pid" 2>/dev/null && (( SECONDS < deadline )); do sleep 0.2; done
        kill -KILL -- "-$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    done
    [[ -n "$ready_file" ]] && rm -f "$ready_file"
    echo "local-topology: stopped (logs in $log_dir)" >&2
}
trap 'stop_all' EXIT
trap 'exit 143' TERM
trap 'exit 130' INT

start() {  # start NAME CMD...: run CMD in its own process group, log to logs/NAME.log
    local name="$1"; shift
    setsid "$@" >"$log_dir/$name.log" 2>&1 < /dev/null &
    pids+=("$!")
    echo "local-topology: started $name (pid $!): $*" >&2
}

wait_for() {  # wait_for NAME PID KIND TARGET: until NAME (process PID) is up, and what it reports
    # KIND http: TARGET (a URL) answers 200. Each process binds port 0 and reports the
    # port it got (a port picked here and bound later could be taken by another process
    # meanwhile): KIND scheduler prints "ADDRESS DASHBOARD_PORT" from the dask scheduler
    # file TARGET; KIND port prints the port in orchard serve's --port-file TARGET
    "$python_bin" - "$@" "$timeout_s" <<'PY' || { echo "local-topology: $1 did not come up; see $log_dir/$1.log" >&2; tail -n 20 "$log_dir/$1.log" >&2 || true; exit 1; }
import json, os, sys, time, urllib.request
name, pid, kind, target, timeout = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4], float(sys.argv[5])


def reported():
    if kind == "http":
        with urllib.request.urlopen(target, timeout=2) as r:
            return "" if r.status == 200 else None
    with open(target) as fh:
        text = fh.read()
    if kind == "scheduler":
        info = json.loads(text)
        return f"{info['address']} {info['services']['dashboard']}"
    return str(int(text))


deadline = time.monotonic() + timeout
while time.monotonic() < deadline:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        sys.exit(f"local-topology: {name} exited during start-up")
    try:
        out = reported()
    except Exception:  # not up yet, or its file not there or being written
        out = None
    if out is not None:
        if out:
            print(out)
        sys.exit(0)
    time.sleep(0.2)
sys.exit(f"local-topology: {name} not up ({kind} {target}) after {timeout:.0f} s")
PY
}

host=127.0.0.1
rm -f "$log_dir/scheduler.json" "$log_dir/api.port"
start scheduler dask scheduler --host "$host" --port 0 --dashboard-address "$host:0" \
    --scheduler-file "$log_dir/scheduler.json"
read -r scheduler dashboard_port < <(wait_for scheduler "${pids[0]}" scheduler "$log_dir/scheduler.json") || exit 1
wait_for scheduler "${pids[0]}" http "http://$host:$dashboard_port/health"

# dask's nanny starts each worker with MALLOC_TRIM_THRESHOLD_=65536, which maps and
# page-faults every array above 128 KiB afresh: the embedded cluster's allocator
# settings instead (workers.cluster.WORKER_MALLOC_ENV), dask's others kept
worker_environ="{'MALLOC_MMAP_THRESHOLD_': '16777216', 'MALLOC_TRIM_THRESHOLD_': '33554432', 'OMP_NUM_THREADS': 1, 'MKL_NUM_THREADS': 1, 'OPENBLAS_NUM_THREADS': 1}"
export DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON="${DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON:-$worker_environ}"
for (( i=1; i<=n_workers; i++ )); do
    # env -u: like a container's clean environment; the nanny lets an inherited
    # MALLOC_* value override its pre-spawn setting
    start "worker-$i" env -u MALLOC_TRIM_THRESHOLD_ -u MALLOC_MMAP_THRESHOLD_ dask worker "$scheduler" --host "$host" --name "local-worker-$i" \
        --preload workers.preload --nworkers 1 --nthreads "${ORCHARD_WORKER_THREADS:-1}" \
        --memory-limit "${ORCHARD_WORKER_MEMORY:-2GiB}" \
        --dashboard-address "$host:0" --local-directory "$data_dir/dask-worker-$i"
done
"$python_bin" - "$scheduler" "$n_workers" "$timeout_s" <<'PY' || { echo "local-topology: workers did not register with the scheduler" >&2; exit 1; }
import sys
from distributed import Client
with Client(sys.argv[1], timeout=float(sys.argv[3])) as client:
    client.wait_for_workers(int(sys.argv[2]), timeout=float(sys.argv[3]))
PY

start api orchard serve --host "$host" --port 0 --port-file "$log_dir/api.port" --data-dir "$data_dir" --scheduler "$scheduler"
api_port="$(wait_for api "${pids[-1]}" port "$log_dir/api.port")" || exit 1
wait_for api "${pids[-1]}" http "http://$host:$api_port/healthz"

export ORCHARD_URL="http://$host:$api_port"
export ORCHARD_SCHEDULER="$scheduler"
export ORCHARD_DATA_DIR="$data_dir"
if [[ -n "$ready_file" ]]; then
    tmp="$ready_file.tmp"
    {   # quoted for the shell (%q): `source` the file to get these variables
        printf '%s=%q\n' ORCHARD_URL "$ORCHARD_URL" ORCHARD_SCHEDULER "$ORCHARD_SCHEDULER" \
            ORCHARD_DATA_DIR "$ORCHARD_DATA_DIR" DASHBOARD_URL "http://$host:$dashboard_port" \
            LOG_DIR "$log_dir" PIDS "${pids[*]}" TOPOLOGY_PID "$$"
    } > "$tmp"
    mv "$tmp" "$ready_file"
fi
echo "local-topology: up. API $ORCHARD_URL, scheduler $ORCHARD_SCHEDULER, dashboard http://$host:$dashboard_port/status, data $data_dir" >&2

if [[ ${#command[@]} -gt 0 ]]; then
    # In the background, so that a SIGTERM or Ctrl-C is acted on at once (bash runs a
    # trap only once its foreground child has ended), with the terminal's stdin kept
    # (a background command would read /dev/null); stop_all stops it first.
    "${command[@]}" 0<&0 &
    command_pid=$!
    status=0
    wait "$command_pid" || status=$?
    command_pid=""
    exit "$status"
fi
echo "local-topology: Ctrl-C to stop" >&2
while true; do
    # Exit (and stop everything) if any role dies.
    for pid in "${pids[@]}"; do
        if ! kill -0 "$pid" 2>/dev/null; then
            echo "local-topology: process $pid exited; stopping" >&2
            exit 1
        fi
    done
    sleep 1 &
    wait $! || true
done
