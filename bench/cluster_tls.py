"""``python -m bench.cluster_tls``: what the embedded cluster's TLS costs a tiled run.

Runs ``orchard process BLOCK --tile-size 10`` on a generated block (3 rows of 8 trees,
seed 5) ``--rounds`` times with TLS and as many without it (the certificates replaced by
none, in this process only), alternating, and prints each wall time [s] and the medians.
Each run starts its own embedded cluster, so the times include the certificate and the
TLS handshakes as well as the tiles' traffic.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.cluster_tls", description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=3, help="runs of each kind (default 3)")
    args = p.parse_args(argv)
    import workers.cluster as cluster
    from simulator.simparams import SimulationParams
    from simulator.truth import write_simulation
    from service.cli import main as orchard

    with tempfile.TemporaryDirectory(prefix="orchard-tls-") as tmp:
        block = Path(tmp) / "block.laz"
        write_simulation(SimulationParams(rows=3, trees_per_row=8, seed=5), str(block), str(block) + ".truth.parquet")
        made = cluster._temporary_security
        times: dict[str, list[float]] = {"tls": [], "plain": []}
        orchard(["process", str(block), "--out", f"{tmp}/warm", "--tile-size", "10", "--no-dashboard"])  # imports, caches
        for i in range(args.rounds):
            for kind in ("tls", "plain"):
                cluster._temporary_security = made if kind == "tls" else (lambda: None)
                t0 = time.perf_counter()
                rc = orchard(["process", str(block), "--out", f"{tmp}/{kind}{i}", "--tile-size", "10", "--no-dashboard"])
                if rc != 0:
                    print(f"orchard process exited {rc}", file=sys.stderr)
                    return 1
                times[kind].append(time.perf_counter() - t0)
                print(f"{kind} {i}: {times[kind][-1]:.2f} s", flush=True)
        cluster._temporary_security = made
    for kind, values in times.items():
        print(f"{kind}: median {statistics.median(values):.2f} s of {len(values)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
