"""Per-bubble sizes joined to bubbles.csv and summarised (surfphase.eval.sizes)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from surfphase.eval.sizes import bubble_sizes_table, cut_bubble_frames, size_metrics


def _bubbles() -> pd.DataFrame:
    rows = [(f, b, 0.001 * b, 0.002, 0.0, 0.0, 0.2, 0.0) for f in range(3) for b in (0, 1, 2)]
    return pd.DataFrame(rows, columns=["frame", "bubble", "x", "y", "z", "vx", "vy", "vz"])


def _sizes() -> pd.DataFrame:
    d = {1: 1.0e-3, 2: 2.0e-3}  # equivalent diameters (m)
    rows = [
        (f, f / 1000, b, math.pi / 6 * d[b] ** 3, d[b], 1, True)
        for f in range(3)
        for b in (1, 2)
        if (f, b) != (2, 2)  # bubble 2 has no mesh in frame 2
    ]
    cols = ["frame", "time_s", "bubble", "volume_m3", "d_eq_m", "components", "closed"]
    return pd.DataFrame(rows, columns=cols)


def test_sizes_join_every_row_of_the_fit_table():
    t = bubble_sizes_table(_bubbles(), _sizes())
    assert len(t) == 9 and list(t.columns[:8]) == list(_bubbles().columns)
    row = t[(t.frame == 1) & (t.bubble == 2)].iloc[0]
    assert row.d_eq_m == pytest.approx(2e-3) and row.closed
    gone = t[(t.frame == 2) & (t.bubble == 2)].iloc[0]
    assert np.isnan(gone.volume_m3) and not gone.closed
    assert t[t.bubble == 0]["volume_m3"].isna().all()  # the nucleation region: no size
    # Without the meshes' table: the same rows, sizes NaN.
    assert bubble_sizes_table(_bubbles(), None)["d_eq_m"].isna().all()


def test_size_summary_and_its_error_against_the_truth():
    t = bubble_sizes_table(_bubbles(), _sizes())
    m = size_metrics(t)
    assert m["bubble_frames"] == 5
    assert m["d_eq_mm_mean"] == pytest.approx((3 * 1.0 + 2 * 2.0) / 5)
    assert m["d_eq_mm_median"] == pytest.approx(1.0)
    v = (3 * math.pi / 6 * 1.0 + 2 * math.pi / 6 * 8.0) / 5  # mm³
    assert m["volume_mm3_mean"] == pytest.approx(v)
    # Truth: bubble 1 is 10 % larger than measured, bubble 2 exact; ids differ.
    matches = pd.DataFrame({"frame": [0, 0, 1], "bubble": [1, 2, 1], "gt_bubble": [7, 8, 7]})
    truth = pd.DataFrame(
        {"frame": [0, 0, 1], "bubble": [7, 8, 7], "r_eq": [0.55e-3, 1e-3, 0.55e-3]}
    )
    m = size_metrics(t, matches, truth)
    assert m["d_eq_compared"] == 3
    assert m["d_eq_rel_error"] == pytest.approx((2 * (0.1 / 1.1) + 0.0) / 3)


def test_a_bubble_the_image_border_cuts_is_flagged():
    """Bubble 2 touches the right border of view 1 in frame 1 (and only there): that
    bubble-frame alone is flagged ``cut``; the sizes stay the meshes'."""
    T, H, W = 3, 20, 30
    views = [np.full((T, H, W), -1, np.int32) for _ in range(2)]
    for lab in views:
        lab[:, 5:9, 5:9] = 1
        lab[:, 12:16, 14:18] = 2
    views[1][1, 12:16, 24:] = 2  # frame 1, view 1: bubble 2 reaches the last column
    views[0][:, 0, 10] = 0  # the nucleation region at the border: not a bubble
    cut = cut_bubble_frames(views, [0, 1, 2])
    assert cut == {(1, 2)}
    t = bubble_sizes_table(_bubbles(), _sizes(), cut)
    flagged = t[t.cut]
    assert list(zip(flagged.frame, flagged.bubble, strict=True)) == [(1, 2)]
    assert flagged.d_eq_m.iloc[0] == pytest.approx(2e-3)
    assert t.drop(columns="cut").equals(bubble_sizes_table(_bubbles(), _sizes()))
    # Session frame indices (a window of the recording) name the rows, not positions.
    assert cut_bubble_frames(views, [40, 41, 42]) == {(41, 2)}
