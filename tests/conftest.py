"""Shared test set-up: two CPU threads, as on the development machine and in CI.

`make test` runs the suite on two pytest-xdist workers (``-n 2 --dist loadfile``: a
test file's tests stay on one worker, so module fixtures are built once). Each worker's
OpenMP threads sleep when idle (``OMP_WAIT_POLICY=PASSIVE``, as ``import surfphase``
sets for the stages), so the two workers do not spin against each other.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
