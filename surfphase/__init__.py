"""SurfPhase: 3D bubble interfaces and metric velocities from synchronized high-speed videos.

Importing the package sets two threading defaults, before PyTorch or numba start their
thread pools (``os.environ.setdefault``: a value the user exported wins):

* ``OMP_WAIT_POLICY=PASSIVE``: PyTorch's OpenMP workers sleep between parallel regions
  instead of spinning. Spinning workers make a shared CPU (a lab workstation, a cluster
  node, numba's own workers) many times slower — a fit beside one CPU-bound process
  took 20× longer with two spinning threads. The thread count is not changed, so
  results stay bit-for-bit what they are for that count.
* ``NUMBA_THREADING_LAYER=workqueue``: the fused rasterizer's kernels
  (:mod:`surfphase.render.fused`) run on numba's workqueue pool, whose idle workers
  wait on a condition variable (never spin) and which loads no second OpenMP runtime
  beside PyTorch's. It does not allow nested parallel kernels or concurrent calls from
  several Python threads; surfphase makes neither.

Both only take effect when ``surfphase`` is imported before ``torch`` and ``numba``
(``python -m surfphase`` and the workflow's rules always do).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

__version__ = "0.1.0"
