"""Bubble guidance (docs/method.md §5.4): bind surfels to bubbles, bubble centroids and
velocities, and advection of each bubble's surfels to initialise the next frame.

Bubble ids are those of the masks: ``-1`` background (a surfel bound to no bubble),
``0`` the nucleation region at the heated plate, ``1, 2, …`` bubbles, consistent across
views and time. Positions in metres (lab frame), times in seconds, velocities in m/s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from surfphase.cameras import Camera


def view_order(labels: Sequence[np.ndarray]) -> list[int]:
    """Order in which views are visited: most valid masks (distinct bubble ids) first.

    Ties are broken by the number of foreground pixels, then by view index.
    """
    keys = []
    for i, lab in enumerate(labels):
        ids = np.unique(lab[lab >= 0])
        keys.append((-len(ids), -int((lab >= 0).sum()), i))
    return [k[2] for k in sorted(keys)]


def bind_surfels_to_bubbles(
    means: np.ndarray,
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
) -> np.ndarray:
    """Bubble id of each surfel from the masks it projects into.

    Views are visited in :func:`view_order`; in each, surfels not yet bound whose centre
    projects (nearest pixel, undistorted pinhole) onto a bubble mask take that bubble's
    id. Surfels bound in an earlier view are skipped.

    Args:
        means: (N, 3) surfel centres, metres.
        cameras: one undistorted :class:`Camera` per view, matching ``labels``.
        labels: per view an (H, W) int mask, ``-1`` background.

    Returns:
        (N,) int32 bubble ids, ``-1`` where no view binds the surfel.
    """
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    out = np.full(means.shape[0], -1, dtype=np.int32)
    for v in view_order(labels):
        cam, lab = cameras[v], labels[v]
        free = out < 0
        if not free.any():
            break
        idx = np.nonzero(free)[0]
        z = cam.world_to_camera(means[idx])[:, 2]
        uv = cam.project(means[idx], distort=False)
        col = np.rint(uv[:, 0]).astype(np.int64)
        row = np.rint(uv[:, 1]).astype(np.int64)
        H, W = lab.shape
        ok = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        hit = np.full(idx.shape[0], -1, dtype=np.int32)
        hit[ok] = lab[row[ok], col[ok]]
        out[idx] = hit
    return out


def surfel_weights(opacity: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Centroid weights ``w_i = o_i · s_x · s_y``: opacity (N,) times area (N, 2 scales, m)."""
    return np.asarray(opacity, dtype=np.float64) * np.prod(np.asarray(scales, np.float64), axis=1)


def bubble_centroids(
    means: np.ndarray, bubble: np.ndarray, weights: np.ndarray
) -> dict[int, np.ndarray]:
    """Weighted centroid ``c_b = Σ w_i μ_i / Σ w_i`` of each bubble ``b ≥ 0``.

    Args:
        means: (N, 3) positions, metres.
        bubble: (N,) bubble ids (``-1`` ignored).
        weights: (N,) non-negative weights.

    Returns:
        ``{b: (3,) centroid}`` for every bubble with positive total weight.
    """
    means = np.asarray(means, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    out: dict[int, np.ndarray] = {}
    for b in np.unique(bubble):
        if b < 0:
            continue
        sel = bubble == b
        w = weights[sel]
        if w.sum() <= 0:
            continue
        out[int(b)] = (w[:, None] * means[sel]).sum(axis=0) / w.sum()
    return out


def bubble_velocities(
    means_prev: np.ndarray,
    means_next: np.ndarray,
    bubble: np.ndarray,
    weights: np.ndarray,
    dt: float,
) -> dict[int, np.ndarray]:
    """Finite-difference bubble velocities (m/s) from two surfel position sets.

    The same surfels (same ``bubble`` binding and ``weights``) are used at both times,
    so a change of which surfels belong to a bubble never shows up as motion:
    ``v_b = (c_b(next) − c_b(prev)) / dt``.

    Args:
        means_prev, means_next: (N, 3) positions of the same surfels, metres.
        bubble: (N,) bubble ids; weights: (N,) centroid weights.
        dt: time between the two position sets, seconds.
    """
    if dt <= 0:
        raise ValueError(f"bubble_velocities: dt must be positive, got {dt}")
    c0 = bubble_centroids(means_prev, bubble, weights)
    c1 = bubble_centroids(means_next, bubble, weights)
    return {b: (c1[b] - c0[b]) / dt for b in c1 if b in c0}


def advect(
    means: np.ndarray,
    bubble: np.ndarray,
    bubble_velocity: dict[int, np.ndarray],
    surfel_velocity: np.ndarray,
    dt: float,
    per_surfel_ids: Sequence[int] = (0,),
) -> np.ndarray:
    """Move surfels by their bubble's velocity to initialise the next frame.

    Surfels of bubble ``b`` move by ``bubble_velocity[b]·dt``; those of bubbles in
    ``per_surfel_ids`` (the nucleation region, 0) and of bubbles without a velocity
    move by their own ``surfel_velocity``; unbound surfels (``-1``) stay.

    Args:
        means: (N, 3) positions, metres.
        bubble: (N,) bubble ids.
        bubble_velocity: ``{b: (3,) m/s}``.
        surfel_velocity: (N, 3) per-surfel velocities, m/s.
        dt: time step, seconds.

    Returns:
        (N, 3) advected positions, metres.
    """
    means = np.asarray(means, dtype=np.float64)
    vel = np.zeros_like(means)
    for b in np.unique(bubble):
        if b < 0:
            continue
        sel = bubble == b
        if int(b) in per_surfel_ids or int(b) not in bubble_velocity:
            vel[sel] = surfel_velocity[sel]
        else:
            vel[sel] = bubble_velocity[int(b)]
    return means + vel * dt


def track_continues(
    bubble_a: np.ndarray,
    bubble_b: np.ndarray,
    weights_a: np.ndarray,
    weights_b: np.ndarray,
    b: int,
    min_share: float = 0.75,
) -> int | None:
    """The bubble that continues bubble ``b`` from one frame to the next, if any.

    Bubble ids of the masks can change from frame to frame, and bubbles merge, so a
    bubble's track is followed through its surfels: ``b`` at frame A continues as ``q``
    at frame B when more than ``min_share`` of ``b``'s surfel weight (at A) is bound to
    ``q`` at B, and more than ``min_share`` of ``q``'s surfel weight (at B) was bound to
    ``b`` at A. A merge (``q`` drawn from two bubbles), a split, or a bubble leaving or
    joining the nucleation region ends the track. The same function runs backwards in
    time with the arguments swapped.

    Args:
        bubble_a, bubble_b: (N,) bubble ids of the same surfels at the two frames
            (``-1`` unbound; surfels that do not exist at a frame: ``-1`` there and
            weight 0).
        weights_a, weights_b: (N,) centroid weights at the two frames.
        b: the bubble at frame A.
        min_share: the fraction of weight that must be exceeded both ways. 0.75: a
            merge of two bubbles ends both tracks unless one is at least 3× the other's
            weight; a few stray or unbound surfels do not.

    Returns:
        The id of the continuing bubble at frame B, or ``None``.
    """
    wa = np.asarray(weights_a, np.float64)
    wb = np.asarray(weights_b, np.float64)
    sel = bubble_a == b
    tot = wa[sel].sum()
    if tot <= 0:
        return None
    ids, inv = np.unique(bubble_b[sel], return_inverse=True)
    share = np.bincount(inv.ravel(), weights=wa[sel], minlength=len(ids)) / tot
    k = int(np.argmax(share))
    q = int(ids[k])
    if q < 0 or share[k] <= min_share or (q == 0) != (b == 0):
        return None
    back = bubble_b == q
    tot_b = wb[back].sum()
    if tot_b <= 0 or wb[back & sel].sum() <= min_share * tot_b:
        return None
    return q
