"""Evaluation harness: the accuracy of a result against ground truth.

Not a kernel of the product: :mod:`~pipeline.evaluation.scores` holds the paper's
metrics on label arrays (generated blocks and labelled real trees alike),
:mod:`~pipeline.evaluation.addresses` the accuracy of row addresses and empty slots, and
:mod:`~pipeline.evaluation.result` scores a result folder against a truth file written by
:mod:`pipeline.synthetic.truth`.
"""
