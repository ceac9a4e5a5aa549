"""Triangulated bubble centres from the masks: sub-pixel silhouette centroids of each
view, triangulated, checked for agreement between the views
([docs/method.md §4.3](../../docs/method.md#43-triangulated-centres)).

Two views constrain a bubble's centre well (its silhouettes' centroids are its
centroid's projections, to first order) and its extent along their bisector poorly.
The fit takes each bubble's position and velocity from these centres
(:mod:`surfphase.fit.outputs`), and the mask stage drops instance pairs whose centres
the two views do not agree on (``consistent`` of :func:`anchor_table`). A silhouette
that touches the image border (:func:`border_ids`) gives no centre.

Pixels per docs/conventions.md §4; cameras are the undistorted cameras of the label
stacks' pixel grid.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np
import pandas as pd
from scipy import ndimage as ndi

from surfphase.cameras import Camera, triangulate

#: Parameters (config ``masks: anchors:``).
ANCHOR_DEFAULTS: dict = {
    # Width (pixels) of the band around each mask whose partial darkness counts as
    # partial cover (anti-aliased, blurred edges): 0 = the binary mask's centroid.
    "ring_px": 2,
    # Two views agree on a bubble when its triangulated centre reprojects within this
    # many pixels of both silhouette centroids ...
    "max_reproj_px": 1.0,
    # ... and the sizes its two silhouettes give at that centre (equivalent radius ×
    # distance / focal length) differ by at most this factor.
    "max_size_ratio": 1.3,
    # A bubble whose triangulated centre moves slower than this (m/s; the least-squares
    # speed over its frames, at least 3) is a static feature of the scene (a speck on
    # the plate or the window), not a free bubble: buoyancy lifts a free bubble of 0.1 mm
    # diameter in water at about 5 mm/s, larger ones faster. 0 keeps them all.
    "min_speed_mps": 0.005,
}

ANCHOR_COLUMNS = ["frame", "bubble", "x", "y", "z", "reproj_px", "size_ratio", "consistent"]


def coverage_centroids(
    contrast: np.ndarray, labels: np.ndarray, ring_px: int = 2
) -> dict[int, tuple[float, float, float]]:
    """Sub-pixel centroid of every labelled region of one frame.

    A silhouette's binary mask quantises its outline to whole pixels. Its edge pixels
    are partly covered and, in a backlit image, partly dark, so each pixel of the band
    within ``ring_px`` of the mask's outline (and not inside another region) is
    weighted by its relative darkness over the typical darkness of the mask's own edge
    pixels (the 75th percentile), clipped to [0, 1]; interior pixels weigh 1. A band
    pixel counts for the region nearest to it only, so two bubbles close together do not
    share their edges' darkness.

    Args:
        contrast: (H, W) relative darkness in [0, 1]
            (:func:`surfphase.masks.classical.relative_contrast`).
        labels: (H, W) int, −1 background, ≥ 0 region ids.
        ring_px: band width, pixels (0: binary centroids).

    Returns:
        ``{id: (u, v, area)}``: centroid in pixels (column, row) and the weighted area
        (pixels²).
    """
    lab = np.asarray(labels)
    c = np.asarray(contrast, dtype=np.float64)
    out: dict[int, tuple[float, float, float]] = {}
    ids = np.unique(lab[lab >= 0])
    owner = lab
    if ring_px > 0 and len(ids):
        _, (ri, ci) = ndi.distance_transform_edt(lab < 0, return_indices=True)
        owner = lab[ri, ci]
    for b in ids:
        m = lab == b
        ys, xs = np.nonzero(m)
        pad = int(ring_px) + 1
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, lab.shape[0])
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, lab.shape[1])
        mm, cc, ll = m[y0:y1, x0:x1], c[y0:y1, x0:x1], owner[y0:y1, x0:x1]
        w = mm.astype(np.float64)
        if ring_px > 0:
            inner = ndi.binary_erosion(mm)
            edge = mm & ~inner
            band = ndi.binary_dilation(mm, iterations=int(ring_px)) & ~inner & (ll == b)
            ref = float(np.percentile(cc[edge], 75)) if edge.any() else 0.0
            if ref > 1e-3 and inner.any():
                w = np.where(inner, 1.0, np.where(band, np.clip(cc / ref, 0.0, 1.0), 0.0))
        s = float(w.sum())
        vv, uu = np.mgrid[y0:y1, x0:x1]
        out[int(b)] = (float((w * uu).sum() / s), float((w * vv).sum() / s), s)
    return out


def border_ids(labels: np.ndarray, margin_px: int = 1) -> set[int]:
    """Ids (≥ 0) of the regions of an (H, W) label image within ``margin_px`` pixels of
    the image border: their silhouettes may be cut by the frame, so their centroids are
    not their centres' projections."""
    lab = np.asarray(labels)
    m = int(margin_px)
    edge = np.concatenate(
        [lab[:m].ravel(), lab[-m:].ravel(), lab[:, :m].ravel(), lab[:, -m:].ravel()]
    )
    return {int(b) for b in np.unique(edge[edge >= 0])}


def apparent_size(cam: Camera, X: np.ndarray, area_px: float) -> float:
    """Equivalent radius (m) of a silhouette of ``area_px`` pixels² seen at point ``X``
    (m, lab frame): ``sqrt(area / π) · depth / f``."""
    depth = float((cam.world_to_camera(np.asarray(X, np.float64)[None]))[0, 2])
    f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
    return float(np.sqrt(area_px / np.pi) * depth / f)


def anchor_table(
    cameras: Sequence[Camera],
    centroids: Sequence[Sequence[Mapping[int, tuple[float, float, float]]]],
    frames: np.ndarray,
    params: Mapping | None = None,
) -> pd.DataFrame:
    """Triangulated centre of every bubble (id ≥ 1) that the first two views both see.

    Args:
        cameras: the two views' undistorted cameras.
        centroids: per view, per frame position, :func:`coverage_centroids`' dict.
        frames: (T,) session frame index of each position.
        params: overrides of :data:`ANCHOR_DEFAULTS`.

    Returns:
        :data:`ANCHOR_COLUMNS`: centre (m, lab frame), the larger reprojection error of
        the two centroids (pixels), the ratio of the two apparent sizes (≥ 1) and whether
        both are within the limits.
    """
    p = {**ANCHOR_DEFAULTS, **(params or {})}
    ca, cb = cameras[0], cameras[1]
    rows = []
    for k, f in enumerate(np.asarray(frames, dtype=np.int64)):
        a, b = centroids[0][k], centroids[1][k]
        for bid in sorted(set(a) & set(b)):
            if bid < 1:
                continue
            ua, ub = np.array([a[bid][:2]]), np.array([b[bid][:2]])
            X = triangulate([ca, cb], [ua, ub])[0]
            rep = max(
                float(np.linalg.norm(ca.project(X[None])[0] - ua[0])),
                float(np.linalg.norm(cb.project(X[None])[0] - ub[0])),
            )
            sa, sb = apparent_size(ca, X, a[bid][2]), apparent_size(cb, X, b[bid][2])
            ratio = max(sa, sb) / max(min(sa, sb), 1e-12)
            ok = rep <= float(p["max_reproj_px"]) and ratio <= float(p["max_size_ratio"])
            rows.append((int(f), int(bid), *map(float, X), rep, ratio, bool(ok)))
    return pd.DataFrame(rows, columns=ANCHOR_COLUMNS)


def track_speeds(table: pd.DataFrame, fps: float, min_frames: int = 3) -> dict[int, float]:
    """Least-squares speed (m/s) of each bubble's centre over its frames.

    Args:
        table: ``frame, bubble, x, y, z`` (m) centres (:func:`anchor_table`'s consistent
            rows), any frames.
        fps: frame rate (frames per second) of the session's frame indices.
        min_frames: bubbles with fewer frames get no speed (too few to tell).

    Returns:
        ``{bubble: |slope|}`` of the straight line fitted to the centre against time
        (s), for bubbles ≥ 1 with at least ``min_frames`` frames.
    """
    out: dict[int, float] = {}
    for b, g in table.groupby("bubble"):
        if int(b) < 1 or len(g) < int(min_frames):
            continue
        t = g["frame"].to_numpy(np.float64) / float(fps)
        X = g[["x", "y", "z"]].to_numpy(np.float64)
        tc = t - t.mean()
        slope = (tc[:, None] * (X - X.mean(axis=0))).sum(axis=0) / float((tc**2).sum())
        out[int(b)] = float(np.linalg.norm(slope))
    return out


def downsample_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) int labels (−1 background) → (h, w) = ``size[::-1]`` labels of the
    downscaled frame: each output pixel takes the region covering most of it
    (area-averaged cover, ``cv2.INTER_AREA`` as the ingest's frames), background where
    no region covers half of it."""
    lab = np.asarray(labels)
    w, h = int(size[0]), int(size[1])
    out = np.full((h, w), -1, np.int32)
    best = np.full((h, w), 0.5, np.float32)
    for b in np.unique(lab[lab >= 0]):
        cover = cv2.resize((lab == b).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        take = cover > best
        out[take] = int(b)
        best[take] = cover[take]
    return out
