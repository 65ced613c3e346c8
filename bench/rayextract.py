"""Ours against raycloudtools' ``rayextract trees`` on the same generated blocks.

    python -m bench.rayextract --rayextract PATH [--scenes default,hedgerows] [--seeds 0,1] [--work-dir DIR]

raycloudtools (CSIRO, C++) is the reference the project measures itself against: its
``rayextract trees cloud.ply ground_mesh.ply`` finds trunks without priors and segments
every point by shortest paths from the ground. It is not on PyPI or in Debian, so this
module does not install it: give the path of a ``rayextract`` binary built from its
sources (github.com/csiro-robotics/raycloudtools; it needs Eigen and libnabo).

``bench/build_rayextract.sh`` builds one from the two source trees.

For each block of the chosen scene groups (``SCENES``: ``default``, the two accuracy
settings of :mod:`bench.oracles`; ``hedgerows``, tall spindle at 1.0 m and 1.5 m in the
row with 3.5 m between rows and hedge at 1.35 m x 4 m; ``mobile``, the hedgerow blocks of
:mod:`bench.density` at a mobile scan's density) and each evaluation seed 0..N-1:

- **ours**: the block's LAZ through :func:`workers.job.run_job` (LAZ in, Parquet out),
  scored by :func:`simulator.scoring.result.evaluate_result`;
- **rayextract trees**, defaults: the same points, in the same order, written as a ray
  cloud (``cloud.ply``: float x, y, z relative to the block's local origin, a time per
  point, and a 1 m vertical ray per point in the normal field, as
  ``rayimport cloud.laz ray 0,0,-1`` makes for a cloud without a trajectory; the tool's
  tree segmentation does not use the ray starts), and the simulator's *true* ground as
  the mesh (``mesh.ply``, 0.25 m triangles; the tool's own ``rayextract terrain``
  would have to estimate it). Its ``cloud_segmented.ply`` gives one colour per tree
  (black: no tree) in the input order; its ``cloud_trees.txt`` gives each tree's base.

Then the same for real trees (``--adtree``): the row of four AdTree scans of
:func:`bench.real_data.adtree_row` at each crown overlap, written to a LAZ for ours and
given its flat ground plane as the mesh for rayextract (read from ``../shared/data/real/``;
left out with a note when that folder is missing).

Both are scored by :func:`simulator.scoring.scores.score_labels` on the same truth: trunk F1
with one-to-one matching within half the in-row spacing, at most 1 m (as
:mod:`bench.hedgerows`), v-measure on true tree points. ``rayextract`` has no
per-point wood flag, so wood F1 is left out. Seconds are wall-clock for the whole run of
each (reading, processing, writing) on one core: ours in a fresh process
(:func:`bench.isolation.measure`) pinned to one core (the LAZ decoder and the Parquet
writer would otherwise use every core), after one untimed warm-up run (as a dask worker
runs it), or with ``--whole-command`` as a whole ``orchard process`` run in a fresh process
(start-up, imports, report and map included); rayextract as a fresh process pinned to the same core, with
``OMP_NUM_THREADS=1``; the median of ``--repeats`` timed runs of each (default 3). Each
tool's peak RSS is its own process's high-water
mark (``getrusage``; ours includes the interpreter and its imports), also given per
input point. Prints a Markdown table, then per scene the ratios rayextract / ours of
time and of peak memory.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import threading
import time
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

from bench.blocks import make_block
from bench.hedgerows import match_distance
from bench.isolation import SINGLE_THREAD_ENV, measure, one_core, pinned_to
from bench.oracles import SETTINGS
from bench.real_data import REAL, adtree_row
from simulator.scoring.result import evaluate_result
from simulator.scoring.scores import score_labels
from pipeline.reading import read_points
from simulator.orchard import GROUND, LEAF, Orchard
from simulator.simparams import SimulationParams
from simulator.terrain import ground_height
from simulator.truth import read_truth, write_simulation

MESH_CELL = 0.25
"""Edge of the ground mesh's grid cells [m]."""

RAY_LENGTH = 1.0
"""Length of the vertical ray written for each point [m]."""

SCENES: dict[str, dict[str, dict]] = {
    "default": SETTINGS,
    "hedgerows": {
        "tall spindle 1.0 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=14, spacing=1.0, row_spacing=3.5),
        "tall spindle 1.5 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=12, spacing=1.5, row_spacing=3.5),
        "hedge 1.35 m × 4 m": dict(form="hedge", rows=2, trees_per_row=12, spacing=1.35, row_spacing=4.0),
    },
    # bench.density's blocks: `density` is its mobile_density() for the layout (seed 0)
    "mobile": {
        "tall spindle 1.0 m × 3.5 m, mobile density": dict(form="spindle", rows=2, trees_per_row=12, spacing=1.0,
                                                          row_spacing=3.5, density=3.047),
        "hedge 1.35 m × 4 m, mobile density": dict(form="hedge", rows=2, trees_per_row=10, spacing=1.35,
                                                  row_spacing=4.0, density=3.077),
    },
    # a few trees of a hedgerow at a lower density: 0.27 and 0.32 M points, where fixed costs weigh
    "small": {
        "tall spindle 1.0 m × 3.5 m, 2 × 6 trees, 0.27 M points": dict(form="spindle", rows=2, trees_per_row=6,
                                                                      spacing=1.0, row_spacing=3.5, density=0.45),
        "tall spindle 1.5 m × 3.5 m, 2 × 5 trees, 0.32 M points": dict(form="spindle", rows=2, trees_per_row=5,
                                                                      spacing=1.5, row_spacing=3.5, density=0.55),
    },
}
"""Scene groups of ``--scenes``: setting name -> ``SimulationParams`` fields (no seed).
``mobile`` holds the hedgerow blocks of :mod:`bench.density` (2.4-2.7 M points), ``small``
two spindle hedgerows of 0.27 and 0.32 M points."""


def write_ray_cloud(path: Path, xyz: np.ndarray) -> None:
    """Write points (n, 3), local coordinates [m], as a raycloudtools ray cloud PLY.

    Each point is a ray end; its start, ``RAY_LENGTH`` above it, is stored as the vector
    start - end in the normal field (``nx``, ``ny``, ``nz``), as raycloudtools does.
    Times count up in input order; colours are grey with alpha 255 (a bounded ray: a
    real return).
    """
    from plyfile import PlyData, PlyElement

    n = len(xyz)
    v = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("time", "<f8"), ("nx", "<f4"), ("ny", "<f4"),
                           ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])
    v["x"], v["y"], v["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    v["time"] = np.arange(n, dtype=np.float64) * 1e-5
    v["nz"] = RAY_LENGTH
    v["red"] = v["green"] = v["blue"] = 128
    v["alpha"] = 255
    PlyData([PlyElement.describe(v, "vertex")], byte_order="<").write(str(path))


def write_ground_mesh(path: Path, ground: Callable[[np.ndarray, np.ndarray], np.ndarray], lo: np.ndarray,
                      hi: np.ndarray) -> int:
    """Write the ground surface ``ground(x, y) -> z`` (local [m]) over the XY box
    ``lo``-``hi`` as a triangle-mesh PLY in local coordinates; returns the number of
    triangles."""
    from plyfile import PlyData, PlyElement

    gx = np.arange(lo[0] - MESH_CELL, hi[0] + 2 * MESH_CELL, MESH_CELL)
    gy = np.arange(lo[1] - MESH_CELL, hi[1] + 2 * MESH_CELL, MESH_CELL)
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    Z = np.broadcast_to(np.asarray(ground(X.ravel(), Y.ravel()), dtype=np.float64), (X.size,))
    verts = np.zeros(X.size, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    verts["x"], verts["y"], verts["z"] = X.ravel(), Y.ravel(), Z
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.c_[a, b, c], np.c_[a, c, d]]).astype(np.int32)
    faces = np.zeros(len(tri), dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = tri
    PlyData([PlyElement.describe(verts, "vertex"), PlyElement.describe(faces, "face")], byte_order="<").write(str(path))
    return len(tri)


def read_segmented(path: Path, xyz: np.ndarray, tolerance: float = 1e-3) -> np.ndarray:
    """Tree labels (n,) int64 from rayextract's ``_segmented.ply``: one label per colour,
    0 for black (no tree). The file must hold the input's points in the input's order."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    if len(v) != len(xyz):
        raise ValueError(f"{path.name} has {len(v)} points, the input {len(xyz)}: the order cannot be matched")
    got = np.c_[v["x"], v["y"], v["z"]].astype(np.float64)
    worst = float(np.abs(got - xyz).max()) if len(xyz) else 0.0
    if worst > tolerance:
        raise ValueError(f"{path.name} is not in the input's order (a point moved {worst:.3g} m)")
    rgb = (v["red"].astype(np.int64) << 16) | (v["green"].astype(np.int64) << 8) | v["blue"].astype(np.int64)
    _, labels = np.unique(rgb, return_inverse=True)
    labels = labels.astype(np.int64) + 1
    labels[rgb == 0] = 0
    return labels


def read_tree_bases(path: Path) -> np.ndarray:
    """Base (first segment's x, y, z) of every tree in rayextract's ``_trees.txt``: (k, 3)."""
    bases = []
    for line in path.read_text().splitlines():
        text = line.strip()
        if not text or not (text[0].isdigit() or text[0] in "-."):
            continue  # the comment and the column-name lines
        bases.append([float(s) for s in text.replace(",", " ").split()[:3]])
    return np.asarray(bases, dtype=np.float64).reshape(-1, 3)


def _run_pinned(cmd: list[str], cwd: Path, env: dict, core: int, timeout: float) -> tuple[int, str, int]:
    """Run ``cmd`` pinned to ``core``; returns (exit code, its output, its own peak RSS
    [bytes]). ``os.wait4`` gives the child's own high-water mark, which
    ``RUSAGE_CHILDREN`` would mix with every earlier child's."""
    with open(cwd / "rayextract.log", "w+") as log:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT,
                                preexec_fn=pinned_to(core))
        timer = threading.Timer(timeout, proc.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            timer.cancel()
        proc.returncode = code = os.waitstatus_to_exitcode(status)
        log.seek(0)
        return code, log.read(), usage.ru_maxrss * 1024  # Linux: kB


def run_rayextract(binary: str, folder: Path, xyz: np.ndarray, ground: Callable[[np.ndarray, np.ndarray], np.ndarray],
                   *, repeats: int = 1, timeout: float = 3600.0) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Write the ray cloud of ``xyz`` (local [m]) and the mesh of ``ground`` (see
    :func:`write_ground_mesh`) into ``folder``, run ``rayextract trees`` on them
    ``repeats`` times; returns (labels (n,), tree bases (k, 3) in local coordinates,
    median wall time [s], largest peak RSS of a run [bytes])."""
    folder.mkdir(parents=True, exist_ok=True)
    cloud, mesh = folder / "cloud.ply", folder / "mesh.ply"
    write_ray_cloud(cloud, xyz)
    write_ground_mesh(mesh, ground, xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0))
    env = dict(os.environ, **SINGLE_THREAD_ENV)
    walls, peak = [], 0
    with one_core() as core:
        for _ in range(max(1, repeats)):
            t = time.perf_counter()
            code, output, rss = _run_pinned([binary, "trees", cloud.name, mesh.name], folder, env, core, timeout)
            walls.append(time.perf_counter() - t)
            peak = max(peak, rss)
            if code != 0:
                tail = "\n".join(output.strip().splitlines()[-5:])
                raise RuntimeError(f"rayextract exited {code}: {tail}")
    labels = read_segmented(folder / "cloud_segmented.ply", xyz)
    return labels, read_tree_bases(folder / "cloud_trees.txt"), statistics.median(walls), peak


def _run_ours(las: str, result_dir: Path, repeats: int = 1) -> tuple[float, int]:
    """Our job on ``las`` (LAZ in, Parquet out) in a fresh process on one core
    (:func:`bench.isolation.measure`): one untimed warm-up run, as in the stand benchmark,
    then ``repeats`` timed runs; returns (their median wall time [s], the process's peak
    RSS [bytes]). The last run's outputs are left in ``result_dir / "run{repeats-1}"``."""
    shutil.rmtree(result_dir, ignore_errors=True)
    r = measure({"kind": "job", "input": las, "out": str(result_dir), "workers": 0, "warmup": 1,
                 "repeats": max(1, repeats)}, timeout=3600)
    return statistics.median(run["wall_s"] for run in r["runs"]), int(r["main_maxrss"])


def _run_command(las: str, result_dir: Path, repeats: int = 1) -> tuple[float, int]:
    """``orchard process`` on ``las`` as a fresh process pinned to one core, ``repeats``
    times, start-up, imports, report and map included (a grower's run); returns (the
    median wall time [s], the largest peak RSS of a run [bytes]). The last run's outputs
    are left in ``result_dir / "run{repeats-1}"``."""
    shutil.rmtree(result_dir, ignore_errors=True)
    result_dir.mkdir(parents=True)
    env = dict(os.environ, **SINGLE_THREAD_ENV)
    walls, peak = [], 0
    with one_core() as core:
        for r in range(max(1, repeats)):
            cmd = [sys.executable, "-m", "service.cli", "process", os.path.abspath(las), "--out", f"run{r}"]
            t = time.perf_counter()
            code, output, rss = _run_pinned(cmd, result_dir, env, core, timeout=3600.0)
            walls.append(time.perf_counter() - t)
            peak = max(peak, rss)
            if code != 0:
                raise RuntimeError(f"orchard process exited {code}: {output.strip().splitlines()[-1:]}")
    return statistics.median(walls), peak


def compare_scene(binary: str, work: Path, las: str, truth_path: str,
                  ground: Callable[[np.ndarray, np.ndarray], np.ndarray], repeats: int = 1,
                  match: float = 1.0, whole_command: bool = False) -> dict:
    """Ours and rayextract on one block with its truth file (``simulator.truth``'s
    format): {method: scores, seconds and peak RSS [bytes]}. ``ground(x, y) -> z`` is the
    true ground in the block's absolute coordinates [m]; trunks match within ``match`` [m]."""
    truth, true_trunks = read_truth(truth_path)
    name = Path(las).stem
    result_dir = work / "rayextract-results" / name
    seconds, rss = (_run_command if whole_command else _run_ours)(las, result_dir, repeats)
    ours = evaluate_result(truth_path, str(result_dir / f"run{max(1, repeats) - 1}"), match_distance=match)
    methods = {"ours": dict(ours, seconds=seconds, found=ours["n_found_trees"], peak_rss=rss)}

    xyz, info = read_points(las)
    origin = np.asarray(info.origin, dtype=np.float64)
    labels, bases, seconds, rss = run_rayextract(binary, work / "rayextract-runs" / name, xyz,
                                                 lambda x, y: ground(x + origin[0], y + origin[1]) - origin[2],
                                                 repeats=repeats)
    scores = score_labels(
        true_tree_id=truth["tree_id"], true_is_wood=truth["is_wood"], true_trunks=true_trunks,
        pred_tree_id=labels, pred_is_wood=np.zeros(len(labels), bool), found_trunks=bases + origin,
        match_distance=match,
    )
    methods["rayextract trees"] = dict(scores, seconds=seconds, found=scores["n_found_trees"], peak_rss=rss)
    return methods


def compare_block(binary: str, work: Path, setting: str, seed: int, repeats: int = 1,
                  sim: dict | None = None, whole_command: bool = False) -> dict:
    """Ours and rayextract on one generated block of ``sim`` (simulator fields; default
    ``SETTINGS[setting]``): {method: scores}, plus block facts."""
    sim = SETTINGS[setting] if sim is None else sim
    params = SimulationParams(seed=seed, **sim)
    block = make_block(work, f"rayextract-s{seed}", params)
    methods = compare_scene(binary, work, block.las, block.truth, partial(ground_height, params), repeats,
                            match=match_distance(params.spacing), whole_command=whole_command)
    return {"setting": setting, "seed": seed, "n_points": block.n_points, "n_trees": block.n_trees, "methods": methods}


def compare_adtree(binary: str, work: Path, overlap: float, repeats: int = 1, whole_command: bool = False) -> dict:
    """Ours and rayextract on the real-tree row of :func:`bench.real_data.adtree_row`
    (four AdTree scans, crowns overlapping by ``overlap`` of their summed radii, on a flat
    ground plane at z = 0), written as a block with its exact tree ids as the truth. The
    scans carry no wood labels: ``is_wood`` is all False there (wood F1 is not reported)."""
    xyz, tid, bases = adtree_row(overlap=overlap)
    row = Orchard(xyz=xyz, tree_id=tid, is_wood=np.zeros(len(xyz), bool),
                  kind=np.where(tid > 0, LEAF, GROUND).astype(np.uint8), trunks=bases,
                  trunk_radius=np.full(len(bases), np.nan))
    folder = work / "blocks"
    folder.mkdir(parents=True, exist_ok=True)
    las, truth = folder / f"adtree-row-{overlap:g}.laz", folder / f"adtree-row-{overlap:g}.truth.parquet"
    write_simulation(row, str(las), str(truth))
    methods = compare_scene(binary, work, str(las), str(truth), lambda x, y: np.zeros(len(x)), repeats,
                            whole_command=whole_command)
    return {"setting": f"AdTree row (real trees), overlap {overlap:g}", "seed": "-", "n_points": len(xyz),
            "n_trees": len(bases), "methods": methods}


def table(rows: list[dict]) -> str:
    """Markdown table: one line per scene and method, then one per scene with the
    ratios rayextract / ours of wall time and of peak RSS."""
    lines = ["| setting | seed | points | method | trunks found (true) | trunk F1 | v-measure | seconds | peak RSS [MiB] "
             "| bytes / point |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for name, m in r["methods"].items():
            lines.append(f"| {r['setting']} | {r['seed']} | {r['n_points']:,} | {name} | {m['found']} ({r['n_trees']}) "
                         f"| {m['trunk_f1']:.2f} | {m['v_measure']:.3f} | {m['seconds']:.1f} "
                         f"| {m['peak_rss'] / 2**20:,.0f} | {m['peak_rss'] / max(r['n_points'], 1):,.0f} |")
    lines += ["", "| setting | seed | time rayextract / ours | peak RSS rayextract / ours |", "|---|---|---|---|"]
    for r in rows:
        ours, other = r["methods"]["ours"], r["methods"]["rayextract trees"]
        lines.append(f"| {r['setting']} | {r['seed']} | {other['seconds'] / ours['seconds']:.2f} "
                     f"| {other['peak_rss'] / ours['peak_rss']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.rayextract", description=__doc__.splitlines()[0])
    p.add_argument("--rayextract", required=True, help="path of a rayextract binary (raycloudtools)")
    p.add_argument("--scenes", default="default",
                   help=f"scene groups, comma-separated, of: {', '.join(SCENES)} (default: default)")
    p.add_argument("--seeds", default="0,1", help="evaluation seeds, comma-separated (default 0,1)")
    p.add_argument("--work-dir", type=Path, default=Path(os.environ.get("ORCHARD_BENCH_WORK", "/tmp/orchard-bench")),
                   help="folder for the blocks and both tools' outputs (default /tmp/orchard-bench)")
    p.add_argument("--adtree", default="0.8,1.0",
                   help="also the row of four real AdTree trees (bench.real_data) at these crown overlaps, "
                        "comma-separated fractions of the summed crown radii; '' for none (default 0.8,1.0)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs of each tool per scene; the median is reported (default 3)")
    p.add_argument("--whole-command", action="store_true",
                   help="time ours as a whole `orchard process` run in a fresh process (start-up, imports, report "
                        "and map included) instead of the job after a warm-up run")
    args = p.parse_args(argv)
    binary = shutil.which(args.rayextract) or args.rayextract
    if not (os.path.isfile(binary) and os.access(binary, os.X_OK)):
        print(f"error: {args.rayextract} is not an executable file", file=sys.stderr)
        return 2
    groups = [g.strip() for g in args.scenes.split(",") if g.strip()]
    unknown = [g for g in groups if g not in SCENES]
    if unknown:
        print(f"error: unknown scene group {', '.join(unknown)}; choose from {', '.join(SCENES)}", file=sys.stderr)
        return 2
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    rows = [compare_block(binary, args.work_dir, setting, seed, args.repeats, sim, args.whole_command)
            for g in groups for setting, sim in SCENES[g].items() for seed in seeds]
    overlaps = [float(o) for o in args.adtree.split(",") if o.strip()]
    if overlaps and not (REAL / "AdTree").is_dir():
        print(f"note: {REAL / 'AdTree'} is missing; the real-tree rows are left out", file=sys.stderr)
        overlaps = []
    rows += [compare_adtree(binary, args.work_dir, o, args.repeats, args.whole_command) for o in overlaps]
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
