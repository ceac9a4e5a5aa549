"""Benchmarks that judge the whole workflow against ground truth (``surfphase bench ...``).

:mod:`surfphase.bench.accuracy` — the varied synthetic preset through the default
workflow, scored against the truth beside the classical two-view baseline.
"""
