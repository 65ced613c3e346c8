"""``orchard evaluate``: score a processed block against a simulation's ground truth."""

from __future__ import annotations

import argparse
import json
import math

from pipeline.errors import ParameterError

NAME = "evaluate"
HELP = (
    "Score the result of `orchard process` on a generated block against its truth file: trunk "
    "precision/recall/F1 (one-to-one matching within --match-distance) and mean distance of the "
    "matches, V-measure of the tree labels and wood F1, both on the points that truly belong to a tree, "
    "and the trunk diameter error of the matched trees (truth at 0.3 m above the base)."
)

_ROWS = [
    ("trunk_precision", "trunk precision", "{:.3f}"),
    ("trunk_recall", "trunk recall", "{:.3f}"),
    ("trunk_f1", "trunk F1", "{:.3f}"),
    ("trunk_mean_distance", "trunk mean distance [m]", "{:.3f}"),
    ("trunk_tp", "trunks matched (TP)", "{:d}"),
    ("trunk_fp", "false trunks (FP)", "{:d}"),
    ("trunk_fn", "missed trunks (FN)", "{:d}"),
    ("v_measure", "V-measure (tree points)", "{:.3f}"),
    ("homogeneity", "  homogeneity", "{:.3f}"),
    ("completeness", "  completeness", "{:.3f}"),
    ("wood_f1", "wood F1 (tree points)", "{:.3f}"),
    ("wood_precision", "  wood precision", "{:.3f}"),
    ("wood_recall", "  wood recall", "{:.3f}"),
    ("address_accuracy", "address accuracy (row, position)", "{:.3f}"),
    ("n_correct", "  trees at their true address", "{:d}"),
    ("gap_precision", "empty-slot precision", "{:.3f}"),
    ("gap_recall", "empty-slot recall", "{:.3f}"),
    ("young_true", "replants (true)", "{:d}"),
    ("young_found", "  flagged young", "{:d}"),
    ("young_correct", "  flagged and true", "{:d}"),
    ("trunk_diameter_mae", "trunk diameter error [m]", "{:.3f}"),
    ("trunk_diameter_bias", "  bias (measured - true) [m]", "{:+.3f}"),
    ("trunk_diameter_n", "  trees compared", "{:d}"),
    ("trunk_diameter_unmeasured", "  not measurable", "{:d}"),
    ("n_true_trees", "true trees", "{:d}"),
    ("n_found_trees", "found trees", "{:d}"),
    ("n_points", "points", "{:,d}"),
    ("n_tree_points", "true tree points", "{:,d}"),
    ("n_missing_points", "points missing from the result", "{:,d}"),
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--truth", required=True, metavar="TRUTH.parquet", help="truth file written by `orchard simulate`")
    parser.add_argument("--result", required=True, metavar="DIR", help="output folder of `orchard process` (trees.parquet, points.parquet)")
    parser.add_argument("--match-distance", type=float, default=1.0, metavar="M", help="largest distance of a trunk match [m] (default 1.0)")
    parser.add_argument("--json", action="store_true", help="print the metrics as one JSON object instead of a table")


def format_table(metrics: dict) -> str:
    """The metrics as a two-column text table."""
    width = max(len(label) for _, label, _ in _ROWS)
    lines = []
    for key, label, fmt in _ROWS:
        if key not in metrics:
            continue
        value = metrics[key]
        text = "n/a" if isinstance(value, float) and math.isnan(value) else fmt.format(value)
        lines.append(f"{label:<{width}}  {text:>10}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if not (args.match_distance > 0 and math.isfinite(args.match_distance)):
        raise ParameterError(f"--match-distance must be a positive number of metres, not {args.match_distance}")
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from simulator.scoring.result import evaluate_result  # imported here: `orchard --help` needs no scipy

    metrics = evaluate_result(args.truth, args.result, match_distance=args.match_distance)
    if args.json:
        print(json.dumps({k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in metrics.items()}))
    else:
        print(format_table(metrics))
    return 0
