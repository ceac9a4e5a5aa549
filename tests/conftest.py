"""Shared test set-up: deterministic seeds, `--runslow` for long end-to-end runs."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", help="run long end-to-end tests")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="long run: use --runslow (CI runs the small version)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
