"""Shared test set-up: one CPU thread per worker.

`make test` runs the suite on two pytest-xdist workers (``-n 2 --dist loadfile``: a
test file's tests stay on one worker, so module fixtures are built once), which fill
the two cores of the development machine and of CI. Each worker computes on one thread
(``OMP_NUM_THREADS=1``; the processes it starts inherit it, and Snakemake jobs get the
threads their rule asks for): two threads per worker, four on two cores, made the
whole suite slower (CHANGELOG.md, session 46). The tests that are about threads set
their own count (the determinism benchmark's ``threads: 2``).
OpenMP threads sleep when idle (``OMP_WAIT_POLICY=PASSIVE``, as ``import surfphase``
sets for the stages).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A tiny synthetic campaign with two sessions on one rig (generated once per test
    module; the workflow tests' campaign, test_workflow_run and test_workflow_faults)."""
    from surfphase.synth.campaign import write_campaign

    out = tmp_path_factory.mktemp("tiny") / "campaign"
    write_campaign(out, preset="tiny", seed=3, sessions=2)
    return out
