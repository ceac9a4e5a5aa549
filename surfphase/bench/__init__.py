"""Benchmarks that judge the whole workflow (``surfphase bench ...``).

* :mod:`surfphase.bench.accuracy` — the varied synthetic preset through the default
  workflow, scored against the truth beside the classical two-view baseline.
* :mod:`surfphase.bench.determinism` — one campaign run twice, idle and under load,
  compared byte for byte with :mod:`surfphase.bench.compare`.
"""
