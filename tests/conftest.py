"""Shared test set-up: two CPU threads, as on the development machine and in CI.

`make test` runs the suite on two pytest-xdist workers (``-n 2 --dist loadfile``: a
test file's tests stay on one worker, so module fixtures are built once). Each worker's
OpenMP threads sleep when idle (``OMP_WAIT_POLICY=PASSIVE``, as ``import surfphase``
sets for the stages), so the two workers do not spin against each other.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A tiny synthetic campaign with two sessions on one rig (generated once per test
    module; the workflow tests' campaign, test_workflow_run and test_workflow_faults)."""
    from surfphase.synth.campaign import write_campaign

    out = tmp_path_factory.mktemp("tiny") / "campaign"
    write_campaign(out, preset="tiny", seed=3, sessions=2)
    return out
