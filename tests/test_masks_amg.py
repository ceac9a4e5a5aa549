"""Automatic-mask-generation post-processing, against brute-force references."""

from __future__ import annotations

import numpy as np

from surfphase.masks import amg


def test_point_grid_tiles_the_image():
    g = amg.point_grid(2, 100, 60)
    np.testing.assert_allclose(g, [[24.5, 14.5], [74.5, 14.5], [24.5, 44.5], [74.5, 44.5]])


def test_stability_score_brute_force():
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 3, size=(4, 16, 16))
    s = amg.stability_score(logits, 0.0, 1.0)
    for i in range(4):
        hi = sum(1 for v in logits[i].ravel() if v > 1.0)
        lo = sum(1 for v in logits[i].ravel() if v > -1.0)
        assert s[i] == hi / lo


def test_box_iou_and_nms():
    boxes = np.array([[0, 0, 9, 9], [1, 1, 10, 10], [20, 20, 29, 29], [0, 0, 4, 9]])
    iou = amg.box_iou(boxes, boxes)
    assert iou[0, 1] == 81 / (100 + 100 - 81)
    assert iou[0, 3] == 50 / 100 and iou[0, 2] == 0
    keep = amg.box_nms(boxes, np.array([0.9, 0.95, 0.5, 0.8]), 0.7)
    # IoU(box 0, box 1) = 81/119 ≈ 0.68: kept under a 0.7 threshold, not under 0.6.
    assert keep.tolist() == [1, 0, 3, 2]
    keep = amg.box_nms(boxes, np.array([0.9, 0.95, 0.5, 0.8]), 0.6)
    assert keep.tolist() == [1, 3, 2]


def test_mask_boxes_are_inclusive():
    m = np.zeros((2, 8, 8), bool)
    m[0, 2:5, 3:7] = True
    assert amg.mask_boxes(m).tolist() == [[3, 2, 6, 4], [0, 0, 0, 0]]


def test_small_regions_removed_and_holes_filled():
    m = np.zeros((20, 20), bool)
    m[2:12, 2:12] = True
    m[5, 5] = False  # a 1-pixel hole
    m[16:18, 16:18] = True  # a 4-pixel island
    out, changed = amg.remove_small_regions(m, 5, "holes")
    assert changed and out[5, 5] and out[16, 16]
    out, changed = amg.remove_small_regions(out, 5, "islands")
    assert changed and not out[16:18, 16:18].any() and out[2:12, 2:12].all()
    same, changed = amg.remove_small_regions(out, 5, "islands")
    assert not changed and (same == out).all()


def test_postprocess_and_paint():
    h = w = 32
    yy, xx = np.mgrid[0:h, 0:w]
    disk = (xx - 10) ** 2 + (yy - 10) ** 2 <= 36
    other = (xx - 24) ** 2 + (yy - 22) ** 2 <= 25
    masks = np.stack([disk, disk.copy(), other])
    masks[1, 10, 10] = False  # near duplicate, lower score, with a hole
    scores = np.array([0.9, 0.8, 0.95])
    kept, s = amg.postprocess_masks(masks, scores, 0.7, 4)
    assert len(kept) == 2 and s.tolist() == [0.95, 0.9]
    labels, ls = amg.masks_to_labels(kept, s)
    assert (labels[other] == 0).all() and (labels[disk] == 1).all()
    assert (labels[~(disk | other)] == -1).all() and ls.tolist() == [
        np.float32(0.95),
        np.float32(0.9),
    ]


def test_filter_candidates():
    logits = np.full((3, 8, 8), -10.0)
    logits[0, 2:6, 2:6] = 10.0  # stable, good
    logits[1, 2:6, 2:6] = 0.5  # unstable: vanishes at threshold +1
    logits[2, 2:6, 2:6] = 10.0  # stable but low predicted IoU
    m, s = amg.filter_candidates(logits, np.array([0.95, 0.95, 0.5]), 0.88, 0.9)
    assert m.shape == (1, 8, 8) and m[0].sum() == 16 and s.tolist() == [0.95]
