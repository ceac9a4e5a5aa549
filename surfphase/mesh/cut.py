"""Silhouettes the image border cuts, completed beyond it for the elliptic hull
([docs/method.md §10](../../docs/method.md#10-meshes)).

A bubble that enters or leaves the frame shows one view only part of its silhouette.
Its hull, made from that part, stops at the border: the mesh is a slice of the bubble,
its volume too small, and once moved to the bubble's reported centre (which the mask
stage takes from the whole silhouette's ellipse, :mod:`surfphase.masks.anchors`) it
sits off the bubble's surface. Here each such silhouette is drawn whole on a label image
grown by a margin beyond the frame: as the shape the same view shows whole in the
nearest frame of the bubble's track, moved onto the visible outline (as the mask stage's
``tracked_cut_centres``), else as the image of the sphere the mask stage gave it (its
reported centre and size, :func:`surfphase.mesh.stage.sphere_shapes`, where the visible
part fits inside it), else, with ``circles``, as the circle fitted to the visible
outline; the shape and the circle only when at least ``min_visible_tracked`` of it is
inside the frame, the visible part fits inside it and the outline fits it within
``max_shape_rms`` of its radius (``masks: anchors:``); with ``tracked_circles``, one
less inside as the circle of the radius its track's nearest frame gave it so, placed on
its visible outline. The ellipse fitted to a partial outline, which the mask stage's
centres take when 60 % is visible, is not used: across the cut its axis is poorly
constrained (a sphere's silhouette 64 % inside, radius 9.2 px, gave semi-axes of 7.4 and
9.1 px; the circle 9.5 px). Inside the frame the masks are kept as they are;
only pixels beyond the border are drawn. The outlines are the binary masks' own (pixel
edges): the mesh stage has labels, not the images.

Pixels per docs/conventions.md §4; cameras are the undistorted cameras of the label
stacks' pixel grid.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy import ndimage as ndi

from surfphase.cameras import Camera
from surfphase.masks.anchors import (
    _MIN_OUTLINE_POINTS,
    NUCLEATION_ID,
    border_ids,
    circle_fit,
    inside_ellipse,
    nearest_whole,
    outline_ellipse,
    shape_centre,
    visible_outline,
)
from surfphase.masks.classical import fill_holes_to_border

#: An ellipse ``(u, v, a, b, angle)``: centre (pixels, column, row), semi-axes (pixels)
#: and orientation (degrees, ``cv2.fitEllipse``'s convention).
Ellipse = tuple[float, float, float, float, float]


def _outline(lab: np.ndarray, b: int, margin_px: int = 1) -> tuple[np.ndarray, float] | None:
    """The binary silhouette's visible outline (pixel edges; the frame's cut and the
    edges shared with another region left out) and its area (pixels²)."""
    return visible_outline(
        (lab == b).astype(np.float64), lab, lab, b, ring_px=0, margin_px=margin_px
    )


def ellipse_area(e: Ellipse) -> float:
    """Area (pixels²) of ``e``."""
    return float(np.pi * e[2] * e[3])


def whole_shape(labels: np.ndarray, t: int, b: int) -> Ellipse | None:
    """The ellipse fitted to region ``b``'s outline in frame ``t`` of a view's (T, H, W)
    labels when the border does not cut it there, else None."""
    lab = np.asarray(labels[t])
    if b in border_ids(lab) or not (lab == b).any():
        return None
    vis = _outline(lab, b)
    if vis is None or len(vis[0]) < _MIN_OUTLINE_POINTS:
        return None
    return outline_ellipse(vis[0])


def cut_shapes(
    labels: np.ndarray,
    t: int,
    rules: Mapping,
    cache: dict | None = None,
    circles: bool = False,
    tracked_circles: bool = False,
    spheres: Mapping[int, Ellipse] | None = None,
) -> dict[int, Ellipse]:
    """The whole silhouette of every region (id ≥ 1) the border cuts in frame ``t``.

    Args:
        labels: (T, H, W) int labels of one view, −1 background.
        t: the frame's position in ``labels``.
        rules: ``min_visible_tracked`` (above 1: no shapes), ``max_shape_rms`` (as
            config ``masks: anchors:``).
        cache: kept between calls on the same ``labels``: ``{(t, id): ellipse or None}``
            of whole shapes and ``{("frames", id): positions where id is}``.
        circles: a region whose track shows no whole shape gets the circle fitted to
            its visible outline, by the same rules (a prior: a bubble of a millimetre is
            near-spherical; ``mesh: complete_cut_circles``).
        tracked_circles: with ``circles``, a region less of which is inside than
            ``min_visible_tracked`` gets the circle of the radius its track's nearest
            frame gave it that way, placed on its visible outline (a centre fitted to a
            short arc of known radius; ``mesh: complete_cut_tracked_circles``).
        spheres: ``{id: circle}`` of regions whose track shows no whole shape that take
            this circle before any fitted one (the image of the mask stage's sphere,
            ``mesh: complete_cut_spheres``).

    Returns:
        ``{id: ellipse}``: the shape of each cut region that gets one.
    """
    labels = np.asarray(labels)
    lab = labels[t]
    cache = {} if cache is None else cache
    lo, rms_max = float(rules["min_visible_tracked"]), float(rules["max_shape_rms"])
    out: dict[int, Ellipse] = {}
    if lo > 1.0:
        return out
    for b in sorted(i for i in border_ids(lab) if i >= 1):
        vis = _outline(lab, b)
        if vis is None or len(vis[0]) < _MIN_OUTLINE_POINTS:
            continue
        pts, area = vis
        if ("frames", b) not in cache:
            cache[("frames", b)] = np.flatnonzero((labels == b).any(axis=(1, 2)))
        frames = cache[("frames", b)]

        def whole_at(k: int, b: int = b):
            if (k, b) not in cache:
                cache[(k, b)] = whole_shape(labels, k, b)
            return cache[(k, b)]

        ref = nearest_whole(frames, t, whole_at)
        fit = None if ref is None else shape_centre(pts, ref)
        # The visible part lies inside the whole silhouette.
        if (
            fit is not None
            and fit[2] <= rms_max * np.sqrt(ref[2] * ref[3])
            and lo * ellipse_area(ref) <= area <= ellipse_area(ref)
        ):
            out[b] = (fit[0], fit[1], ref[2], ref[3], ref[4])
        if b not in out and spheres and b in spheres:
            out[b] = spheres[b]
        if b not in out and circles:
            c = fit_circle(pts)
            if _circle_holds(c, area, lo, rms_max):
                out[b] = (c[0], c[1], c[2], c[2], 0.0)
        if b not in out and circles and tracked_circles:

            def circle_at(k: int, b: int = b):
                key = ("circle", k, b)
                if key not in cache:
                    cache[key] = _circle_shape(labels[k], b, whole_at(k), lo, rms_max)
                return cache[key]

            ref = nearest_whole(frames, t, circle_at)
            c = None if ref is None else place_circle(pts, lab == b, ref[2])
            if c is not None and c[3] <= rms_max * ref[2] and area <= np.pi * ref[2] ** 2:
                out[b] = (c[0], c[1], ref[2], ref[2], 0.0)
    return out


def place_circle(
    points: np.ndarray, region: np.ndarray, radius: float, inside: float = 0.95
) -> tuple[float, float, float, float] | None:
    """The circle of the given radius (pixels) on a short visible arc: of
    :func:`fit_circle_of_radius` from starts one radius from the outline's mean in eight
    directions, the one with the least rms among those that hold at least ``inside``
    of the (H, W) bool ``region``'s pixels (an arc fits a circle on either side of it;
    the visible part lies inside the bubble); None when none does."""
    P = np.asarray(points, np.float64)
    vv, uu = np.nonzero(region)
    if len(P) < 3 or len(uu) == 0:
        return None
    best = None
    mid = P.mean(axis=0)
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        c = fit_circle_of_radius(P, radius, mid + radius * np.array([np.cos(a), np.sin(a)]))
        if c is None:
            continue
        held = np.mean(np.hypot(uu - c[0], vv - c[1]) <= radius + 0.5)
        if held >= inside and (best is None or c[3] < best[3]):
            best = c
    return best


def _circle_shape(
    lab: np.ndarray, b: int, whole: Ellipse | None, lo: float, rms_max: float
) -> Ellipse | None:
    """The circle of region ``b`` in one frame's (H, W) labels of a view: from
    ``whole``, the ellipse of its outline where the border does not cut it
    (:func:`whole_shape`), else the circle fitted to its visible outline when at least
    ``lo`` of it is inside and the outline fits it within ``rms_max`` of its radius;
    None otherwise. As an ellipse of equal semi-axes (the mean of the whole shape's)."""
    lab = np.asarray(lab)
    if not (lab == b).any():
        return None
    if whole is not None:
        r = float(np.sqrt(whole[2] * whole[3]))
        return (whole[0], whole[1], r, r, 0.0)
    vis = _outline(lab, b)
    if vis is None or len(vis[0]) < _MIN_OUTLINE_POINTS:
        return None
    c = fit_circle(vis[0])
    if not _circle_holds(c, vis[1], lo, rms_max):
        return None
    return (c[0], c[1], c[2], c[2], 0.0)


def _circle_holds(c: tuple | None, area: float, lo: float, rms_max: float) -> bool:
    """Whether the circle ``(u, v, r, rms)`` fitted to a cut silhouette's visible outline
    takes it: the outline within ``rms_max`` of the radius, and the visible ``area``
    (pixels²) at least ``lo`` of the circle's and at most all of it."""
    return (
        c is not None
        and c[3] <= rms_max * c[2]
        and lo * np.pi * c[2] ** 2 <= area <= np.pi * c[2] ** 2
    )


def fit_circle_of_radius(
    points: np.ndarray, radius: float, start: tuple[float, float]
) -> tuple[float, float, float, float] | None:
    """``(u, v, radius, rms)``: the centre of the circle of the given radius (pixels)
    nearest (N, 2) outline points in the least squares of their distances to it
    (``scipy.optimize.least_squares`` from ``start``), and the rms of those distances;
    None where it fails."""
    from scipy.optimize import least_squares

    P = np.asarray(points, np.float64)
    if len(P) < 3:
        return None
    res = least_squares(
        lambda c: np.linalg.norm(P - c, axis=1) - radius, np.asarray(start, np.float64),
        method="lm",
    )  # fmt: skip
    if not res.success or not np.isfinite(res.x).all():
        return None
    return float(res.x[0]), float(res.x[1]), float(radius), float(np.sqrt(np.mean(res.fun**2)))


def fit_circle(points: np.ndarray) -> tuple[float, float, float, float] | None:
    """``(u, v, r, rms)``: the circle nearest (N, 2) outline points (pixels) in the least
    squares of their distances to it (``scipy.optimize.least_squares`` from the
    algebraic fit, :func:`surfphase.masks.anchors.circle_fit`), and the rms of those
    distances; None where it fails."""
    from scipy.optimize import least_squares

    P = np.asarray(points, np.float64)
    start = circle_fit(P)
    if start is None:
        return None
    res = least_squares(
        lambda c: np.linalg.norm(P - c[:2], axis=1) - c[2], np.array(start), method="lm"
    )
    if not res.success or not np.isfinite(res.x).all() or res.x[2] <= 0:
        return None
    return float(res.x[0]), float(res.x[1]), float(res.x[2]), float(np.sqrt(np.mean(res.fun**2)))


#: Inside the frame, a completed shape claims the background pixels at least this many
#: pixels inside its ellipse (:func:`completed_view`): its outline was fitted to the
#: mask's half-cover line, so the pixels along it are the mask's own to decide.
CORE_INSET_PX = 1.0


def nucleation_cut_shapes(lab: np.ndarray, rules: Mapping) -> list[Ellipse]:
    """The whole silhouettes, as circles, of the nucleation region's pieces that the
    image's bottom border cuts in one frame's (H, W) labels of a view.

    The nucleation region (:data:`~surfphase.masks.anchors.NUCLEATION_ID`) holds every
    attached bubble under one id, and has no track: each of its connected pieces that
    reaches the last row (a bubble growing on a plate just below the frame; a piece
    the side borders cut is the plate's edge as often as a bubble, and is left as it
    is) is filled as if the border closed it (a backlit bubble's bright core, which the border opens,
    is no hole of its ring) and gets the circle fitted to its visible outline
    (:func:`fit_circle`), by the rules of a bubble's circle (:func:`_circle_holds`:
    ``min_visible_tracked`` of it inside, the outline within ``max_shape_rms`` of its
    radius; ``rules`` as config ``masks: anchors:``). Returns those circles, as
    ellipses of equal semi-axes (pixels)."""
    lab = np.asarray(lab)
    lo, rms_max = float(rules["min_visible_tracked"]), float(rules["max_shape_rms"])
    nuc = lab == NUCLEATION_ID
    if lo > 1.0 or not nuc.any():
        return []
    comp, _ = ndi.label(nuc)
    out: list[Ellipse] = []
    for i in np.unique(comp[-1][nuc[-1]]):
        piece = comp == i
        sides = (bool(piece[0].any()), True, bool(piece[:, 0].any()), bool(piece[:, -1].any()))
        filled = fill_holes_to_border(piece, sides)
        one = lab.copy()
        one[nuc & ~piece] = -1
        one[filled & (one == -1)] = NUCLEATION_ID
        vis = _outline(one, NUCLEATION_ID)
        if vis is None or len(vis[0]) < _MIN_OUTLINE_POINTS:
            continue
        c = fit_circle(vis[0])
        if _circle_holds(c, vis[1], lo, rms_max):
            out.append((c[0], c[1], c[2], c[2], 0.0))
    return out


def completed_view(
    camera: Camera,
    lab: np.ndarray,
    shapes: Mapping[int, Ellipse],
    pieces: list[Ellipse] | tuple = (),
) -> tuple[Camera, np.ndarray]:
    """One view's labels grown beyond the frame, with ``shapes`` drawn there.

    Args:
        camera: the view's undistorted camera of the (H, W) ``lab`` grid.
        lab: (H, W) int labels, −1 background.
        shapes: ``{id: ellipse}`` of :func:`cut_shapes`.
        pieces: ellipses of the nucleation region's pieces
            (:func:`nucleation_cut_shapes`), drawn as its id.

    Returns:
        ``(camera, labels)``: the camera of the grown grid (the same camera, its image
        grown by a margin ``m`` on every side: :meth:`Camera.cropped` at ``(−m, −m)``)
        and its (H + 2m, W + 2m) labels: ``lab`` inside the frame, the ellipses beyond
        it (where two overlap, the larger id's), and inside the frame each ellipse's
        background pixels a pixel or more inside it (:data:`CORE_INSET_PX`) its own: a
        backlit bubble's bright core, which the frame cuts open, is a gap in its mask
        that no hole filling closes. Unchanged when ``shapes`` is empty.
    """
    lab = np.asarray(lab)
    items = [(NUCLEATION_ID, ell) for ell in pieces] + sorted(shapes.items())
    if not items:
        return camera, lab
    h, w = lab.shape
    e = np.array([(u, v, max(a, b)) for _, (u, v, a, b, _) in items])
    reach = np.max([e[:, 2] - e[:, 0], e[:, 0] + e[:, 2] - (w - 1), e[:, 2] - e[:, 1],
                    e[:, 1] + e[:, 2] - (h - 1)])  # fmt: skip
    m = int(np.ceil(max(float(reach), 0.0))) + 2
    grown = np.full((h + 2 * m, w + 2 * m), -1, lab.dtype)
    vv, uu = np.mgrid[-m : h + m, -m : w + m]
    outside = (uu < 0) | (uu >= w) | (vv < 0) | (vv >= h)
    for b, ell in items:
        grown[outside & inside_ellipse(uu, vv, ell)] = b
    inner = lab.copy()
    fu, fv = np.meshgrid(np.arange(w), np.arange(h))
    for b, (u, v, a, bb, ang) in items:
        if min(a, bb) > CORE_INSET_PX:
            inset = (u, v, a - CORE_INSET_PX, bb - CORE_INSET_PX, ang)
            inner[inside_ellipse(fu, fv, inset) & (inner == -1)] = b
    grown[m : m + h, m : m + w] = inner
    return camera.cropped(-m, -m, w + 2 * m, h + 2 * m), grown
