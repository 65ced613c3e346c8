"""Benchmark suite: ``python -m bench [--quick]`` writes ``bench/results.md``, PNG plots
next to it, and the section of docs/benchmarks.md between ``<!-- bench:start -->`` and ``<!-- bench:end -->``.

Every figure in the results comes from the run that writes them. Measurements run in
fresh subprocesses (:mod:`bench.measure`) so that timings and peak memory of one do
not leak into another. Not part of the test suite: nothing here asserts a time.
"""
