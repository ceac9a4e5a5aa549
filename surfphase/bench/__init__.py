"""Benchmarks (``surfphase bench ...``); the stage packages import none of them.

* :mod:`surfphase.bench.accuracy` — the varied synthetic preset through the default
  workflow, scored against the truth beside the classical two-view baseline.
* :mod:`surfphase.bench.determinism` — one campaign run twice, idle and under load,
  compared byte for byte with :mod:`surfphase.bench.compare`.
* :mod:`surfphase.bench.fit` — ``surfphase bench fit``: the stage-1 fit on the demo
  session, with and without bubble guidance, against the ground truth.
* :mod:`surfphase.bench.fit_stage2` — ``surfphase bench fit2``: a stage-2 step's cost
  against a stage-1 step's.
* :mod:`surfphase.bench.mesh` — ``surfphase bench mesh``: Chamfer distance of the meshes
  to the true meshes.
"""
