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


def _match_rows(
    pred: pd.DataFrame, truth: pd.DataFrame, gate: float, size: np.ndarray | None
) -> list[list]:
    """Per frame (ascending; a frame's rows in table order), the predicted and true rows
    with finite centres paired by :func:`gated_assignment` on the centre distance, over
    ``size`` (the truth's (M,) r_eq, m; rows with r_eq ≤ 0 left out) where given; one
    :data:`MATCH_COLUMNS` row per pair, plus the true r_eq where ``size`` is given."""
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    P, PV = pred[xyz].to_numpy(np.float64), pred[vel].to_numpy(np.float64)
    G, GV = truth[xyz].to_numpy(np.float64), truth[vel].to_numpy(np.float64)
    pb, gb = pred["bubble"].to_numpy(), truth["bubble"].to_numpy()
    ok_p = np.isfinite(P).all(axis=1)
    ok_g = np.isfinite(G).all(axis=1) if size is None else np.isfinite(G).all(axis=1) & (size > 0)
    by_frame = truth.groupby("frame", sort=False).indices
    rows: list[list] = []
    for f, pi in sorted(pred.groupby("frame", sort=False).indices.items()):
        gi = by_frame.get(f)
        if gi is None:
            continue
        pi, gi = pi[ok_p[pi]], gi[ok_g[gi]]
        if not len(pi) or not len(gi):
            continue
        d = np.linalg.norm(P[pi][:, None] - G[gi][None], axis=-1)
        r = None if size is None else size[gi]
        for i, j in gated_assignment(d if r is None else d / r[None], gate):
            v, gv = PV[pi[i]], GV[gi[j]]
            row = [int(f), int(pb[pi[i]]), int(gb[gi[j]]), float(d[i, j]),
                   *v, *gv, float(np.linalg.norm(v - gv))]  # fmt: skip
            rows.append(row if r is None else [*row, float(r[j])])
    return rows


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
    return pd.DataFrame(_match_rows(pred, truth, max_dist, None), columns=MATCH_COLUMNS)


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
    size = truth["r_eq"].to_numpy(np.float64)
    rows = _match_rows(pred, truth, gate_r_eq, size)
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
