"""Benchmarks of pgvd and the fleet on real data; ``python3 -m bench --help`` lists them.

The benchmarks a user runs sit here, the analyses behind the merge's design in
:mod:`bench.studies`, and the pair and trajectory generators they share in :mod:`bench.data`.
"""
