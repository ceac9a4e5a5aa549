"""Bubble velocity error against ground truth.

Per frame, predicted bubbles are matched one-to-one to true bubbles by the Hungarian
algorithm on centroid distance (metres); pairs further apart than a gating distance
are left unmatched. Over the matched bubble-frames where both velocities are known:

* ``mean_abs_error_mps`` = mean ``|v − v_gt|`` (Euclidean norm, m/s),
* ``relative_error`` = mean ``|v − v_gt|`` / mean ``|v_gt|`` (dimensionless).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

#: Default gating distance between matched centroids, metres (bubbles are ~0.5–1 mm).
MAX_MATCH_DIST = 1.5e-3

MATCH_COLUMNS = [
    "frame", "bubble", "gt_bubble", "dist_m",
    "vx", "vy", "vz", "gt_vx", "gt_vy", "gt_vz", "abs_error_mps",
]  # fmt: skip


def match_bubbles(
    pred: pd.DataFrame, truth: pd.DataFrame, max_dist: float = MAX_MATCH_DIST
) -> pd.DataFrame:
    """One row per matched (frame, predicted bubble, true bubble).

    Args:
        pred, truth: tables with ``frame, bubble, x, y, z, vx, vy, vz`` (m, m/s).
        max_dist: gating distance, metres.

    Returns:
        Columns :data:`MATCH_COLUMNS`; ``abs_error_mps`` is NaN where a velocity is
        unknown.
    """
    rows = []
    for f, p in pred.groupby("frame", sort=True):
        g = truth[truth["frame"] == f]
        p = p[np.isfinite(p[["x", "y", "z"]].to_numpy()).all(axis=1)]
        g = g[np.isfinite(g[["x", "y", "z"]].to_numpy()).all(axis=1)]
        if p.empty or g.empty:
            continue
        P = p[["x", "y", "z"]].to_numpy(np.float64)
        G = g[["x", "y", "z"]].to_numpy(np.float64)
        d = np.linalg.norm(P[:, None] - G[None], axis=-1)
        for i, j in zip(*linear_sum_assignment(d), strict=True):
            if d[i, j] > max_dist:
                continue
            v = p[["vx", "vy", "vz"]].to_numpy(np.float64)[i]
            gv = g[["vx", "vy", "vz"]].to_numpy(np.float64)[j]
            rows.append(
                [int(f), int(p["bubble"].iloc[i]), int(g["bubble"].iloc[j]), float(d[i, j]),
                 *v, *gv, float(np.linalg.norm(v - gv))]
            )  # fmt: skip
    return pd.DataFrame(rows, columns=MATCH_COLUMNS)


def velocity_errors(matches: pd.DataFrame) -> dict:
    """``mean_abs_error_mps``, ``relative_error``, ``mean_speed_gt_mps`` and ``matched``
    (bubble-frames with both velocities known) of a :func:`match_bubbles` table."""
    m = matches[np.isfinite(matches["abs_error_mps"].to_numpy(np.float64))]
    if m.empty:
        nan = float("nan")
        return {
            "mean_abs_error_mps": nan,
            "relative_error": nan,
            "mean_speed_gt_mps": nan,
            "matched": 0,
        }
    err = m["abs_error_mps"].to_numpy(np.float64)
    speed = np.linalg.norm(m[["gt_vx", "gt_vy", "gt_vz"]].to_numpy(np.float64), axis=1)
    return {
        "mean_abs_error_mps": float(err.mean()),
        "relative_error": float(err.mean() / speed.mean()) if speed.mean() > 0 else float("nan"),
        "mean_speed_gt_mps": float(speed.mean()),
        "matched": int(len(m)),
    }
