"""Mask accuracy figures on hand-made label stacks, and label warping."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from surfphase.cameras import look_at
from surfphase.masks.metrics import mask_metrics, match_frame, warp_labels


def _stack(t, h=20, w=20):
    return np.full((t, h, w), -1, np.int32)


def test_perfect_prediction_scores_one():
    gt = {c: _stack(4) for c in ("cam0", "cam1")}
    for c in gt:
        gt[c][:, 2:8, 2:8] = 1
        gt[c][:, 10:16, 10:18] = 2
    pred = {c: np.where(g >= 0, g + 10, -1) for c, g in gt.items()}
    m = mask_metrics(gt, pred)
    assert m["mean_iou"] == 1.0 and m["detection_recall"] == 1.0
    assert m["cross_view_identity"] == 1.0 and m["temporal_identity_frames"] == 1.0
    assert m["false_positives"] == 0 and m["tracked_bubbles"] == 4


def test_swaps_and_switches_are_counted():
    gt = {c: _stack(4) for c in ("cam0", "cam1")}
    for c in gt:
        gt[c][:, 2:8, 2:8] = 1
        gt[c][:, 10:16, 10:18] = 2
    pred = {c: np.where(g >= 0, g + 10, -1) for c, g in gt.items()}
    pred["cam1"][3] = np.where(gt["cam1"][3] == 1, 12, np.where(gt["cam1"][3] == 2, 11, -1))
    pred["cam0"][2, 2:8, 2:8] = 15  # id switch for one frame in one view
    m = mask_metrics(gt, pred)
    # 8 bubble-frames seen in both views: frame 3 (2 swapped) and frame 2 (1 switched).
    assert m["cross_view_identity"] == pytest.approx(5 / 8)
    assert m["temporal_identity_frames"] == pytest.approx(13 / 16)


def test_per_bubble_life_and_an_id_inherited_by_a_merged_bubble():
    """Truth: bubbles 1 and 2 merge into 3 at frame 3 (of 6)."""
    gt = {c: _stack(6) for c in ("cam0", "cam1")}
    for c in gt:
        gt[c][:3, 2:8, 2:8] = 1
        gt[c][:3, 10:16, 2:8] = 2
        gt[c][3:, 4:14, 2:8] = 3
    # cam0: the merged bubble keeps bubble 1's id; cam1: it gets its own id a frame late.
    pred = {c: np.where(g >= 0, g + 10, -1) for c, g in gt.items()}
    pred["cam0"][3:][gt["cam0"][3:] == 3] = 11
    pred["cam1"][3][gt["cam1"][3] == 3] = 11
    m = mask_metrics(gt, pred)
    per = {
        (b["camera"], b["truth"]): (b["id"], b["kept"], b["frames"])
        for b in m["temporal_identity_per_bubble"]
    }
    assert per[("cam0", 3)] == (11, 3, 3) and per[("cam1", 3)] == (13, 2, 3)
    assert per[("cam0", 1)] == (11, 3, 3)
    assert m["temporal_identity_min"] == pytest.approx(2 / 3)
    assert m["temporal_identity_mean"] == pytest.approx((5 + 2 / 3) / 6)
    assert m["temporal_identity_ok_frac"] == pytest.approx(5 / 6)
    assert m["shared_ids"] == 1  # id 11 is the id of truth 1 and truth 3 in cam0


def test_nucleation_region_groups_attached_bubbles():
    gt = np.full((20, 20), -1, np.int32)
    gt[15:19, 2:6] = 3
    gt[15:19, 10:14] = 4
    pred = np.where(gt >= 0, 0, -1)
    m = match_frame(gt, pred)
    assert m == [((3, 4), 0, 1.0)]


def test_warp_labels_identity_and_downscale():
    cam = look_at("c", [0, 0.008, 0.06], [0, 0.006, 0], fx=900, width=64, height=64)
    lab = np.full((1, 64, 64), -1, np.int32)
    lab[0, 16:48, 20:40] = 5
    same = warp_labels(lab, cam, cam, supersample=1)
    np.testing.assert_array_equal(same, lab)
    half = warp_labels(lab, cam, cam.scaled(0.5), supersample=4)
    assert half.shape == (1, 32, 32)
    np.testing.assert_array_equal(half[0, 8:24, 10:20], 5)
    assert (half == 5).sum() == 16 * 10
    moved = replace(cam, t=cam.t + 0.001)
    with pytest.raises(ValueError, match="centre"):
        warp_labels(lab, cam, moved)
