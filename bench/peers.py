"""Peers from PyPI on the same generated data: dendromatics (3DFin's library).

dendromatics pins older laspy and scipy than this project uses, so it is installed
in its own virtualenv (``--peers-venv``, by default under ``~/.cache/orchard-bench``)
and run there as a subprocess on the block's points; its labels are scored here with
the same ``simulator.scoring.scores.score_labels`` as our method. Every step that fails is
recorded with the reason, and the report says exactly why the peer did not run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.isolation import one_core, pinned_to

PEER = "dendromatics"
SCRIPT = Path(__file__).with_name("peer_dendromatics.py")

#: 3DFin's default parameters (three_d_fin.processing.configuration), as 3DFin passes them
FIN_DEFAULTS = {
    "res_cloth": 0.7, "lower_limit": 0.7, "upper_limit": 3.5, "number_of_iterations": 2,
    "verticality_scale": 0.1, "verticality_thresh": 0.7, "number_of_points": 1000,
    "res_xy_stripe": 0.02, "res_z_stripe": 0.02, "res_z": 0.035, "res_xy": 0.035,
    "height_range": 0.7, "maximum_d": 15.0, "minimum_points": 20, "distance_to_axis": 1.5,
    "maximum_dev": 25.0, "res_heights": 0.3,
}
#: the same with the stem stripe lowered to the clear trunk of orchard trees (they branch low)
FIN_ORCHARD = dict(FIN_DEFAULTS, lower_limit=0.15, upper_limit=0.7, number_of_points=200)


def _tail(text: str, n: int = 6) -> str:
    return " | ".join(line.strip() for line in text.strip().splitlines()[-n:])


def prepare(work: Path, venv: Path, log=print) -> dict:
    """Download check, install into ``venv`` and import check; returns a status dict."""
    status: dict = {"peer": PEER, "venv": str(venv)}
    dl = work / "peers" / "download"
    dl.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "download", "--no-deps", "--disable-pip-version-check", "-q", "-d", str(dl), PEER],
        capture_output=True, text=True, timeout=600,
    )
    wheels = sorted(p.name for p in dl.glob(f"{PEER}-*"))
    status["download"] = "ok: " + ", ".join(wheels) if proc.returncode == 0 and wheels else f"failed: {_tail(proc.stderr)}"
    if proc.returncode != 0:
        return status
    py = venv / "bin" / "python"
    if not py.exists():
        log(f"  creating {venv} for {PEER}")
        proc = subprocess.run([sys.executable, "-m", "venv", str(venv)], capture_output=True, text=True, timeout=300)
        if proc.returncode != 0:
            status["install"] = f"venv failed: {_tail(proc.stderr)}"
            return status
    proc = subprocess.run(
        [str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q", PEER],
        capture_output=True, text=True, timeout=1800,
    )
    if proc.returncode != 0:
        status["install"] = f"failed: {_tail(proc.stderr)}"
        return status
    proc = subprocess.run(
        [str(py), "-c", "import importlib.metadata as m, dendromatics, laspy, scipy, sklearn; "
         "print(m.version('dendromatics'), m.version('laspy'), m.version('scipy'), m.version('scikit-learn'))"],
        capture_output=True, text=True, timeout=300,
    )
    if proc.returncode != 0:
        status["install"] = f"import failed: {_tail(proc.stderr)}"
        return status
    v = proc.stdout.split()
    status["install"] = "ok"
    status["versions"] = {"dendromatics": v[0], "laspy": v[1], "scipy": v[2], "scikit-learn": v[3]}
    status["python"] = str(py)
    return status


def run_on_block(status: dict, block, work: Path, *, config_name: str, timeout: float, log=print) -> dict:
    """Run the peer on ``block`` with a named configuration; returns metrics or an error."""
    import numpy as np

    from simulator.scoring.scores import score_labels
    from pipeline.reading import read_points
    from simulator.truth import read_truth

    cfg = FIN_DEFAULTS if config_name == "3DFin defaults" else FIN_ORCHARD
    folder = work / "peers" / Path(block.las).stem
    folder.mkdir(parents=True, exist_ok=True)
    xyz, info = read_points(block.las)
    pts = folder / "points.npy"
    np.save(pts, xyz)
    del xyz
    out = folder / f"labels-{config_name.replace(' ', '_')}.npz"
    out.unlink(missing_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    t = time.perf_counter()
    try:
        with open(folder / "peer.log", "w") as logf, one_core() as core:
            proc = subprocess.run(
                [status["python"], str(SCRIPT), str(pts), str(out), json.dumps(cfg)],
                stdout=logf, stderr=subprocess.STDOUT, timeout=timeout, env=env, preexec_fn=pinned_to(core),
            )
    except subprocess.TimeoutExpired:
        return {"error": f"did not finish within {timeout:.0f} s"}
    wall = time.perf_counter() - t
    if proc.returncode != 0 or not out.exists():
        log_text = (folder / "peer.log").read_text(errors="replace")
        if "need at least one array to concatenate" in log_text:
            return {"error": "found no stem in the stripe (dendromatics: ValueError: need at least one array to concatenate)"}
        return {"error": f"exit {proc.returncode}: {_tail(log_text, 1)}"}
    res = np.load(out)
    truth, true_trunks = read_truth(block.truth)
    stems = res["stems"]
    found = stems[:, 1:3] + np.asarray(info.origin[:2]) if len(stems) else np.zeros((0, 2))
    metrics = score_labels(
        true_tree_id=truth["tree_id"], true_is_wood=truth["is_wood"], true_trunks=true_trunks,
        pred_tree_id=res["tree_id"], pred_is_wood=np.zeros(len(res["tree_id"]), bool), found_trunks=found,
    )
    metrics["wood_f1"] = float("nan")  # dendromatics has no wood/leaf output
    metrics["seconds"] = float(res["seconds"])
    metrics["wall_s"] = wall
    pts.unlink(missing_ok=True)
    return metrics
