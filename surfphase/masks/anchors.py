"""Triangulated bubble centres from the masks: sub-pixel silhouette centroids of each
view, triangulated, checked for agreement between the views
([docs/method.md §4.3](../../docs/method.md#43-triangulated-centres)).

Two views constrain a bubble's centre well (its silhouettes' centroids are its
centroid's projections, to first order) and its extent along their bisector poorly.
The fit takes each bubble's position and velocity from these centres
(:mod:`surfphase.fit.outputs`), and the mask stage drops instance pairs whose centres
the two views do not agree on (``consistent`` of :func:`anchor_table`). A silhouette
that touches the image border (:func:`border_ids`) is cut by the frame, so its centroid
is not its centre's projection: its centre and full area are those of the ellipse fitted
to its visible outline (:func:`cut_centres`) when enough of it is visible, else it has
no centre.

Pixels per docs/conventions.md §4; cameras are the undistorted cameras of the label
stacks' pixel grid.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence

import cv2
import numpy as np
import pandas as pd
from scipy import ndimage as ndi
from skimage.measure import find_contours

from surfphase.cameras import Camera, triangulate
from surfphase.masks.classical import fill_holes_to_border
from surfphase.masks.params import ANCHOR_DEFAULTS

#: Fewest outline points an outline fit takes (a conic has 5 degrees of freedom).
_MIN_OUTLINE_POINTS = 8
#: :func:`moving_sphere`'s prior on the velocity (m/s): each component costs as much as
#: one outline point 1 pixel off per this speed. It decides what the outlines leave free
#: (along a view's ray where the other view shows no outline) and weighs little against
#: what they measure, tens to hundreds of points (an analytic sphere at 0.3 m/s is
#: found to within 1 % of its radius: tests/test_masks_anchors.py).
_SPHERE_SPEED_SCALE = 1.0

ANCHOR_COLUMNS = [
    "frame", "bubble", "x", "y", "z", "reproj_px", "size_ratio", "r_m", "cut", "consistent"
]  # fmt: skip


def _crop(mask: np.ndarray, pad: int) -> tuple[slice, slice]:
    """The (rows, columns) slices of ``mask``'s bounding box grown by ``pad`` pixels,
    clipped to the image."""
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return (
        slice(max(int(ys.min()) - pad, 0), min(int(ys.max()) + pad + 1, h)),
        slice(max(int(xs.min()) - pad, 0), min(int(xs.max()) + pad + 1, w)),
    )


#: Fewest edge pixels of a silhouette on one background (plate or backlight) that set
#: that part's own darkness reference in :func:`_cover_weights`.
_MIN_PART_EDGE = 3


def _cover_weights(
    mask: np.ndarray,
    contrast: np.ndarray,
    own: np.ndarray,
    ring_px: int,
    static: np.ndarray | None = None,
) -> np.ndarray:
    """Per-pixel cover (0..1) of one region in a crop: 1 inside ``mask`` (bool (h, w)),
    and on its edge and the band of ``ring_px`` pixels about it (where ``own``, the
    pixels nearer to this region than to any other) the relative darkness
    ``contrast`` over the 75th percentile of the mask's edge pixels' darkness, clipped
    to [0, 1]; the binary mask where ``ring_px`` is 0 or there is no edge contrast.

    ``static`` ((h, w) bool, the plate's image): a silhouette seen partly in front of
    the plate has a darkness there relative to the plate, less than against the
    backlight, so the pixels on the plate and those off it each take the percentile of
    their own edge pixels (where at least :data:`_MIN_PART_EDGE` of them lie on that
    background, else the whole edge's): one reference weighed the part in front of the
    plate light, and the centroid of a bubble rising from it drifted up (0.3–0.5 px)."""
    w = mask.astype(np.float64)
    if ring_px <= 0:
        return w
    inner = ndi.binary_erosion(mask)
    edge = mask & ~inner
    band = ndi.binary_dilation(mask, iterations=int(ring_px)) & ~inner & own
    ref = float(np.percentile(contrast[edge], 75)) if edge.any() else 0.0
    if ref > 1e-3 and inner.any():
        refs = np.full(mask.shape, ref)
        if static is not None and (edge & static).any():
            for part in (static, ~static):
                if (edge & part).sum() >= _MIN_PART_EDGE:
                    refs[part] = max(float(np.percentile(contrast[edge & part], 75)), 1e-3)
        w = np.where(inner, 1.0, np.where(band, np.clip(contrast / refs, 0.0, 1.0), 0.0))
    return w


def coverage_centroids(
    contrast: np.ndarray,
    labels: np.ndarray,
    ring_px: int = ANCHOR_DEFAULTS["ring_px"],
    static: np.ndarray | None = None,
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
        static: (H, W) bool image of the plate, whose edge pixels take their own
            darkness reference (:func:`_cover_weights`), or ``None``.

    Returns:
        ``{id: (u, v, area)}``: centroid in pixels (column, row) and the weighted area
        (pixels²).
    """
    lab = np.asarray(labels)
    c = np.asarray(contrast, dtype=np.float64)
    out: dict[int, tuple[float, float, float]] = {}
    ids = np.unique(lab[lab >= 0])
    owner = region_owners(lab, ring_px) if len(ids) else lab
    for b in ids:
        m = lab == b
        sl = _crop(m, int(ring_px) + 1)
        st = None if static is None else np.asarray(static)[sl]
        w = _cover_weights(m[sl], c[sl], owner[sl] == b, ring_px, st)
        s = float(w.sum())
        vv, uu = np.mgrid[sl]
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


def silhouette_pieces(lab: np.ndarray, b: int) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Connected pieces (8-connected) of id ``b`` in one (H, W) label image: per piece
    its (2,) centroid (u, v) pixels, its area (pixels) and its (H, W) bool mask."""
    from scipy import ndimage as ndi

    comp, n = ndi.label(lab == b, structure=np.ones((3, 3), bool))
    out = []
    for k in range(1, n + 1):
        m = comp == k
        r, c = np.nonzero(m)
        out.append((np.array([c.mean(), r.mean()]), float(len(r)), m))
    return out


def pair_sphere(cameras: Sequence[Camera], uvs: Sequence[np.ndarray], areas: Sequence[float]):
    """Two silhouettes' centroids ``uvs`` ((2,) px each) and areas (px) triangulated:
    (centre (3,) m, mean radius m, largest reprojection error over the view's equivalent
    radius, ratio of the larger to the smaller radius); None where the point is behind a
    view or not finite."""
    X = triangulate(list(cameras[:2]), [np.asarray(u)[None] for u in uvs])[0]
    if not np.all(np.isfinite(X)):
        return None
    radii, errs = [], []
    for cam, uv, a in zip(cameras[:2], uvs, areas, strict=True):
        z = float(cam.world_to_camera(X[None])[0, 2])
        if z <= 0:
            return None
        r_px = np.sqrt(a / np.pi)
        radii.append(r_px * z / float(np.sqrt(cam.K[0, 0] * cam.K[1, 1])))
        errs.append(float(np.linalg.norm(cam.project(X[None], distort=False)[0] - uv)) / r_px)
    return X, float(np.mean(radii)), max(errs), max(radii) / max(min(radii), 1e-12)


#: The id of the nucleation region, which holds every attached bubble.
NUCLEATION_ID = 0
#: Two pieces of one id (the nucleation region), one per view, are the same object
#: when their centroids triangulate to a point that reprojects within this fraction of each
#: piece's equivalent radius ...
PIECE_REPROJ_R = 0.25
#: ... and the radii the two pieces give at that point differ by at most this factor.
PIECE_SIZE_RATIO = 1.5


def pieces_agree(sp: tuple | None) -> bool:
    """Whether two pieces are one object by the rule of the nucleation region's pieces:
    their :func:`pair_sphere` ``sp`` exists, reprojects within :data:`PIECE_REPROJ_R`
    of each piece's equivalent radius, and the radii they give differ by at most
    :data:`PIECE_SIZE_RATIO`."""
    return sp is not None and sp[2] <= PIECE_REPROJ_R and sp[3] <= PIECE_SIZE_RATIO


def agreeing_pieces(
    cameras: Sequence[Camera], lab0: np.ndarray, lab1: np.ndarray, b: int
) -> list[tuple[np.ndarray, float, np.ndarray, np.ndarray]]:
    """The pairs of pieces of id ``b``, one from each of two views' (H, W) labels, that
    are the same object: their centroids triangulate (undistorted ``cameras``) to a
    point that reprojects within :data:`PIECE_REPROJ_R` of each piece's equivalent
    radius, and the radii they give there differ by at most :data:`PIECE_SIZE_RATIO`;
    best agreeing first, each piece in one pair, and the point above the plate (lab y >
    0: what of an attached bubble the views see is above it). Per pair: ``(centre (3,)
    m, radius m, mask in view 0, mask in view 1)``. The nucleation region holds every
    attached bubble, and two views need not hold the same pieces of it (a speck on the
    plate's edge in one view, a bubble hidden in the other). Sites along the plate's
    edge lie on nearly one epipolar line: a piece of one site and a piece of another,
    across the views, can agree in size and reproject better than either site's own
    pair, their point millimetres in front of or behind them, and under the plate or
    above it."""
    p0, p1 = silhouette_pieces(lab0, b), silhouette_pieces(lab1, b)
    cands = []
    for i, (u0, a0, _) in enumerate(p0):
        for j, (u1, a1, _) in enumerate(p1):
            sp = pair_sphere(cameras, [u0, u1], [a0, a1])
            if pieces_agree(sp) and sp[0][1] > 0:
                cands.append((sp[2], i, j, sp))
    used0, used1, out = set(), set(), []
    for _, i, j, sp in sorted(cands, key=lambda x: x[:3]):
        if i not in used0 and j not in used1:
            used0.add(i)
            used1.add(j)
            out.append((sp[0], sp[1], p0[i][2], p1[j][2]))
    return out


def sphere_image(cam: Camera, X: np.ndarray, r: float) -> tuple[float, float, float] | None:
    """The circle ``(u, v, ρ)`` (pixels) of a sphere of centre ``X`` (m, lab frame) and
    radius ``r`` (m) in the undistorted ``cam``: its centre's projection and
    ``ρ = f·r / depth`` (the inverse of :func:`apparent_size`); None behind the camera."""
    X = np.asarray(X, np.float64)[None]
    z = float(cam.world_to_camera(X)[0, 2])
    if z <= 0:
        return None
    u, v = cam.project(X, distort=False)[0]
    return float(u), float(v), float(np.sqrt(cam.K[0, 0] * cam.K[1, 1])) * float(r) / z


def circle_sphere(
    cam: Camera, u: float, v: float, area: float, depth: float
) -> tuple[np.ndarray, float]:
    """The sphere ((3,) centre m, radius m) whose image in the undistorted ``cam`` is the
    circle of centre (``u``, ``v``) pixels and ``area`` pixels², at ``depth`` m
    (the inverse of :func:`sphere_image`)."""
    f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
    ray = cam.R.T @ np.linalg.solve(cam.K, np.array([u, v, 1.0]))
    X = np.asarray(cam.center, np.float64) + float(depth) * ray / float((cam.R @ ray)[2])
    return X, float(np.sqrt(area / np.pi)) * float(depth) / f


def apparent_size(cam: Camera, X: np.ndarray, area_px: float) -> float:
    """Equivalent radius (m) of a silhouette of ``area_px`` pixels² seen at point ``X``
    (m, lab frame): ``sqrt(area / π) · depth / f``."""
    depth = float((cam.world_to_camera(np.asarray(X, np.float64)[None]))[0, 2])
    f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
    return float(np.sqrt(area_px / np.pi) * depth / f)


def pair_agreement(
    cameras: Sequence[Camera], a: tuple[float, float, float], b: tuple[float, float, float]
) -> tuple[np.ndarray, float, float, float]:
    """The triangulated centre X (3,) m of one bubble's two silhouette entries ``(u, v,
    area)`` (pixels, pixels²) in the two views, the larger reprojection error of the two
    centres (pixels), the ratio of the two apparent sizes at X (≥ 1) and the two
    silhouettes' mean equivalent radius ``sqrt(area / π)`` (pixels)."""
    ca, cb = cameras[0], cameras[1]
    ua, ub = np.array([a[:2]], np.float64), np.array([b[:2]], np.float64)
    X = triangulate([ca, cb], [ua, ub])[0]
    rep = max(
        float(np.linalg.norm(ca.project(X[None])[0] - ua[0])),
        float(np.linalg.norm(cb.project(X[None])[0] - ub[0])),
    )
    sa, sb = apparent_size(ca, X, a[2]), apparent_size(cb, X, b[2])
    r_px = 0.5 * (np.sqrt(max(a[2], 0.0) / np.pi) + np.sqrt(max(b[2], 0.0) / np.pi))
    return X, rep, max(sa, sb) / max(min(sa, sb), 1e-12), float(r_px)


def views_agree(rep: float, ratio: float, r_px: float, params: Mapping) -> bool:
    """Whether two views agree on a bubble (:func:`pair_agreement`'s reprojection error
    ``rep`` and mean equivalent radius ``r_px``, pixels, and size ratio ``ratio``): the
    error within ``max_reproj_px`` or ``max_reproj_r`` of the radius, whichever is
    larger, and the ratio within ``max_size_ratio`` (``params``: :data:`ANCHOR_DEFAULTS`'
    keys)."""
    limit = max(float(params["max_reproj_px"]), float(params["max_reproj_r"]) * r_px)
    return rep <= limit and ratio <= float(params["max_size_ratio"])


def anchor_table(
    cameras: Sequence[Camera],
    centroids: Sequence[Sequence[Mapping[int, tuple[float, float, float]]]],
    frames: np.ndarray,
    params: Mapping | None = None,
    cut: Sequence[Sequence[set[int]]] | None = None,
    young: Mapping[int, set[int]] | None = None,
) -> pd.DataFrame:
    """Triangulated centre of every bubble (id ≥ 1) that the first two views both see.

    Args:
        cameras: the two views' undistorted cameras.
        centroids: per view, per frame position, ``{id: (u, v, area)}``: the
            silhouette's centre (pixels) and area (pixels²), :func:`coverage_centroids`'
            or, for a silhouette the border cuts, :func:`cut_centres`' (fitted full area).
        frames: (T,) session frame index of each position.
        params: overrides of :data:`ANCHOR_DEFAULTS`.
        cut: per view, per frame position, the ids whose entry came from
            :func:`cut_centres` (default: none).
        young: frame position → ids of bubbles just born of a merge, held to
            ``max_reproj_px`` alone: two lobes whose silhouettes overlap differently in
            each view are not one deformed bubble (default: none).

    Returns:
        :data:`ANCHOR_COLUMNS`: centre (m, lab frame), the larger reprojection error of
        the two centres (pixels), the ratio of the two apparent sizes (≥ 1), their mean
        (``r_m``, m: :func:`apparent_size`, the whole silhouette's where fitted), whether
        either view's centre came from an outline fit (``cut``) and whether both are
        within the limits (:func:`views_agree`). Fitted and measured centres pass the
        same test.
    """
    p = {**ANCHOR_DEFAULTS, **(params or {})}
    ca, cb = cameras[0], cameras[1]
    rows = []
    for k, f in enumerate(np.asarray(frames, dtype=np.int64)):
        a, b = centroids[0][k], centroids[1][k]
        fitted = set().union(*(views[k] for views in cut)) if cut is not None else set()
        for bid in sorted(set(a) & set(b)):
            if bid < 1:
                continue
            X, rep, ratio, r_px = pair_agreement((ca, cb), a[bid], b[bid])
            lobes = young is not None and bid in young.get(k, ())
            ok = views_agree(rep, ratio, 0.0 if lobes else r_px, p)
            r_m = 0.5 * (apparent_size(ca, X, a[bid][2]) + apparent_size(cb, X, b[bid][2]))
            rows.append(
                (int(f), int(bid), *map(float, X), rep, ratio, r_m, bid in fitted, bool(ok))
            )
    return pd.DataFrame(rows, columns=ANCHOR_COLUMNS)


def visible_shares(
    table: pd.DataFrame,
    centroids: Sequence[Sequence[Mapping[int, tuple[float, float, float]]]],
    cut: Sequence[Sequence[set[int]]],
    labels: Sequence[np.ndarray],
    frames: np.ndarray,
) -> np.ndarray:
    """(R,) each :func:`anchor_table` row's visible share: over the two views whose
    centre came from an outline fit (``cut``: the frame's border or a bubble in front
    hides part of the silhouette), the least of its silhouette's pixel count in that
    view's (T, H, W) ``labels`` over the fitted whole area (``centroids``' third entry,
    pixels²), at most 1; 1 where neither view's centre was fitted. A centre fitted to a
    short arc moves with the bubble's shape modes as well as its centre."""
    out = np.ones(len(table))
    pos = {int(f): k for k, f in enumerate(np.asarray(frames, np.int64))}
    for i, (f, b) in enumerate(zip(table["frame"], table["bubble"], strict=True)):
        k, b = pos[int(f)], int(b)
        for v in (0, 1):
            if b in cut[v][k] and b in centroids[v][k]:
                area = float(centroids[v][k][b][2])
                seen = float(np.count_nonzero(np.asarray(labels[v][k]) == b))
                if area > 0:
                    out[i] = min(out[i], seen / area)
    return np.minimum(out, 1.0)


def low_bottoms(
    table: pd.DataFrame,
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    frames: np.ndarray,
    height: float,
) -> np.ndarray:
    """(R,) bool: each row of an :func:`anchor_table` whose silhouette bottoms (the
    lowest row of the bubble's pixels in each of the two views' (T, H, W) ``labels``,
    at its mean column) triangulate to within ``height`` metres of the plate (lab
    y = 0). Such a bubble has just left the plate: its silhouette still merges with the
    plate's image and its centroid is not its centre's projection."""
    out = np.zeros(len(table), bool)
    pos = {int(f): k for k, f in enumerate(np.asarray(frames, np.int64))}
    rows = pd.DataFrame(
        {"k": [pos[int(f)] for f in table["frame"]], "b": table["bubble"].to_numpy(np.int64)}
    )
    for k, group in rows.groupby("k"):
        bottoms = []
        for lab in labels:
            frame = np.asarray(lab[int(k)])
            boxes = ndi.find_objects(frame + 1)  # box of id b at index b
            uv = np.full((len(group), 2), np.nan)
            for i, b in enumerate(group["b"].astype(int)):
                box = boxes[b] if 0 <= b < len(boxes) else None
                if box is None:
                    continue
                ys, xs = np.nonzero(frame[box] == b)
                bot = ys.max()
                uv[i] = (xs[ys == bot].mean() + box[1].start, bot + box[0].start)
            bottoms.append(uv)
        ok = np.isfinite(bottoms[0]).all(1) & np.isfinite(bottoms[1]).all(1)
        if ok.any():
            y = triangulate(list(cameras), [bottoms[0][ok], bottoms[1][ok]])[:, 1]
            out[group.index.to_numpy()[ok]] = y < height
    return out


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


def region_owners(lab: np.ndarray, ring_px: int) -> np.ndarray:
    """Each pixel's nearest region id (the labels themselves where ``ring_px`` is 0)."""
    if ring_px <= 0:
        return lab
    _, (ri, ci) = ndi.distance_transform_edt(lab < 0, return_indices=True)
    return lab[ri, ci]


def visible_outline(
    contrast: np.ndarray,
    labels: np.ndarray,
    owner: np.ndarray,
    b: int,
    ring_px: int,
    margin_px: int = 1,
) -> tuple[np.ndarray, float] | None:
    """The visible outline of region ``b`` of one frame, for an outline fit.

    The sub-pixel half-cover line (level 0.5 of the cover weights of
    :func:`coverage_centroids`, marching squares) of the region, its bright core filled
    where the frame cuts it open; its points within ``margin_px`` of the outermost pixel
    centres (the frame's cut) or within ``ring_px`` + 1 pixels of another region (a
    shared edge) are left out.

    Args:
        contrast: (H, W) relative darkness in [0, 1]. labels: (H, W) int, −1 background.
        owner: (H, W) nearest region id of each pixel (:func:`region_owners`).
        b: the region. ring_px: band width of the cover weights, pixels.
        margin_px: as :func:`cut_centres`.

    Returns:
        ``(points, cover)``: (N, 2) kept outline points (pixels, column, row) and the
        region's cover-weighted area (pixels²); None without an outline.
    """
    lab = np.asarray(labels)
    h, w = lab.shape
    m = lab == b
    if not m.any():
        return None
    sl = _crop(m, int(ring_px) + 2)
    y0, y1, x0, x1 = sl[0].start, sl[0].stop, sl[1].start, sl[1].stop
    mm = fill_holes_to_border(m[sl], (y0 == 0, y1 == h, x0 == 0, x1 == w))
    cover = _cover_weights(mm, np.asarray(contrast, np.float64)[sl], owner[sl] == b, ring_px)
    lines = find_contours(np.pad(cover, 1), 0.5)  # closed: zero cover outside
    if not lines:
        return None
    pts = max(lines, key=len)[:, ::-1] + (x0 - 1.0, y0 - 1.0)  # (column, row)
    near = ndi.binary_dilation((lab[sl] >= 0) & (lab[sl] != b), iterations=int(ring_px) + 1)
    iy = np.clip(np.rint(pts[:, 1]).astype(int) - y0, 0, y1 - y0 - 1)
    ix = np.clip(np.rint(pts[:, 0]).astype(int) - x0, 0, x1 - x0 - 1)
    keep = (
        (pts[:, 0] >= margin_px)
        & (pts[:, 0] <= w - 1 - margin_px)
        & (pts[:, 1] >= margin_px)
        & (pts[:, 1] <= h - 1 - margin_px)
        & ~near[iy, ix]
    )
    return pts[keep], float(cover.sum())


def cut_centres(
    contrast: np.ndarray,
    labels: np.ndarray,
    ids: set[int],
    ring_px: int = ANCHOR_DEFAULTS["ring_px"],
    min_visible: float = ANCHOR_DEFAULTS["min_visible"],
    margin_px: int = 1,
    max_aspect: float = ANCHOR_DEFAULTS["max_cut_aspect"],
    max_area_error: float = ANCHOR_DEFAULTS["max_cut_area_error"],
) -> dict[int, tuple[float, float, float]]:
    """Centre and full area of each silhouette of ``ids`` that the image border cuts,
    from the ellipse fitted to the visible part of its outline
    (:func:`visible_outline`). A silhouette gets a centre where the fit has at least
    ``_MIN_OUTLINE_POINTS`` points, the visible (cover-weighted) area is at least
    ``min_visible`` of the fitted ellipse's, the ellipse's long axis is at most
    ``max_aspect`` times its short axis and its part inside the frame
    (:func:`ellipse_area_inside`) has the visible area to within ``max_area_error``: the
    short arc of a silhouette mostly outside the frame is fitted as a flat ellipse that
    closes just past the border, and its visible share then reads high (even above 1).

    Args:
        contrast: (H, W) relative darkness in [0, 1].
        labels: (H, W) int, −1 background, ≥ 0 region ids.
        ids: the regions to fit (those of :func:`border_ids`).
        ring_px: band width of the cover weights, pixels.
        min_visible: least fraction of the fitted silhouette's area inside the frame
            (above 1: no fits, no centres).
        margin_px: outline points less than this (pixels) inside the outermost pixel
            centres are the frame's cut, not the silhouette's outline.
        max_aspect: largest ratio of the fitted ellipse's long to short axis.
        max_area_error: largest relative difference between the ellipse's area inside
            the frame and the visible area.

    Returns:
        ``{id: (u, v, area)}``: the fitted ellipse's centre (pixels, column, row) and its
        area (pixels², the whole silhouette's, hidden part included).
    """
    lab = np.asarray(labels)
    out: dict[int, tuple[float, float, float]] = {}
    ids = {int(b) for b in ids if (lab == b).any()}
    if not ids or float(min_visible) > 1.0:
        return out
    owner = region_owners(lab, ring_px)
    for b in sorted(ids):
        vis = visible_outline(contrast, lab, owner, b, ring_px, margin_px)
        if vis is None or len(vis[0]) < _MIN_OUTLINE_POINTS:
            continue
        ell = outline_ellipse(vis[0])
        if ell is None or max(ell[2:4]) > float(max_aspect) * min(ell[2:4]):
            continue
        area = float(np.pi * ell[2] * ell[3])
        if vis[1] < float(min_visible) * area:
            continue
        inside = ellipse_area_inside(ell, lab.shape)
        if abs(inside - vis[1]) <= float(max_area_error) * vis[1]:
            out[b] = (ell[0], ell[1], area)
    return out


def ellipse_area_inside(
    ellipse: tuple[float, float, float, float, float], shape: tuple[int, int], step: float = 0.25
) -> float:
    """Area (pixels²) of an ellipse ``(u, v, a, b, angle)`` (:func:`outline_ellipse`)
    inside an image of ``shape`` (H, W), whose pixels span [−0.5, W − 0.5] ×
    [−0.5, H − 0.5]: counted on a grid of ``step`` pixels (error about the perimeter ×
    ``step`` / 6)."""
    u, v, a, b, _ = ellipse
    h, w = shape
    reach = max(a, b)
    x0, x1 = max(-0.5, u - reach), min(w - 0.5, u + reach)
    y0, y1 = max(-0.5, v - reach), min(h - 0.5, v + reach)
    if x1 <= x0 or y1 <= y0:
        return 0.0
    uu, vv = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step))
    return float(inside_ellipse(uu, vv, ellipse).sum() * step * step)


def inside_ellipse(
    u: np.ndarray, v: np.ndarray, e: tuple[float, float, float, float, float]
) -> np.ndarray:
    """Whether the points (u, v) (pixels, any matching shapes) are inside the ellipse
    ``e`` = ``(u, v, a, b, angle)`` (:func:`outline_ellipse`)."""
    cu, cv, a, b, ang = e
    t = np.radians(ang)
    du, dv = u - cu, v - cv
    x = du * np.cos(t) + dv * np.sin(t)  # along the first axis (cv2's width)
    y = -du * np.sin(t) + dv * np.cos(t)
    return (x / a) ** 2 + (y / b) ** 2 <= 1.0


def outline_ellipse(points: np.ndarray) -> tuple[float, float, float, float, float] | None:
    """``(u, v, a, b, angle)`` of the ellipse fitted to (N, 2) outline points (pixels;
    ``cv2.fitEllipse``): centre, semi-axes (pixels) and orientation (degrees); None
    where the fit fails or is degenerate."""
    try:
        (u, v), (da, db), ang = cv2.fitEllipse(np.asarray(points, np.float32))
    except cv2.error:
        return None
    if not np.isfinite([u, v, da, db, ang]).all() or min(da, db) <= 0:
        return None
    return float(u), float(v), float(da) / 2, float(db) / 2, float(ang)


def shape_centre(
    points: np.ndarray, shape: tuple[float, float, float, float, float]
) -> tuple[float, float, float] | None:
    """Centre of a known ellipse fitted to part of its outline: only the translation.

    Args:
        points: (N, 2) visible outline points, pixels (column, row), N ≥ 3.
        shape: ``(u, v, a, b, angle)`` of :func:`outline_ellipse`: the start centre, the
            semi-axes (pixels) and the orientation (degrees, ``cv2.fitEllipse``'s).

    Returns:
        ``(u, v, rms)``: the centre (pixels) minimising the points' radial distances to
        the ellipse (least squares, ``scipy.optimize.least_squares``) and their rms
        (pixels); None where it does not converge.
    """
    from scipy.optimize import least_squares

    u0, v0, a, b, ang = shape
    t = np.radians(ang)
    rot = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
    inv = np.diag([1.0 / a**2, 1.0 / b**2])
    A = rot.T @ inv @ rot
    scale = float(np.sqrt(a * b))
    P = np.asarray(points, np.float64)

    def resid(c):
        q = P - c
        return (np.sqrt(np.einsum("ni,ij,nj->n", q, A, q)) - 1.0) * scale

    best = None
    for start in (np.array([u0, v0]), P.mean(axis=0)):
        r = least_squares(resid, start, method="lm")
        if r.success and (best is None or r.cost < best.cost):
            best = r
    if best is None:
        return None
    rms = float(np.sqrt(np.mean(best.fun**2)))
    return float(best.x[0]), float(best.x[1]), rms


def nearest_whole(frames: Sequence[int], t: int, whole_at: Callable[[int], object]):
    """The shape ``whole_at(k)`` of the frame ``k`` ≠ ``t`` of ``frames`` nearest to
    ``t`` (the earlier of two as near) where it is not None; None when there is none."""
    for k in sorted((int(k) for k in frames if k != t), key=lambda k: (abs(k - t), k)):
        shape = whole_at(k)
        if shape is not None:
            return shape
    return None


def tracked_cut_centres(
    contrast_at: Callable[[int], np.ndarray],
    labels: np.ndarray,
    missing: Mapping[int, set[int]],
    ring_px: int = ANCHOR_DEFAULTS["ring_px"],
    min_visible: float = ANCHOR_DEFAULTS["min_visible_tracked"],
    max_rms: float = ANCHOR_DEFAULTS["max_shape_rms"],
    margin_px: int = 1,
) -> dict[int, dict[int, tuple[float, float, float]]]:
    """Centres of border-cut silhouettes too little inside the frame for an ellipse of
    their own, from the shape their track shows whole.

    A bubble that leaves (or enters) the frame is seen whole in other frames of the same
    view: the ellipse fitted to its outline in the nearest frame where the border does
    not cut it (:func:`outline_ellipse`) is its shape, and its centre in the cut frame is
    that ellipse moved onto the visible outline (:func:`shape_centre`). A centre is kept
    where the outline has at least ``_MIN_OUTLINE_POINTS`` points, their rms distance is
    at most ``max_rms`` of the ellipse's equivalent radius √(ab) and the visible
    (cover-weighted) area is at least ``min_visible`` of the ellipse's.

    Args:
        contrast_at: frame position → its (H, W) relative darkness in [0, 1] (called
            only for the frames a fit needs).
        labels: (T, H, W) int labels of the view, −1 background.
        missing: ``{position: ids}`` of the cut silhouettes without a centre.
        ring_px, margin_px: as :func:`cut_centres`.
        min_visible: least visible fraction of the moved ellipse.
        max_rms: largest rms distance of the outline to the moved ellipse, over its
            equivalent radius.

    Returns:
        ``{position: {id: (u, v, area)}}``: centre (pixels) and the shape's area
        (pixels²).
    """
    lab = np.asarray(labels)
    shapes: dict[tuple[int, int], tuple | None] = {}

    def whole(t: int, b: int):
        if (t, b) not in shapes:
            shapes[(t, b)] = None
            if b not in border_ids(lab[t]):
                vis = visible_outline(
                    contrast_at(t), lab[t], region_owners(lab[t], ring_px), b, ring_px
                )
                if vis is not None and len(vis[0]) >= _MIN_OUTLINE_POINTS:
                    shapes[(t, b)] = outline_ellipse(vis[0])
        return shapes[(t, b)]

    out: dict[int, dict[int, tuple[float, float, float]]] = {}
    wanted = set().union(*missing.values()) if missing else set()
    frames_of: dict[int, list[int]] = {}
    for k in range(lab.shape[0]):
        for b in set(np.unique(lab[k]).tolist()) & wanted:
            frames_of.setdefault(int(b), []).append(k)
    for t, ids in sorted(missing.items()):
        owner = None
        for b in sorted(ids):
            ref = nearest_whole(frames_of.get(b, []), t, lambda k, b=b: whole(k, b))
            if ref is None:
                continue
            owner = region_owners(lab[t], ring_px) if owner is None else owner
            vis = visible_outline(contrast_at(t), lab[t], owner, b, ring_px, margin_px)
            if vis is None or len(vis[0]) < _MIN_OUTLINE_POINTS:
                continue
            fit = shape_centre(vis[0], ref)
            area = float(np.pi * ref[2] * ref[3])
            rms_max = max_rms * float(np.sqrt(ref[2] * ref[3]))
            if fit is not None and fit[2] <= rms_max and vis[1] >= min_visible * area:
                out.setdefault(t, {})[b] = (fit[0], fit[1], area)
    return out


def lowest_point(rows: np.ndarray, cols: np.ndarray, reach: float) -> tuple[float, float]:
    """Sub-pixel lowest point ``(u, v)`` (pixels) of a silhouette given as its pixels'
    ``rows`` and ``cols`` (N,): the vertex of the parabola fitted to its bottom outline
    (each column's lowest pixel centre) over the columns whose lowest pixel lies within
    ``reach`` rows of the lowest row. The lowest row alone moves in whole pixels, while
    a bubble at 10,000 fps rises a tenth of one a frame. The lowest row's mean column and
    its row where fewer than 3 columns qualify or the vertex falls outside them (a flat
    bottom)."""
    rows, cols = np.asarray(rows), np.asarray(cols)
    low = int(rows.max())
    u, v = float(cols[rows == low].mean()), float(low)
    c0 = int(cols.min())
    edge = np.full(int(cols.max()) - c0 + 1, -1)
    np.maximum.at(edge, cols - c0, rows)
    us = np.flatnonzero(edge >= low - reach)
    if len(us) >= 3:
        mid = us.mean()
        a, b, c = np.polyfit(us - mid, edge[us], 2)
        if a < 0 and abs(b / (2 * a)) <= (us.max() - us.min()) / 2:
            u, v = float(c0 + mid - b / (2 * a)), float(c - b * b / (4 * a))
    return u, v


def circle_fit(points: np.ndarray) -> tuple[float, float, float] | None:
    """``(u, v, r)`` of the circle fitted to (N, 2) points (pixels; the algebraic
    least-squares fit of Kåsa: ``u² + v² + D u + E v + F = 0`` linear in D, E, F);
    None where N < 3 or the points are collinear."""
    P = np.asarray(points, np.float64)
    if len(P) < 3:
        return None
    c = P.mean(axis=0)
    Q = P - c  # centred, for conditioning
    A = np.c_[Q, np.ones(len(Q))]
    sol, *_ = np.linalg.lstsq(A, -(Q**2).sum(axis=1), rcond=None)
    u, v = -sol[0] / 2, -sol[1] / 2
    r2 = u * u + v * v - sol[2]
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return float(u + c[0]), float(v + c[1]), float(np.sqrt(r2))


def sphere_centres(
    cameras: Sequence[Camera],
    outlines: Sequence[np.ndarray | None],
    covers: Sequence[float],
    known: Sequence[tuple[float, float, float] | None] = (None, None),
    min_visible: float = ANCHOR_DEFAULTS["min_visible_sphere"],
    max_rms: float = ANCHOR_DEFAULTS["max_sphere_rms"],
) -> list[tuple[float, float, float]] | None:
    """The sphere that a bubble's visible outline in one or two views lies on.

    A bubble that the frame cuts in a view and that no frame of that view shows whole
    (it enters or leaves the frame at the session's start or end) has no centre there
    from :func:`cut_centres` or :func:`tracked_cut_centres`. Its silhouette in a view is
    close to the circle of centre X's projection and radius f·R / depth (sphere centre
    X, radius R); the fit minimises the visible outline points' radial distances to
    those circles (``scipy.optimize.least_squares``):

    * where the other view has the bubble's centre and area (``known``), X lies on that
      centre's ray and R is the area's equivalent radius at X's depth: one unknown, the
      depth along the ray, from the cut view's outline alone;
    * where neither view has one, X and R from both views' outlines at once, from the
      triangulated centres of each outline's circle (:func:`circle_fit`). A spheroid's
      arc bends less than its equivalent circle, so this centre drifts as less of the
      bubble is inside (about 0.1 r at 30 %).

    Args:
        cameras: the two views' undistorted cameras.
        outlines: per view, (N, 2) visible outline points (pixels, column, row;
            :func:`visible_outline`), at least ``_MIN_OUTLINE_POINTS`` where fitted;
            None (or anything) where ``known``.
        covers: per view, the silhouette's visible (cover-weighted) area, pixels².
        known: per view, the centre and area ``(u, v, area)`` it already has, or None.
        min_visible: least fraction of each fitted view's circle inside the frame.
        max_rms: largest rms radial distance of a fitted view's outline points to its
            circle, over the circle's radius.

    Returns:
        per view ``(u, v, area)``: the circle's centre (pixels) and area (pixels², the
        whole silhouette's), the ``known`` entry where given; None where an outline is
        too short, the fit fails or a fitted view's circle misses ``min_visible`` or
        ``max_rms``.
    """
    from scipy.optimize import least_squares

    cams = list(cameras)[:2]
    fitted = [k for k in (0, 1) if known[k] is None]
    if not fitted:
        return [tuple(map(float, k)) for k in known]
    pts = {k: np.asarray(outlines[k], np.float64).reshape(-1, 2) for k in fitted}
    if any(len(p) < _MIN_OUTLINE_POINTS for p in pts.values()):
        return None
    circles = {k: circle_fit(pts[k]) for k in fitted}
    if any(c is None for c in circles.values()):
        return None
    focal = [float(np.sqrt(c.K[0, 0] * c.K[1, 1])) for c in cams]
    start = [known[k][:2] if known[k] is not None else circles[k][:2] for k in (0, 1)]
    X0 = triangulate(cams, [np.array([u]) for u in start])[0]

    def depth(k: int, X: np.ndarray) -> float:
        return float(cams[k].world_to_camera(X[None])[0, 2])

    if not np.all(np.isfinite(X0)) or min(depth(k, X0) for k in (0, 1)) <= 0:
        return None

    if len(fitted) == 1:
        j = 1 - fitted[0]
        cam, (u, v, area) = cams[j], known[j]
        ray = cam.R.T @ np.linalg.solve(cam.K, np.array([u, v, 1.0]))
        ray /= np.linalg.norm(ray)
        x0 = np.array([float((X0 - cam.center) @ ray)])

        def sphere(x: np.ndarray) -> tuple[np.ndarray, float]:
            X = cam.center + x[0] * ray
            return X, apparent_size(cam, X, area)

        scale = np.array([max(x0[0], 1e-6) * 0.01])
    else:
        R0 = float(np.mean([circles[k][2] * depth(k, X0) / focal[k] for k in (0, 1)]))
        x0 = np.r_[X0, R0]

        def sphere(x: np.ndarray) -> tuple[np.ndarray, float]:
            return x[:3], float(x[3])

        scale = np.full(4, max(R0, 1e-6))

    def circle_of(k: int, x: np.ndarray) -> tuple[np.ndarray, float]:
        X, R = sphere(x)
        return cams[k].project(X[None], distort=False)[0], focal[k] * R / max(depth(k, X), 1e-9)

    def resid(x: np.ndarray) -> np.ndarray:
        out = []
        for k in fitted:
            c, r = circle_of(k, x)
            out.append(np.linalg.norm(pts[k] - c, axis=1) - r)
        return np.concatenate(out)

    fit = least_squares(resid, x0, x_scale=scale, method="lm")
    X, R = sphere(fit.x)
    if not fit.success or not np.all(np.isfinite(X)) or not R > 0:
        return None
    if min(depth(k, X) for k in (0, 1)) <= 0:
        return None
    out = [None if k is None else tuple(map(float, k)) for k in known]
    for k in fitted:
        c, r = circle_of(k, fit.x)
        rms = float(np.sqrt(np.mean((np.linalg.norm(pts[k] - c, axis=1) - r) ** 2)))
        area = float(np.pi * r * r)
        if rms > float(max_rms) * r or float(covers[k]) < float(min_visible) * area:
            return None
        out[k] = (float(c[0]), float(c[1]), area)
    return out


def occluded_centres(
    cameras: Sequence[Camera],
    fused: int,
    outline: np.ndarray,
    known: Mapping[int, tuple[float, float, float]],
    max_rms: float = ANCHOR_DEFAULTS["max_sphere_rms"],
    grid: int = 40,
    loose: Collection[int] = (),
) -> dict[int, tuple[float, float, float, float]] | None:
    """The circles of two or three bubbles whose silhouettes one view fuses into one.

    One view (``1 − fused``) sees the bubbles apart, with whole silhouettes: each has
    its centre and area there (``known``). The other view (``fused``) sees them
    overlap, one in front of another, as one silhouette whose visible ``outline`` is
    made of arcs of their circles. As in :func:`sphere_centres` with a known view,
    each sphere lies on its centre's ray with the size its area gives at its depth
    (:func:`apparent_size`), and projects in the fused view to the circle of centre
    X's projection and radius f·R / depth; the unknowns are the depths along the rays.
    Each outline point's residual is its signed distance to the union of the circles
    (the least of its radial distances to each); the depths start from the best of a
    ``grid`` per ray (the stretch of ray whose circle centre falls near the outline)
    and are refined by ``scipy.optimize.least_squares``.

    Args:
        cameras: the two views' undistorted cameras.
        fused: index (0 or 1) of the view that fuses the silhouettes.
        outline: (N, 2) visible outline points of the fused silhouette in that view
            (pixels, column, row; :func:`visible_outline`).
        known: ``{bubble: (u, v, area)}`` of 2 or 3 bubbles in the other view (pixels,
            pixels²).
        max_rms: largest rms residual over the circles' mean radius.
        grid: depths tried per ray for the start.
        loose: bubbles of ``known`` that need not be spheres (an attached bubble, which
            the plate cuts and deforms): each a circle free in the fused view (centre
            and radius, from its sphere's start; its depth the start's), and the rms is
            that of the outline points the other circles own, over their mean radius.

    Returns:
        ``{bubble: (u, v, area, depth)}`` in the fused view: each circle's centre
        (pixels), area (pixels², its whole silhouette's) and the sphere centre's depth
        there (m; the least is in front); None where the outline is short, the fit
        misses ``max_rms``, or some circle owns less than a tenth of the outline (its
        bubble is hidden, or not there: its depth is not measured).
    """
    from scipy.optimize import least_squares

    ids = sorted(known)
    pts = np.asarray(outline, np.float64).reshape(-1, 2)
    if not 2 <= len(ids) <= 3 or len(pts) < _MIN_OUTLINE_POINTS * len(ids):
        return None
    cu, cv = cameras[1 - fused], cameras[fused]
    f_v = float(np.sqrt(cv.K[0, 0] * cv.K[1, 1]))
    rays = []
    for b in ids:
        d = cu.R.T @ np.linalg.solve(cu.K, np.array([known[b][0], known[b][1], 1.0]))
        rays.append(d / np.linalg.norm(d))

    def circles(b: int, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centres (S, 2) px, radii (S,) px and depths (S,) m in the fused view of bubble
        ``ids[b]``'s spheres at distances ``s`` (S,) m along its ray."""
        X = cu.center[None] + s[:, None] * rays[b][None]
        R = np.array([apparent_size(cu, x, known[ids[b]][2]) for x in X])
        z = cv.world_to_camera(X)[:, 2]
        return cv.project(X, distort=False), f_v * R / np.maximum(z, 1e-12), z

    # Distances along each ray whose circle centre lies near the outline: the start.
    lo, hi = pts.min(0), pts.max(0)
    pad = 0.5 * (hi - lo) + 1.0
    mid = triangulate([cu, cv], [np.array([known[ids[0]][:2]]), np.array([pts.mean(0)])])[0]
    s_ref = float(np.linalg.norm(mid - cu.center))
    if not np.isfinite(s_ref) or s_ref <= 0:
        return None
    starts = []
    for b in range(len(ids)):
        s = np.geomspace(0.3 * s_ref, 3.0 * s_ref, 800)
        c, _r, z = circles(b, s)
        near = (z > 0) & np.all((c >= lo - pad) & (c <= hi + pad), axis=1)
        if not near.any():
            return None
        s = s[near]
        starts.append(s[np.unique(np.linspace(0, len(s) - 1, grid).round().astype(int))])
    if len(ids) == 3:
        starts = [s[:: max(1, len(s) // 16)] for s in starts]

    def signed(b: int, s: np.ndarray) -> np.ndarray:
        c, r, _z = circles(b, s)
        return np.linalg.norm(pts[None] - c[:, None], axis=2) - r[:, None]  # (S, N)

    d = [signed(b, s) for b, s in enumerate(starts)]
    if len(ids) == 2:
        cost = (np.minimum(d[0][:, None], d[1][None]) ** 2).mean(-1)
    else:
        cost = (np.minimum(np.minimum(d[0][:, None, None], d[1][None, :, None]),
                           d[2][None, None]) ** 2).mean(-1)  # fmt: skip
    best = np.unravel_index(int(np.argmin(cost)), cost.shape)
    s0 = np.array([starts[b][i] for b, i in enumerate(best)])
    # A loose bubble's circle is free in the fused view: (u, v, radius) px from its start.
    free = [b for b in range(len(ids)) if ids[b] in loose]
    held_ids = [b for b in range(len(ids)) if ids[b] not in loose]
    if not held_ids:
        return None
    z_free = {}
    x0, scale = [s0[b] for b in held_ids], [0.01 * s_ref] * len(held_ids)
    for b in free:
        c, r, z = circles(b, s0[b : b + 1])
        x0 += [c[0, 0], c[0, 1], r[0]]
        scale += [1.0, 1.0, 1.0]
        z_free[b] = float(z[0])

    def circle_of(b: int, x: np.ndarray) -> tuple[np.ndarray, float, float]:
        """Centre (2,) px, radius px and depth m of bubble ``ids[b]`` at parameters ``x``."""
        if b in z_free:
            k = len(held_ids) + 3 * free.index(b)
            return x[k : k + 2], float(x[k + 2]), z_free[b]
        c, r, z = circles(b, x[held_ids.index(b) : held_ids.index(b) + 1])
        return c[0], float(r[0]), float(z[0])

    def dist(x: np.ndarray) -> np.ndarray:
        """(B, N) signed distance of each outline point to each circle's edge."""
        out = []
        for b in range(len(ids)):
            c, r, _z = circle_of(b, x)
            out.append(np.linalg.norm(pts - c[None], axis=1) - r)
        return np.array(out)

    def resid(x: np.ndarray) -> np.ndarray:
        return dist(x).min(axis=0)

    fit = least_squares(resid, np.array(x0), x_scale=np.array(scale))
    if not fit.success or not np.all(np.isfinite(fit.x)):
        return None
    out = {}
    radii = []
    for b in range(len(ids)):
        c, r, z = circle_of(b, fit.x)
        if not (z > 0 and r > 0):
            return None
        out[ids[b]] = (float(c[0]), float(c[1]), float(np.pi * r**2), float(z))
        radii.append(r)
    res = resid(fit.x)
    owner = np.argmin(np.abs(dist(fit.x)), axis=0)
    strict = np.array([b not in loose for b in ids])
    held = strict[owner]
    if not held.any():
        return None
    rms = float(np.sqrt(np.mean(res[held] ** 2)))
    if rms > float(max_rms) * float(np.mean(np.asarray(radii)[strict])):
        return None
    if np.bincount(owner, minlength=len(ids)).min() < 0.1 * len(pts):
        return None
    return out


def register_outline(
    points: np.ndarray, ref: np.ndarray, start: np.ndarray | None = None, iters: int = 30
) -> tuple[np.ndarray, float] | None:
    """The translation that lays a visible outline onto a reference outline of the
    same silhouette (translation-only ICP: each point to the nearest point of the
    reference line, densified every 0.1 px between its points less than 2 px apart).

    A bubble leaving the frame shows a shrinking part of one outline: each frame's
    visible arc is a piece of the arc of the frame where most of it was inside, moved.

    Args:
        points: (N, 2) visible outline points (pixels, column, row), N ≥ 1.
        ref: (M, 2) reference outline points in order along the line, M ≥ 2.
        start: (2,) starting translation (default 0).
        iters: ICP iterations.

    Returns:
        ``(d, rms)``: the (2,) translation (pixels) taking ``points`` onto ``ref`` and the
        rms distance of the moved points to the line (pixels); None without points.
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points, np.float64).reshape(-1, 2)
    R = np.asarray(ref, np.float64).reshape(-1, 2)
    if len(P) == 0 or len(R) < 2:
        return None
    dense = [R]
    for a, b in zip(R[:-1], R[1:], strict=True):
        n = int(np.linalg.norm(b - a) / 0.1)
        if 1 < n and np.linalg.norm(b - a) < 2.0:
            s = np.linspace(0.0, 1.0, n + 1)[1:-1, None]
            dense.append(a + s * (b - a))
    tree = cKDTree(np.concatenate(dense))
    d = np.zeros(2) if start is None else np.asarray(start, np.float64).copy()
    for _ in range(int(iters)):
        _, j = tree.query(P + d)
        step = (tree.data[j] - (P + d)).mean(axis=0)
        d += step
        if np.hypot(*step) < 1e-4:
            break
    dist, _ = tree.query(P + d)
    return d, float(np.sqrt(np.mean(dist**2)))


def revolution_centroid(weights: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """Centroid (u, v) (pixels) of the solid of revolution a silhouette outlines about
    its long axis: the silhouette cut into one-pixel slices across its principal axis
    of inertia, each slice the disc of its (weighted) chord, at the chord's middle.

    A young merged bubble is two lobes of different size: its vapour's centroid weighs
    each lobe by its volume (∝ r³), its silhouette's centroid by its area (∝ r²), which
    pulls it towards the smaller lobe (by 0.15 mm, a tenth of the radius, for lobes of
    1.0 and 1.3 mm one above the other). The discs weigh the slices by the squared
    chord, as the volume does; for a sphere or any body of revolution about that axis,
    seen across it, the centroid is its centre's projection.

    Args:
        weights: (h, w) cover of each pixel (0..1). rows, cols: (h, w) pixel centres.

    Returns:
        ``(u, v)`` pixels.
    """
    w = np.asarray(weights, np.float64)
    uu, vv = np.asarray(cols, np.float64), np.asarray(rows, np.float64)
    s = float(w.sum())
    cu, cv = float((w * uu).sum() / s), float((w * vv).sum() / s)
    du, dv = uu - cu, vv - cv
    cuv = float((w * du * dv).sum())
    cov = np.array([[(w * du * du).sum(), cuv], [cuv, (w * dv * dv).sum()]])
    axis = np.linalg.eigh(cov)[1][:, 1]  # the long axis
    along = du * axis[0] + dv * axis[1]
    across = -du * axis[1] + dv * axis[0]
    k = np.floor(along + 0.5).astype(np.int64)
    k -= k.min()
    chord = np.bincount(k.ravel(), w.ravel())
    ok = chord > 0
    mid = np.bincount(k.ravel(), (w * across).ravel())[ok] / chord[ok]
    pos = np.bincount(k.ravel(), (w * along).ravel())[ok] / chord[ok]
    disc = chord[ok] ** 2
    a, c = float((disc * pos).sum() / disc.sum()), float((disc * mid).sum() / disc.sum())
    return cu + a * axis[0] - c * axis[1], cv + a * axis[1] + c * axis[0]


def lobe_centroids(
    contrast: np.ndarray,
    labels: np.ndarray,
    ids: set[int],
    ring_px: int = ANCHOR_DEFAULTS["ring_px"],
    static: np.ndarray | None = None,
) -> dict[int, tuple[float, float, float]]:
    """:func:`coverage_centroids`' entries of the regions ``ids`` with the centroid of
    their solid of revolution (:func:`revolution_centroid`, same cover weights)."""
    lab = np.asarray(labels)
    c = np.asarray(contrast, dtype=np.float64)
    ids = {int(b) for b in ids if (lab == b).any()}
    if not ids:
        return {}
    owner = region_owners(lab, ring_px)
    out = {}
    for b in sorted(ids):
        m = lab == b
        sl = _crop(m, int(ring_px) + 1)
        st = None if static is None else np.asarray(static)[sl]
        w = _cover_weights(m[sl], c[sl], owner[sl] == b, ring_px, st)
        vv, uu = np.mgrid[sl]
        out[b] = (*revolution_centroid(w, vv, uu), float(w.sum()))
    return out


def circle_reach(rho: float) -> float:
    """Radius (pixels) about a sphere's image circle of radius ``rho`` within which its
    bubble's pixels may lie: 0.1 radius + 1 pixel beyond it. A bubble is no sphere (a
    spheroid or a shape mode reaches past its equivalent sphere)."""
    return 1.1 * float(rho) + 1.0


def circle_meets_frame(u: float, v: float, rho: float, shape: tuple[int, int]) -> bool:
    """Whether the circle of centre ``(u, v)`` and radius ``rho`` (pixels) overlaps an
    image of ``shape`` (H, W): its pixels' area, from −0.5 to W − 0.5 and H − 0.5
    (pixel centres at integers), not only their centres."""
    h, w = int(shape[0]), int(shape[1])
    du = u - float(np.clip(u, -0.5, w - 0.5))
    dv = v - float(np.clip(v, -0.5, h - 0.5))
    return bool(np.hypot(du, dv) < rho)


def continued_centres(
    table: pd.DataFrame,
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    frames: np.ndarray,
    fps: float,
    continue_s: float = ANCHOR_DEFAULTS["continue_s"],
) -> pd.DataFrame:
    """Centres of bubbles leaving (or entering) the frame past their last (first)
    centre, continued along their track: :data:`ANCHOR_COLUMNS` rows plus ``visible``.

    A bubble whose silhouette shrinks to a sliver at the border has no centre from an
    outline fit (too little of it shows: ``min_visible_sphere``), yet both views still
    see part of it. From the frame after a run of its consistent centres (``table``)
    that ends with a cut one (``cut``), for up to ``continue_s`` seconds, its centre
    continues the least-squares line through the run's centres of its last
    ``continue_s`` seconds (at least two) and its radius is their median ``r_m``, while
    at least one view still has pixels of its id in ``labels``, the sphere's image (the
    centre's projection, radius f·r / depth), grown by 0.1 radius + 1 pixel, reaches
    into both frames and holds every view's pixels of the id (at most 10 % of them
    outside it); the same backwards from a run's first centre. The growth allows for
    the bubble's shape (a spheroid or a shape mode reaches past its equivalent sphere),
    and "reaches" is an overlap of the frame's pixel area (:func:`circle_meets_frame`):
    a circle ending between two rows of pixel centres still darkens the row it reaches
    into. A continued centre is a prediction, not a measurement: its ``visible`` share
    is the least, over the two views, of the id's pixels there over the circle's area.

    Args:
        table: :func:`anchor_table` rows (with ``consistent``).
        cameras: the two views' undistorted cameras of ``labels``' grids.
        labels: per view, (T, H, W) int labels.
        frames: (T,) session frame index of each position.
        fps: frames per second.
        continue_s: seconds past a run's end a centre is continued; 0: none.

    Returns:
        the continued rows (``reproj_px`` 0, ``size_ratio`` 1, ``cut`` and
        ``consistent`` True), in frame order.
    """
    cols = [*ANCHOR_COLUMNS, "visible"]
    if continue_s <= 0 or fps <= 0 or not len(table):
        return pd.DataFrame(columns=cols)
    frames = np.asarray(frames, np.int64)
    pos = {int(f): k for k, f in enumerate(frames)}
    n = len(frames)
    cams = list(cameras)[:2]
    span = int(np.floor(continue_s * fps + 1e-9))
    good = table[table["consistent"].astype(bool) & (table["bubble"] >= 1)]
    taken = {(pos[int(f)], int(b)) for f, b in zip(good["frame"], good["bubble"], strict=True)}
    rows = []
    for b, g in good.groupby("bubble"):
        b = int(b)
        k = np.array([pos[int(f)] for f in g["frame"]])
        order = np.argsort(k)
        k = k[order]
        X = g[["x", "y", "z"]].to_numpy(np.float64)[order]
        r = g["r_m"].to_numpy(np.float64)[order]
        cut = g["cut"].to_numpy(bool)[order]
        starts = np.flatnonzero(np.r_[True, np.diff(k) != 1])
        ends = np.r_[starts[1:], len(k)] - 1
        for a, e in zip(starts, ends, strict=True):
            for edge, step in ((e, 1), (a, -1)):
                if not cut[edge]:
                    continue
                near = np.flatnonzero((np.abs(k - k[edge]) <= span) & (k >= k[a]) & (k <= k[e]))
                if len(near) < 2:
                    continue
                t = k[near] / fps
                coef = np.polyfit(t - t.mean(), X[near], 1)
                R = float(np.median(r[near]))
                for j in range(1, span + 1):
                    q = int(k[edge] + step * j)
                    if q < 0 or q >= n or (q, b) in taken:
                        break
                    c = coef[0] * (q / fps - t.mean()) + coef[1]
                    shares = _continued_shares(c, R, b, q, cams, labels)
                    if shares is None:
                        break
                    taken.add((q, b))
                    share = min(min(shares), 1.0)
                    rows.append((int(frames[q]), b, *map(float, c), 0.0, 1.0, R, True, True, share))
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values(["frame", "bubble"], kind="stable").reset_index(drop=True)


def _continued_shares(
    X: np.ndarray,
    R: float,
    b: int,
    q: int,
    cams: Sequence[Camera],
    labels: Sequence[np.ndarray],
) -> list[float] | None:
    """:func:`continued_centres`' test of the sphere ``(X, R)`` of id ``b`` at position
    ``q``: per view, the pixels of the id over the area of the sphere's image circle
    (its ``visible`` share is the least of them, at most 1), or None where it fails."""
    shares, present = [], False
    for cam, lab in zip(cams, labels, strict=True):
        circle = sphere_image(cam, X, R)
        if circle is None:
            return None
        u, v, rho = circle
        im = np.asarray(lab[q])
        reach = circle_reach(rho)
        if not circle_meets_frame(u, v, reach, im.shape):
            return None
        ys, xs = np.nonzero(im == b)
        if len(ys):
            present = True
            if np.mean(np.hypot(xs - u, ys - v) > reach) > 0.1:
                return None
        shares.append(len(ys) / (np.pi * rho * rho))
    return shares if present else None


def moving_sphere(
    cameras: Sequence[Camera],
    outlines: Mapping[int, Sequence[np.ndarray | None]],
    fps: float,
) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """The sphere moving at a constant velocity whose images' circles a bubble's visible
    outlines lie on, over several frames and both views at once.

    A bubble entering or leaving the frame that no frame shows whole, in either view,
    has no track to continue; in some frames one view shows a sliver too small to fit,
    or none. One moving sphere fitted to every frame's outlines takes its depth from
    the frames both views see and carries it, with the velocity, into those one view
    sees. The fit minimises the outline points' radial distances to the circles (centre
    X(q)'s projection, radius f·R / depth; soft-L1 with a 1-pixel scale:
    ``scipy.optimize.least_squares``), from the sphere triangulated from the circles
    (:func:`circle_fit`) of the frame whose lesser outline is longest, at rest.

    Args:
        cameras: the two views' undistorted cameras.
        outlines: ``{frame position q: (points of view 0, points of view 1)}``, each
            (N, 2) visible outline points (pixels, column, row;
            :func:`visible_outline`) or None where that view shows none.
        fps: frames per second.

    Returns:
        ``(X, V, R, q0)``: the centre X (3,) m at position q0 (the mean fitted
        position), the velocity V (3,) m/s (X(q) = X + V·(q − q0)/fps) and the radius R
        (m); None where no frame has both views' outlines of at least
        ``_MIN_OUTLINE_POINTS`` points or the fit fails.
    """
    from scipy.optimize import least_squares

    cams = list(cameras)[:2]
    pts = {
        q: [None if p is None else np.asarray(p, np.float64).reshape(-1, 2) for p in o]
        for q, o in outlines.items()
    }
    both = [
        q for q, o in pts.items() if all(p is not None and len(p) >= _MIN_OUTLINE_POINTS for p in o)
    ]
    if not both or fps <= 0:
        return None
    q_init = max(both, key=lambda q: (min(len(p) for p in pts[q]), -q))
    circles = [circle_fit(p) for p in pts[q_init]]
    if any(c is None for c in circles):
        return None
    focal = [float(np.sqrt(c.K[0, 0] * c.K[1, 1])) for c in cams]

    def depth(k: int, X: np.ndarray) -> float:
        return float(cams[k].world_to_camera(X[None])[0, 2])

    X_init = triangulate(cams, [np.array([c[:2]]) for c in circles])[0]
    if not np.all(np.isfinite(X_init)) or min(depth(k, X_init) for k in (0, 1)) <= 0:
        return None
    R_init = float(np.mean([circles[k][2] * depth(k, X_init) / focal[k] for k in (0, 1)]))
    qs = sorted(pts)
    q0 = float(np.mean(qs))
    terms = [(q, k, p) for q in qs for k, p in enumerate(pts[q]) if p is not None and len(p)]
    P = np.concatenate([p for _, _, p in terms])  # (N, 2) every outline point, its
    K = np.concatenate([np.full(len(p), k) for _, k, p in terms])  # view
    dq = np.concatenate([np.full(len(p), q - q0) for q, _, p in terms])  # and time
    f_of = np.asarray(focal)[K]
    in_view = [K == k for k in (0, 1)]

    def resid(x: np.ndarray) -> np.ndarray:
        X = x[:3] + x[3:6][None] * dq[:, None] / fps  # (N, 3) the centre at each point's frame
        c, z = np.empty((len(P), 2)), np.empty(len(P))
        for k, m in enumerate(in_view):
            c[m] = cams[k].project(X[m], distort=False)
            z[m] = cams[k].world_to_camera(X[m])[:, 2]
        r = np.linalg.norm(P - c, axis=1) - f_of * x[6] / np.maximum(z, 1e-9)
        return np.r_[r, x[3:6] / _SPHERE_SPEED_SCALE]  # the weak prior: pixels per m/s

    span = max(qs[-1] - qs[0], 1)
    scale = np.r_[np.full(3, R_init), np.full(3, R_init * fps / span), R_init]
    x0 = np.r_[X_init, np.zeros(3), R_init]
    fit = least_squares(resid, x0, x_scale=np.maximum(scale, 1e-9), loss="soft_l1", f_scale=1.0)
    X, V, R = fit.x[:3], fit.x[3:6], float(fit.x[6])
    if not fit.success or not np.all(np.isfinite(fit.x)) or not R > 0:
        return None
    return X, V, R, q0


def sphere_track_centres(
    table: pd.DataFrame,
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    outline: Callable[[int, int, int], tuple[np.ndarray, float] | None],
    frames: np.ndarray,
    fps: float,
    window_s: float = ANCHOR_DEFAULTS["continue_s"],
    max_rms: float = ANCHOR_DEFAULTS["max_sphere_rms"],
    min_visible: float = ANCHOR_DEFAULTS["min_visible_sphere"],
) -> pd.DataFrame:
    """Centres of bubbles the border cuts in frames where they have none, from the
    moving sphere of their outlines (:func:`moving_sphere`): :data:`ANCHOR_COLUMNS`
    rows plus ``visible``, as :func:`continued_centres`'.

    For each id and each run of consecutive frame positions where the id is cut by a
    view's border (:func:`border_ids`) and ``table`` has no measured centre of it
    (none, or a ``continued`` one: a prediction, kept as it is), the sphere is fitted to
    the id's visible outlines (``outline(q, view, id)``) of the run and of the frames
    within ``window_s`` seconds before and after it where the border cuts it too. A
    frame of the run without a centre gets the sphere's where the test of
    :func:`continued_centres` holds (a view shows pixels of the id, the sphere's image
    reaches into both frames and holds them), every outline of the frame lies on its
    circle (rms radial distance at most ``max_rms`` of the radius), as do those of
    every fitted frame that both views see, and the view that shows most of it covers
    at least ``min_visible`` of its circle with pixels of the id (no sphere grown
    round a border fragment).

    Args:
        table: the anchors so far (with ``consistent``; continued rows included).
        cameras: the two views' undistorted cameras of ``labels``' grids.
        labels: per view, (T, H, W) int labels.
        outline: ``(position, view, id) → (points, cover)`` or None
            (:func:`visible_outline` of that frame).
        frames: (T,) session frame index of each position.
        fps: frames per second.
        window_s: seconds of cut frames with centres fitted with a run, each side.
        max_rms: largest rms radial distance of an outline to its circle, over the
            circle's radius.
        min_visible: least share of its circle that the view showing most of the
            sphere covers with pixels.

    Returns:
        the new rows (``reproj_px`` 0, ``size_ratio`` 1, ``cut`` and ``consistent``
        True), in frame order.
    """
    cols = [*ANCHOR_COLUMNS, "visible"]
    cams = list(cameras)[:2]
    frames = np.asarray(frames, np.int64)
    if fps <= 0 or len(frames) == 0:
        return pd.DataFrame(columns=cols)
    pos = {int(f): k for k, f in enumerate(frames)}
    good = table[table["consistent"].astype(bool) & (table["bubble"] >= 1)]
    taken = {(pos[int(f)], int(b)) for f, b in zip(good["frame"], good["bubble"], strict=True)}
    if "continued" in good.columns:  # continued centres are predictions: runs span them
        good = good[~good["continued"].astype(bool)]
    measured = {(pos[int(f)], int(b)) for f, b in zip(good["frame"], good["bubble"], strict=True)}
    cut_at: dict[int, list[int]] = {}
    for q in range(len(frames)):
        ids = set().union(*(border_ids(np.asarray(lab[q])) for lab in labels))
        for b in sorted(i for i in ids if i >= 1):
            cut_at.setdefault(b, []).append(q)
    span = int(np.floor(window_s * fps + 1e-9))

    def rms_ok(X: np.ndarray, R: float, o: Sequence) -> bool:
        for k, p in enumerate(o):
            circle = sphere_image(cams[k], X, R) if p is not None and len(p) else None
            if circle is not None:
                u, v, rho = circle
                res = np.hypot(p[:, 0] - u, p[:, 1] - v) - rho
                if float(np.sqrt(np.mean(res**2))) > max_rms * rho:
                    return False
        return True

    rows = []
    for b, qs in cut_at.items():
        missing = [q for q in qs if (q, b) not in measured]
        if not any((q, b) not in taken for q in missing):
            continue
        starts = np.flatnonzero(np.r_[True, np.diff(missing) != 1])
        ends = np.r_[starts[1:], len(missing)] - 1
        for a, e in zip(starts, ends, strict=True):
            run = missing[a : e + 1]
            near = [q for q in qs if run[0] - span <= q <= run[-1] + span]
            outl = {}
            for q in near:
                o = [outline(q, k, b) for k in (0, 1)]
                outl[q] = [None if x is None else np.asarray(x[0], np.float64) for x in o]
            fit = moving_sphere(cams, outl, fps)
            if fit is None:
                continue
            X0, V, R, q0 = fit
            where = {q: X0 + V * (q - q0) / fps for q in near}
            seen_both = [q for q in near if all(p is not None and len(p) for p in outl[q])]
            if not all(rms_ok(where[q], R, outl[q]) for q in seen_both):
                continue
            for q in (q for q in run if (q, b) not in taken):
                X = where[q]
                shares = _continued_shares(X, R, b, q, cams, labels)
                if shares is None or not rms_ok(X, R, outl[q]) or max(shares) < min_visible:
                    continue
                taken.add((q, b))
                share = min(min(shares), 1.0)
                rows.append((int(frames[q]), b, *map(float, X), 0.0, 1.0, R, True, True, share))
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values(["frame", "bubble"], kind="stable").reset_index(drop=True)
