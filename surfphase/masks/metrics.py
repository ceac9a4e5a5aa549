"""Accuracy of bubble masks and ids against ground-truth label stacks.

Ground truth and prediction are label stacks on the same pixel grid
(frames × H × W, −1 background). Truth ids are the simulator's bubbles; predicted
ids are the stage's (0 = nucleation region, ≥ 1 bubbles).

* **Mask IoU** per matched bubble: per frame and view, truth bubbles that the
  prediction puts in the nucleation region (their pixels are mostly predicted 0)
  form one truth region, since bubble 0 is by design the union of the attached
  bubbles; truth regions and predicted ids are then matched one to one by the
  Hungarian algorithm on IoU (a match needs IoU ≥ ``match_iou``).
* **Cross-view identity**: of the truth bubble-frames matched in both views, the
  fraction whose two predicted ids agree.
* **Temporal identity** ("the same id kept across frames for ≥ 95 % of a bubble's
  visible life"): per truth bubble and view, over the frames where it is matched
  to a bubble other than the nucleation region (its free visible life), the
  fraction of frames carrying its most frequent predicted id; reported per bubble
  (mean, min, share at ≥ 95 %, and the list) and pooled over bubble-frames. An
  attached bubble is bubble 0 by the method's rule, so its change from 0 to its
  own id at detachment is not counted against it.
* **Shared ids**: predicted ids that are the most frequent id of more than one
  truth bubble in a view (e.g. a merged bubble that kept a parent's id, which the
  per-bubble figure alone would not see).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping

import numpy as np
from scipy.optimize import linear_sum_assignment

from surfphase.cameras import Camera


def _overlaps(gt: np.ndarray, pred: np.ndarray):
    """Ids and pixel counts: truth ids, pred ids, (G, P) intersections, areas."""
    g_ids, g_inv = np.unique(gt, return_inverse=True)
    p_ids, p_inv = np.unique(pred, return_inverse=True)
    inter = np.zeros((g_ids.size, p_ids.size), np.int64)
    np.add.at(inter, (g_inv.ravel(), p_inv.ravel()), 1)
    return g_ids, p_ids, inter


def match_frame(
    gt: np.ndarray, pred: np.ndarray, match_iou: float = 0.25, min_area: int = 6
) -> list[tuple[tuple[int, ...], int, float]]:
    """Match the truth bubbles of one frame and view to predicted ids.

    Args:
        gt, pred: (H, W) int labels, −1 background.
        match_iou: least IoU of a match.
        min_area: truth bubbles smaller than this (pixels) are ignored.

    Returns:
        ``[(truth ids, predicted id, IoU)]``; ``truth ids`` has several entries when
        truth bubbles were merged into the predicted nucleation region.
    """
    g_ids, p_ids, inter = _overlaps(gt, pred)
    g_area = inter.sum(axis=1)
    p_area = inter.sum(axis=0)
    gi = [i for i, g in enumerate(g_ids) if g >= 0 and g_area[i] >= min_area]
    pi = [j for j, p in enumerate(p_ids) if p >= 0]
    if not gi or not pi:
        return []
    # Group truth bubbles mostly predicted as the nucleation region.
    groups: list[list[int]] = []
    nuc = [i for i in gi if 0 in p_ids and inter[i, np.searchsorted(p_ids, 0)] * 2 > g_area[i]]
    if nuc:
        groups.append(nuc)
    groups += [[i] for i in gi if i not in nuc]
    iou = np.zeros((len(groups), len(pi)))
    for a, grp in enumerate(groups):
        ga = g_area[grp].sum()
        for b, j in enumerate(pi):
            x = inter[grp, j].sum()
            iou[a, b] = x / (ga + p_area[j] - x)
    rr, cc = linear_sum_assignment(-iou)
    out = []
    for r, c in zip(rr, cc, strict=True):
        if iou[r, c] >= match_iou:
            out.append(
                (tuple(int(g_ids[i]) for i in groups[r]), int(p_ids[pi[c]]), float(iou[r, c]))
            )
    return out


def mask_metrics(
    gt: Mapping[str, np.ndarray],
    pred: Mapping[str, np.ndarray],
    match_iou: float = 0.25,
    min_area: int = 6,
) -> dict:
    """The three figures (and their counts) over all frames of all views.

    Args:
        gt, pred: ``{camera: (T, H, W) int}`` on the same grids, −1 background.

    Returns:
        dict with ``mean_iou``, ``detection_recall`` (matched / truth bubble-frames),
        ``false_positives`` (unmatched predicted instances), ``cross_view_identity``,
        ``temporal_identity_mean``, ``temporal_identity_min``,
        ``temporal_identity_ok_frac`` (bubbles at ≥ 95 %), ``shared_ids``, the counts
        behind them and ``temporal_identity_per_bubble`` (per truth bubble and view:
        ``camera, truth, id`` (its most frequent predicted id), ``frames, kept``).
    """
    cams = list(gt)
    ious = []
    n_truth = 0
    n_fp = 0
    assigned: dict[tuple[str, int, int], int] = {}  # (camera, frame, truth id) → pred id
    for c in cams:
        g_st, p_st = gt[c], pred[c]
        if g_st.shape != p_st.shape:
            raise ValueError(f"{c}: truth {g_st.shape} and prediction {p_st.shape} differ")
        for t in range(g_st.shape[0]):
            g_ids, _, inter = _overlaps(g_st[t], p_st[t])
            n_truth += int(
                sum(1 for i, g in enumerate(g_ids) if g >= 0 and inter[i].sum() >= min_area)
            )
            m = match_frame(g_st[t], p_st[t], match_iou, min_area)
            n_pred = len(np.unique(p_st[t][p_st[t] >= 0]))
            n_fp += n_pred - len(m)
            for gids, pid, iou in m:
                ious.append(iou)
                for g in gids:
                    assigned[(c, t, g)] = pid
    matched_truth = len(assigned)
    # Cross-view identity.
    agree = total = 0
    if len(cams) >= 2:
        a, b = cams[:2]
        for (c, t, g), pid in assigned.items():
            if c != a or (b, t, g) not in assigned:
                continue
            total += 1
            agree += int(assigned[(b, t, g)] == pid)
    # Temporal identity over each truth bubble's free life, per view.
    seqs: dict[tuple[str, int], list[int]] = {}
    for (c, _t, g), pid in sorted(assigned.items(), key=lambda kv: kv[0][1]):
        if pid != 0:
            seqs.setdefault((c, g), []).append(pid)
    per_bubble = []
    for (c, g), s in sorted(seqs.items()):
        pid, kept = Counter(s).most_common(1)[0]
        per_bubble.append(
            {"camera": c, "truth": int(g), "id": int(pid), "frames": len(s), "kept": kept}
        )
    fracs = [b["kept"] / b["frames"] for b in per_bubble]
    frames_kept = sum(b["kept"] for b in per_bubble)
    frames_all = sum(b["frames"] for b in per_bubble)
    owners = Counter((b["camera"], b["id"]) for b in per_bubble)
    return {
        "mean_iou": float(np.mean(ious)) if ious else float("nan"),
        "matched_bubble_frames": len(ious),
        "truth_bubble_frames": n_truth,
        "detection_recall": matched_truth / n_truth if n_truth else float("nan"),
        "false_positives": int(n_fp),
        "cross_view_identity": agree / total if total else float("nan"),
        "cross_view_bubble_frames": total,
        "temporal_identity_mean": float(np.mean(fracs)) if fracs else float("nan"),
        "temporal_identity_min": float(np.min(fracs)) if fracs else float("nan"),
        "temporal_identity_frames": frames_kept / frames_all if frames_all else float("nan"),
        "temporal_identity_ok_frac": float(np.mean([f >= 0.95 for f in fracs]))
        if fracs
        else float("nan"),
        "tracked_bubbles": len(fracs),
        "temporal_identity_per_bubble": per_bubble,
        "shared_ids": sum(1 for n in owners.values() if n > 1),
    }


def warp_labels(labels: np.ndarray, src: Camera, dst: Camera, supersample: int = 4) -> np.ndarray:
    """Resample label stacks seen by camera ``src`` onto the pixel grid of ``dst``.

    Both cameras must share their centre (same pose, e.g. a raw distorted camera and
    its undistorted, cropped, scaled version). Each ``dst`` pixel is split into
    ``supersample``² sub-pixels; each sub-pixel's ray is projected into ``src``
    (with its distortion) and takes the nearest label; the pixel gets the most
    frequent one (ties: the lowest id, background −1 included).

    Args:
        labels: (T, H_src, W_src) int labels of ``src``.

    Returns:
        (T, H_dst, W_dst) int32.
    """
    if np.linalg.norm(src.center - dst.center) > 1e-9 * max(1.0, np.linalg.norm(src.center)):
        raise ValueError(f"cameras {src.name} and {dst.name} do not share their centre")
    s = int(supersample)
    off = (np.arange(s) + 0.5) / s - 0.5
    v, u = np.mgrid[0 : dst.height, 0 : dst.width].astype(np.float64)
    shape = (dst.height, dst.width, s, s)
    uu = np.broadcast_to(u[..., None, None] + off[None, None, None, :], shape).ravel()
    vv = np.broadcast_to(v[..., None, None] + off[None, None, :, None], shape).ravel()
    rays = dst.pixel_rays(np.stack([uu, vv], axis=1), distorted=False)
    pts = src.center + rays  # one metre along each ray: projects like the ray itself
    uv = src.project(pts, distort=True)
    iu = np.round(uv[:, 0]).astype(np.int64)
    iv = np.round(uv[:, 1]).astype(np.int64)
    inside = (iu >= 0) & (iu < src.width) & (iv >= 0) & (iv < src.height)
    iu = np.clip(iu, 0, src.width - 1)
    iv = np.clip(iv, 0, src.height - 1)
    out = np.empty((labels.shape[0], dst.height, dst.width), np.int32)
    for t in range(labels.shape[0]):
        samp = np.where(inside, np.asarray(labels[t])[iv, iu], -1).reshape(-1, s * s)
        # Most frequent label per pixel: sort each row, count runs.
        srt = np.sort(samp, axis=1)
        best = srt[:, 0].copy()
        best_n = np.ones(srt.shape[0], np.int64)
        run = np.ones(srt.shape[0], np.int64)
        for k in range(1, s * s):
            same = srt[:, k] == srt[:, k - 1]
            run = np.where(same, run + 1, 1)
            better = run > best_n
            best = np.where(better, srt[:, k], best)
            best_n = np.where(better, run, best_n)
        out[t] = best.reshape(dst.height, dst.width)
    return out
