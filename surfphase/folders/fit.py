"""Readers of the fit folder (``results/<session>/fit``, ``fit2``, ablation fits) for the
stages after the fit (mesh, evaluate, report). The fit writes it
(:mod:`surfphase.fit.outputs`): ``surfels.npz`` (per-frame surfels) and ``bubbles.csv``
(``frame, bubble, x, y, z, vx, vy, vz``, m and m/s), among others.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

SURFELS, BUBBLES = "surfels.npz", "bubbles.csv"
#: The columns every bubble table (fit or ground truth) has.
BUBBLE_COLUMNS = ("frame", "bubble", "x", "y", "z", "vx", "vy", "vz")


def read_csv_table(path: str | os.PathLike, columns: Sequence[str], what: str) -> pd.DataFrame:
    """A CSV with at least ``columns``; errors name the file and ``what`` it is for
    (e.g. ``session s01``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what}: not found")
    try:
        df = pd.read_csv(path)
    except (ValueError, pd.errors.ParserError) as e:
        raise ValueError(f"{path}: {what}: not a readable CSV ({e})") from e
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: {what}: missing columns {missing}")
    return df


def read_fit_bubbles(fit_dir: str | os.PathLike, what: str) -> pd.DataFrame:
    """A fit folder's ``bubbles.csv`` with :data:`BUBBLE_COLUMNS` (``what``: for errors)."""
    return read_csv_table(Path(fit_dir) / BUBBLES, BUBBLE_COLUMNS, what)


def read_fit_surfels(fit_dir: str | os.PathLike) -> dict[str, np.ndarray]:
    """A fit folder's ``surfels.npz`` as a dict of arrays (FileNotFoundError naming it)."""
    from surfphase.fit.outputs import load_surfels

    return load_surfels(Path(fit_dir) / SURFELS)
