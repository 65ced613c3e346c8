"""Time kernels of this tree against the same kernels at an earlier commit, on one block.

``python -m bench.kernel_revisions BLOCK.laz [--rev 46a6c22] [--repeat 7]``

Runs the pipeline once on the block to capture each kernel's inputs, loads the listed
modules as they were at ``--rev`` (``git show``; their own imports resolve to this
tree), checks that both versions give the same arrays byte for byte, and prints the
CPU seconds of each (the least of ``--repeat`` runs, the two versions alternating, so
that other processes on the machine weigh on both alike).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: (module, function) timed, and the call site whose inputs are captured
KERNELS = [
    ("pipeline.voxels", "voxelize"),
    ("pipeline.nearby", "near_centres"),
    ("pipeline.nearby", "CellIndex"),
    ("pipeline.refine", "rival_distance"),
    ("pipeline.segment", "trunk_feet"),
    ("pipeline.metrics", "trunk_circles"),
    ("pipeline.blockresult", "block_result"),
    ("pipeline.metrics", "tree_partials"),
    ("pipeline.canopy", "canopy_cells"),
    ("pipeline.coverage", "stem_cells"),
]


def _old_module(name: str, rev: str, folder: Path):
    source = subprocess.run(["git", "show", f"{rev}:{name.replace('.', '/')}.py"], check=True, capture_output=True,
                            text=True).stdout
    path = folder / f"{name.replace('.', '_')}_{rev}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _flat(out) -> list[np.ndarray]:
    """The arrays of a kernel's result, whatever its shape (tuples, dataclasses, lists)."""
    if isinstance(out, np.ndarray):
        return [out]
    if isinstance(out, (tuple, list)):
        return [a for o in out for a in _flat(o)]
    if hasattr(out, "__dict__"):
        return [a for o in vars(out).values() for a in _flat(o)]
    if hasattr(out, "__dataclass_fields__"):
        return [a for f in out.__dataclass_fields__ for a in _flat(getattr(out, f))]
    return [np.asarray(out)] if out is not None and not callable(out) else []


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("block")
    p.add_argument("--rev", default="46a6c22")
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--only", nargs="*", help="these kernels only (function names)")
    args = p.parse_args(argv)

    from pipeline.params import PipelineParams
    from pipeline.reading import read_points
    from workers.tasks import process, summarise

    captured: dict[tuple[str, str], tuple] = {}
    new = {}
    for mod_name, fn in KERNELS:
        mod = importlib.import_module(mod_name)
        f = getattr(mod, fn)
        new[(mod_name, fn)] = f

        def spy(*a, _key=(mod_name, fn), _f=f, **k):
            captured.setdefault(_key, (a, k))  # the first call's inputs
            return _f(*a, **k)

        for other in list(sys.modules.values()):  # every module that imported it by name
            if getattr(other, "__name__", "").startswith(("pipeline", "workers")) and getattr(other, fn, None) is f:
                setattr(other, fn, spy)
    xyz, _ = read_points(args.block)
    params = PipelineParams()
    result = process(xyz, params, Path(args.block).name)
    summarise(0, xyz, np.ones(len(xyz), bool), result, None, (0.0, 0.0, 0.0), params)
    for key, f in new.items():  # put the originals back
        for other in list(sys.modules.values()):
            if getattr(other, "__name__", "").startswith(("pipeline", "workers")) and getattr(getattr(other, key[1], None), "__name__", "") == "spy":
                setattr(other, key[1], f)

    print(f"{len(xyz):,} points; CPU seconds, least of {args.repeat}, {args.rev} -> this tree")
    with tempfile.TemporaryDirectory() as tmp:
        for key in KERNELS:
            if args.only and key[1] not in args.only:
                continue
            if key not in captured:
                print(f"{key[1]:16s} not called")
                continue
            a, k = captured[key]
            old = getattr(_old_module(key[0], args.rev, Path(tmp)), key[1])
            x, y = _flat(old(*a, **k)), _flat(new[key](*a, **k))
            same = len(x) == len(y) and all(u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes()
                                            for u, v in zip(x, y))
            best = {"old": float("inf"), "new": float("inf")}
            for _ in range(args.repeat):
                for side, f in (("old", old), ("new", new[key])):
                    t = time.process_time()
                    f(*a, **k)
                    best[side] = min(best[side], time.process_time() - t)
            print(f"{key[1]:16s} {best['old']:.4f} -> {best['new']:.4f}  {'identical' if same else 'DIFFERENT'}", flush=True)


if __name__ == "__main__":
    main()
