"""Conventions of a campaign's sheets (``sessions.tsv``, ``rigs.tsv``) that both the
workflow and the package read.

This module imports nothing but the standard library, so the workflow can read it while
it builds the DAG.
"""

from __future__ import annotations

from collections.abc import Iterable


def camera_columns(columns: Iterable[str]) -> list[str]:
    """The camera columns ``cam0, cam1, …`` among a sheet's ``columns``, in numeric
    order (``cam10`` after ``cam2``)."""
    cols = [c for c in columns if c.startswith("cam") and c[3:].isdigit()]
    return sorted(cols, key=lambda c: int(c[3:]))
