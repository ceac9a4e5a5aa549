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


def gated_assignment(cost: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """One-to-one pairs ``(i, j)`` of an (n, m) cost matrix with ``cost ≤ gate``.

    The gate applies before the assignment: pairs above it cost more than any set of
    pairs within it, so the Hungarian algorithm (``scipy.optimize.linear_sum_assignment``)
    first maximises the number of pairs within the gate, then minimises their summed
    cost. (Gating after an ungated assignment lets a far report take a close report's
    partner to lower the total.) Non-finite costs are never paired.
    """
    c = np.asarray(cost, dtype=np.float64)
    ok = np.isfinite(c) & (c <= gate)
    if not ok.any():
        return []
    big = float(c[ok].sum()) + 1.0  # more than any set of pairs within the gate
    rows, cols = linear_sum_assignment(np.where(ok, c, big))
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True) if ok[i, j]]


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
        for i, j in gated_assignment(d, max_dist):
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


def match_bubbles_relative(
    pred: pd.DataFrame, truth: pd.DataFrame, gate_r_eq: float = 0.5
) -> pd.DataFrame:
    """:func:`match_bubbles` with a gate relative to each true bubble's size.

    Per frame, predicted and true bubbles are paired one-to-one by the Hungarian
    algorithm on ``|c − c_gt| / r_eq`` (the true bubble's equivalent radius); pairs with
    a ratio above ``gate_r_eq`` are left unmatched. ``truth`` needs an ``r_eq`` column (m).

    Returns:
        Columns :data:`MATCH_COLUMNS` plus ``gt_r_eq`` (m).
    """
    if "r_eq" not in truth.columns:
        raise ValueError("relative matching needs the truth's r_eq column (m)")
    rows = []
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    for f, p in pred.groupby("frame", sort=True):
        g = truth[truth["frame"] == f]
        p = p[np.isfinite(p[xyz].to_numpy(np.float64)).all(axis=1)]
        g = g[np.isfinite(g[xyz].to_numpy(np.float64)).all(axis=1) & (g["r_eq"] > 0)]
        if p.empty or g.empty:
            continue
        d = np.linalg.norm(
            p[xyz].to_numpy(np.float64)[:, None] - g[xyz].to_numpy(np.float64)[None], axis=-1
        )
        r = g["r_eq"].to_numpy(np.float64)
        cost = d / r[None]
        for i, j in gated_assignment(cost, gate_r_eq):
            v = p[vel].to_numpy(np.float64)[i]
            gv = g[vel].to_numpy(np.float64)[j]
            rows.append(
                [int(f), int(p["bubble"].iloc[i]), int(g["bubble"].iloc[j]), float(d[i, j]),
                 *v, *gv, float(np.linalg.norm(v - gv)), float(r[j])]
            )  # fmt: skip
    return pd.DataFrame(rows, columns=[*MATCH_COLUMNS, "gt_r_eq"])


def component_errors(matches: pd.DataFrame) -> dict:
    """Mean ``|v_k − v_gt,k|`` (m/s) per component ``k`` = x, y, z over the matched
    bubble-frames whose velocities are both known: ``{"vx": …, "vy": …, "vz": …}``."""
    m = matches[np.isfinite(matches["abs_error_mps"].to_numpy(np.float64))]
    if m.empty:
        return {k: float("nan") for k in ("vx", "vy", "vz")}
    return {
        k: float(np.abs(m[k].to_numpy(np.float64) - m[f"gt_{k}"].to_numpy(np.float64)).mean())
        for k in ("vx", "vy", "vz")
    }
