"""Evaluation harness: the accuracy of a result against ground truth.

Not a kernel of the product: :mod:`~simulator.scoring.scores` holds the paper's
metrics on label arrays (generated blocks and labelled real trees alike),
:mod:`~simulator.scoring.addresses` the accuracy of row addresses and empty slots, and
:mod:`~simulator.scoring.result` scores a result folder against a truth file written by
:mod:`simulator.truth`.
"""
