"""``orchard simulate``: generate an orchard block (LAS/LAZ) and its ground truth (Parquet)."""

from __future__ import annotations

import argparse
import os
import typing

from pipeline.errors import InputError, ParameterError
from service.commands.options import base_type, metavar

NAME = "simulate"
HELP = (
    "Generate an orchard block as a mobile scanner driving the alleys sees it (branching trees with "
    "overlapping crowns - vase trees, tall spindles or a hedgerow wall - on sloping ground with grass, range "
    "fall-off, leaf occlusion, noise, ghosting, outliers, fence posts and a vehicle; optionally a trellis in "
    "every row, irrigation risers, leafless trees, missing trees, replants, ragged, curved or rotated rows), and its ground truth: tree id, "
    "wood flag and kind per point, trunk base, row and planting slot per tree, and the empty slots. "
    "Deterministic for a seed; large blocks are streamed to disk (docs/simulator.md)."
)

if typing.TYPE_CHECKING:
    from simulator.simparams import SimulationParams


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from simulator.simparams import SimulationParams  # imported here: `orchard --help` needs no numpy

    parser.add_argument("--out", required=True, metavar="BLOCK.laz", help="output point cloud (.laz compressed, .las plain)")
    parser.add_argument("--truth", required=True, metavar="TRUTH.parquet", help="output ground truth (one row per point; trunks in the metadata)")
    g = parser.add_argument_group("orchard parameters (lengths in metres)")
    for name, field in SimulationParams.model_fields.items():
        flag = "--" + name.replace("_", "-")
        kind = base_type(field.annotation)
        if typing.get_origin(kind) is tuple:  # per-slot lists of a series of captures: from Python only
            continue
        # a field without a fixed default says in its description what it defaults to
        help_text = field.description if field.default is None else f"{field.description} (default: {field.default})"
        if kind is bool:
            g.add_argument(flag, dest=f"s__{name}", action=argparse.BooleanOptionalAction, default=None, help=help_text)
        elif typing.get_origin(kind) is typing.Literal:
            g.add_argument(flag, dest=f"s__{name}", choices=list(typing.get_args(kind)), default=None, help=help_text)
        else:
            g.add_argument(flag, dest=f"s__{name}", type=kind, default=None, metavar=metavar(kind, field.description), help=help_text)


def params_from_args(args: argparse.Namespace) -> SimulationParams:
    """Validated parameters from the options given (unset options keep their defaults)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from simulator.simparams import SimulationParams

    given = {k[3:]: v for k, v in vars(args).items() if k.startswith("s__") and v is not None}
    return SimulationParams.model_validate(given)


def _check_crs(epsg: int) -> None:
    """ParameterError unless ``epsg`` names a projected CRS in metres (the simulator's
    coordinates are metres east and north)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    import pyproj

    try:
        crs = pyproj.CRS.from_epsg(epsg)
    except pyproj.exceptions.CRSError:
        raise ParameterError(f"--epsg {epsg}: not a known EPSG code") from None
    from pipeline.crs import crs_units_problem

    if not crs.is_projected or crs_units_problem(crs):
        raise ParameterError(f"--epsg {epsg} ({crs.name}): give a projected CRS in metres, e.g. a UTM zone (28356)")


def run(args: argparse.Namespace) -> int:
    params = params_from_args(args)
    _check_crs(params.epsg)
    for path in (args.out, args.truth):
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise InputError(f"folder {folder} does not exist: create it first")
        if os.path.isdir(path):
            raise InputError(f"{path} is a folder: give a file name")
    if not args.out.lower().endswith((".las", ".laz")):
        raise InputError(f"--out {args.out}: the file name must end in .las or .laz")
    if os.path.abspath(args.out) == os.path.abspath(args.truth):
        raise InputError("--out and --truth must be different files")
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from simulator.truth import write_simulation

    summary = write_simulation(params, args.out, args.truth)
    print(
        f"wrote {summary['n_points']:,} points, {summary['n_trees']} {params.form} trees "
        f"({params.rows} rows x {params.trees_per_row} slots, EPSG:{summary['crs_epsg']}, seed {params.seed}) "
        f"to {args.out}; truth in {args.truth}"
    )
    return 0
