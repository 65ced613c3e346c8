"""``orchard convert``: a PLY, PCD, E57 or text point file written as LAZ (the file
``orchard process`` and the service make of such an input before processing it)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import ParameterError

NAME = "convert"
HELP = (
    "Write a PLY (binary or ascii), PCD (ascii, binary, binary_compressed), E57 or text (x y z) point file as "
    "LAZ at millimetre precision, in the same point order (points with a non-finite coordinate are left out). "
    "The format is read from the file's first bytes. Exit codes: 0 done, 2 bad input or options (docs/inputs.md)."
)


def add_input_options(parser) -> None:
    """--crs and --columns: what a non-LAS input's file may not say."""
    parser.add_argument("--crs", default=None, metavar="EPSG:NNNN",
                        help="CRS of the points of a PLY, PCD or text file (which store none; an E57 file's own, if any, is used otherwise)")
    parser.add_argument("--columns", default=None, metavar="NAMES",
                        help="a text file's columns in order, comma-separated, among them x, y and z (e.g. x,y,z,intensity); "
                             "default: its header line, else the first three columns are x y z")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="INPUT", help="PLY, PCD, E57 or text point file")
    parser.add_argument("--out", required=True, metavar="FILE.laz", help="the LAZ file to write (refused if it exists)")
    add_input_options(parser)
    parser.add_argument("--reader", choices=("own", "pdal"), default="own",
                        help="the project's readers (default) or PDAL's (needs PDAL's Python bindings; docs/pdal.md)")


def run(args: argparse.Namespace) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.formats.convert import parse_crs_option, to_laz
    from pipeline.lasheader import check_file

    out = Path(args.out)
    if out.suffix.lower() != ".laz":
        raise ParameterError(f"--out {out} must end in .laz")
    if out.exists():
        raise ParameterError(f"--out {out} exists; give a new file name")
    if not out.parent.is_dir():
        raise ParameterError(f"--out {out}: the folder {out.parent} does not exist")
    crs = parse_crs_option(args.crs)
    src = Path(args.input)
    if not src.is_file():
        check_file(src)  # says what it is instead: no such file, a folder, a device
    done = to_laz(src, out, crs_epsg=crs, columns=args.columns, reader=args.reader)
    left = f" ({done.n_dropped} with a non-finite coordinate left out)" if done.n_dropped else ""
    print(f"{done.n_points} points{left} from {done.format.upper()} {src.name} -> {out}"
          f"{'' if done.has_crs else ' (no CRS: give --crs EPSG:NNNN)'}", file=sys.stderr)
    return 0
