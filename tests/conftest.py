"""Shared test set-up: two CPU threads, as on the development machine and in CI."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")
