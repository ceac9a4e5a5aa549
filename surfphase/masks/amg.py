"""Automatic mask generation post-processing (Segment Anything's "everything" mode).

A grid of single-point prompts covers the image; each prompt gives a few candidate
mask logits and a predicted IoU. Candidates are kept when the predicted IoU and the
*stability score* (IoU between the masks thresholded at ``+offset`` and ``−offset``:
how little the mask moves when the logit threshold does) are high enough, then
de-duplicated by non-maximum suppression on their boxes, cleaned of small islands
and holes, and finally painted into one label image.

Pure NumPy; pixel coordinates use the project convention (origin at the centre of
the top-left pixel, ``u`` right, ``v`` down).
"""

from __future__ import annotations

import cv2
import numpy as np


def point_grid(points_per_side: int, width: int, height: int) -> np.ndarray:
    """(n², 2) float64 pixel coordinates (u, v) of an n×n grid of prompts.

    Points sit at the centres of an n×n tiling of the image:
    ``u = (i + 0.5)·W/n − 0.5``, row-major (v outer, u inner).
    """
    n = int(points_per_side)
    if n < 1:
        raise ValueError(f"points_per_side must be ≥ 1, not {points_per_side}")
    offs = (np.arange(n) + 0.5) / n
    u = offs * width - 0.5
    v = offs * height - 0.5
    vv, uu = np.meshgrid(v, u, indexing="ij")
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def stability_score(logits: np.ndarray, threshold: float = 0.0, offset: float = 1.0) -> np.ndarray:
    """Stability of masks given as logits (..., H, W) → (...) in [0, 1].

    ``|logits > threshold + offset| / |logits > threshold − offset|`` (1 for an
    empty mask's empty union would be meaningless, so that case gives 0).
    """
    hi = (logits > threshold + offset).sum(axis=(-2, -1)).astype(np.float64)
    lo = (logits > threshold - offset).sum(axis=(-2, -1)).astype(np.float64)
    return np.where(lo > 0, hi / np.maximum(lo, 1), 0.0)


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """(N, H, W) bool → (N, 4) int64 boxes ``x0, y0, x1, y1`` (inclusive); empty → zeros."""
    n = masks.shape[0]
    boxes = np.zeros((n, 4), np.int64)
    if n == 0:
        return boxes
    cols = masks.any(axis=1)
    rows = masks.any(axis=2)
    for i in range(n):
        xs = np.flatnonzero(cols[i])
        ys = np.flatnonzero(rows[i])
        if xs.size:
            boxes[i] = (xs[0], ys[0], xs[-1], ys[-1])
    return boxes


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of inclusive pixel boxes (N, 4) × (M, 4) → (N, M)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    area_a = (a[:, 2] - a[:, 0] + 1) * (a[:, 3] - a[:, 1] + 1)
    area_b = (b[:, 2] - b[:, 0] + 1) * (b[:, 3] - b[:, 1] + 1)
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 2], b[None, :, 2])
    y1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0 + 1, 0, None) * np.clip(y1 - y0 + 1, 0, None)
    return inter / (area_a[:, None] + area_b[None, :] - inter)


def box_nms(boxes: np.ndarray, scores: np.ndarray, iou_thresh: float) -> np.ndarray:
    """Greedy non-maximum suppression → indices kept, best score first.

    A box is dropped when its IoU with an already kept, better-scored box exceeds
    ``iou_thresh``. Ties keep the earlier box (stable order).
    """
    order = np.argsort(-np.asarray(scores), kind="stable")
    if order.size == 0:
        return order
    iou = box_iou(boxes[order], boxes[order])
    keep: list[int] = []
    suppressed = np.zeros(order.size, bool)
    for i in range(order.size):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_thresh
    return order[np.asarray(keep, np.int64)]


def remove_small_regions(mask: np.ndarray, min_area: int, mode: str) -> tuple[np.ndarray, bool]:
    """Drop connected ``islands`` (or fill ``holes``) smaller than ``min_area`` pixels.

    Returns the cleaned (H, W) bool mask and whether it changed. Islands: if every
    region is small, the largest one is kept rather than returning an empty mask.
    """
    if mode not in ("islands", "holes"):
        raise ValueError(f"mode must be islands or holes, not {mode!r}")
    work = (mask ^ (mode == "holes")).astype(np.uint8)
    n, regions, stats, _ = cv2.connectedComponentsWithStats(work, connectivity=8)
    sizes = stats[1:, cv2.CC_STAT_AREA]
    small = [i + 1 for i, s in enumerate(sizes) if s < min_area]
    if not small:
        return mask, False
    if mode == "holes":
        fill = np.isin(regions, small)
        return mask | fill, True
    keep = [i for i in range(1, n) if i not in small]
    if not keep:
        keep = [int(np.argmax(sizes)) + 1]
    return np.isin(regions, keep), True


def filter_candidates(
    logits: np.ndarray,
    iou_preds: np.ndarray,
    pred_iou_thresh: float,
    stability_score_thresh: float,
    mask_threshold: float = 0.0,
    stability_offset: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Keep candidate masks by predicted IoU and stability.

    Args:
        logits: (N, H, W) mask logits at the image's resolution.
        iou_preds: (N,) predicted IoU of each candidate.

    Returns:
        masks: (M, H, W) bool, ``logits > mask_threshold``, non-empty;
        scores: (M,) float64 predicted IoU of the kept masks.
    """
    keep = iou_preds > pred_iou_thresh
    if stability_score_thresh > 0:
        stab = stability_score(logits, mask_threshold, stability_offset)
        keep &= stab >= stability_score_thresh
    masks = logits[keep] > mask_threshold
    scores = np.asarray(iou_preds[keep], np.float64)
    nonempty = masks.any(axis=(1, 2))
    return masks[nonempty], scores[nonempty]


def postprocess_masks(
    masks: np.ndarray, scores: np.ndarray, box_nms_thresh: float, min_region_area: int
) -> tuple[np.ndarray, np.ndarray]:
    """NMS, then small-region clean-up, then NMS again favouring untouched masks.

    Args:
        masks: (N, H, W) bool candidates; scores: (N,) their predicted IoU.

    Returns:
        (M, H, W) bool masks and (M,) scores, best first.
    """
    if masks.shape[0] == 0:
        return masks, scores
    keep = box_nms(mask_boxes(masks), scores, box_nms_thresh)
    masks, scores = masks[keep], scores[keep]
    if min_region_area <= 0:
        return masks, scores
    cleaned = []
    rescored = []
    for m in masks:
        m1, c1 = remove_small_regions(m, min_region_area, "holes")
        m2, c2 = remove_small_regions(m1, min_region_area, "islands")
        cleaned.append(m2)
        # The second NMS prefers masks the clean-up left untouched; among equals the
        # order of the first NMS (best predicted IoU first) is kept.
        rescored.append(0.0 if (c1 or c2) else 1.0)
    cleaned = np.asarray(cleaned)
    nonempty = cleaned.any(axis=(1, 2))
    cleaned, scores, rescored = cleaned[nonempty], scores[nonempty], np.asarray(rescored)[nonempty]
    keep = box_nms(mask_boxes(cleaned), rescored, box_nms_thresh)
    keep = keep[np.argsort(-scores[keep], kind="stable")]
    return cleaned[keep], scores[keep]


def masks_to_labels(masks: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Paint (N, H, W) bool masks into (H, W) int32 labels (−1 background).

    Lower-scored masks are painted first so a better mask wins an overlap; masks that
    end up with no pixel are dropped. Returns labels 0..M−1 and their (M,) scores.
    """
    n, h, w = masks.shape
    out = np.full((h, w), -1, np.int32)
    for i in np.argsort(scores, kind="stable"):
        out[masks[i]] = i
    present = np.unique(out[out >= 0])
    lut = np.full(n + 1, -1, np.int32)
    lut[present + 1] = np.arange(present.size, dtype=np.int32)
    return lut[out + 1], np.asarray(scores, np.float32)[present]
