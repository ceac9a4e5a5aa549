"""Per-bubble sizes from the reconstructed surfaces, beside the positions and velocities.

The mesh stage measures each bubble's closed surface per frame (``mesh/bubble_sizes.csv``:
enclosed volume, equivalent diameter ``(6V/π)^(1/3)``); here they join the fit's
``bubbles.csv`` into one table per bubble and frame, and a session's summary (and, with
ground truth, the equivalent diameter's error against the true bubbles') goes into the
evaluation's metrics and the campaign table.

A bubble whose silhouette touches the image border in some input view is partly outside
the frame there: its size rests on that silhouette completed beyond the border (``mesh:
complete_cut``), an extrapolation, less sure than a size from silhouettes seen whole.
Such bubble-frames are flagged ``cut``, so that sizing can leave them out, as particle
sizing leaves out the objects the image border cuts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from surfphase.masks.anchors import border_ids

#: Columns the meshes add to a row of ``bubbles.csv``.
SIZE_COLUMNS = ["volume_m3", "d_eq_m", "closed"]
#: Column flagging the bubble-frames the image border cuts in some view.
CUT_COLUMN = "cut"


def cut_bubble_frames(
    labels: Sequence[np.ndarray], frame_indices: Sequence[int]
) -> set[tuple[int, int]]:
    """``(frame, bubble)`` of every bubble (ids ≥ 1) whose silhouette touches the image
    border (its outermost pixel rows and columns) in some view.

    Args:
        labels: per view, a (T, H, W) int label stack of bubble ids (−1 background).
        frame_indices: (T,) session frame index of each stack position.
    """
    out: set[tuple[int, int]] = set()
    for stack in labels:
        for k, f in enumerate(frame_indices):
            out.update((int(f), b) for b in border_ids(np.asarray(stack[k])) if b >= 1)
    return out


def bubble_sizes_table(
    bubbles: pd.DataFrame,
    sizes: pd.DataFrame | None,
    cut: set[tuple[int, int]] | None = None,
) -> pd.DataFrame:
    """``bubbles`` (the fit's ``bubbles.csv``) with :data:`SIZE_COLUMNS` from the meshes'
    ``sizes`` (``frame, bubble, volume_m3, d_eq_m, closed``; m³, m), matched on frame and
    bubble; NaN (``closed`` false) where a bubble-frame has no mesh or ``sizes`` is None.
    With ``cut`` (:func:`cut_bubble_frames`), the column :data:`CUT_COLUMN` flags those
    bubble-frames (their sizes rest on silhouettes completed beyond the border). Rows
    and their order are those of ``bubbles``."""
    out = bubbles.drop(columns=[c for c in [*SIZE_COLUMNS, CUT_COLUMN] if c in bubbles.columns])
    if sizes is None or len(sizes) == 0:
        sizes = pd.DataFrame(columns=["frame", "bubble", *SIZE_COLUMNS])
    s = sizes[["frame", "bubble", *SIZE_COLUMNS]].astype(
        {"frame": np.int64, "bubble": np.int64, "volume_m3": float, "d_eq_m": float}
    )
    out = out.astype({"frame": np.int64, "bubble": np.int64}).merge(
        s, on=["frame", "bubble"], how="left"
    )
    out["closed"] = out["closed"].fillna(False).astype(bool)
    if cut is not None:
        keys = zip(out["frame"].to_numpy(), out["bubble"].to_numpy(), strict=True)
        out[CUT_COLUMN] = np.array([(int(f), int(b)) in cut for f, b in keys], dtype=bool)
    return out


def size_metrics(table: pd.DataFrame, matches: pd.DataFrame | None = None,
                 truth_r_eq: pd.DataFrame | None = None) -> dict:  # fmt: skip
    """A session's size summary of :func:`bubble_sizes_table`'s bubbles (ids ≥ 1).

    Args:
        table: :func:`bubble_sizes_table`'s output.
        matches: ``frame, bubble, gt_bubble`` of the method's matched bubble-frames.
        truth_r_eq: ``frame, bubble, r_eq`` of the true bubbles (m).

    Returns:
        ``bubble_frames`` (ids ≥ 1 with a measured volume), ``d_eq_mm_mean``,
        ``d_eq_mm_median``, ``volume_mm3_mean``; with ``matches`` and ``truth_r_eq``,
        ``d_eq_rel_error`` (mean |d_eq − 2 r_eq| / 2 r_eq over the matched bubble-frames
        that have a size) and ``d_eq_compared`` (their count). NaN where nothing counts.
    """
    b = table[(table["bubble"] >= 1) & np.isfinite(table["volume_m3"].to_numpy(float))]
    d = b["d_eq_m"].to_numpy(float) * 1e3
    out = {
        "bubble_frames": int(len(b)),
        "d_eq_mm_mean": float(d.mean()) if len(d) else math.nan,
        "d_eq_mm_median": float(np.median(d)) if len(d) else math.nan,
        "volume_mm3_mean": float(b["volume_m3"].mean() * 1e9) if len(b) else math.nan,
    }
    if matches is not None and truth_r_eq is not None:
        m = matches[["frame", "bubble", "gt_bubble"]].merge(
            b[["frame", "bubble", "d_eq_m"]], on=["frame", "bubble"]
        )
        t = truth_r_eq.rename(columns={"bubble": "gt_bubble"})[["frame", "gt_bubble", "r_eq"]]
        m = m.merge(t, on=["frame", "gt_bubble"])
        true_d = 2.0 * m["r_eq"].to_numpy(float)
        err = np.abs(m["d_eq_m"].to_numpy(float) - true_d) / true_d
        out["d_eq_rel_error"] = float(err.mean()) if len(err) else math.nan
        out["d_eq_compared"] = int(len(err))
    return out
