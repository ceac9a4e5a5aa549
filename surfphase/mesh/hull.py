"""The elliptic hull: each bubble's cross-sections as ellipses fitted to its two
silhouettes ([docs/method.md §7](../../docs/method.md#7-meshes)).

Two views bound a bubble's horizontal cross-section by two strips, one per view (the
rays that graze its silhouette): the visual hull's cross-section is their
parallelogram, elongated along the views' bisector (for views 40° apart a circle's
parallelogram reaches 1.6× its radius along it). Every convex cross-section tangent to
the four lines fits both views equally well; a rising bubble is close to axisymmetric
about the vertical, so its cross-sections are close to circles. The elliptic hull
takes, in each horizontal slice, the ellipse tangent to the four lines that is closest
to a circle: for a sphere, or a spheroid with a vertical axis, the true cross-section.

The slices are the epipolar planes, the planes through both camera centres: each cuts
both silhouettes along corresponding epipolar lines, so the visual hull is, plane by
plane, the intersection of the two views' wedges, exactly; and a sphere's section by
any plane is a circle. With views at one height the planes are near horizontal where
the bubbles are. Per bubble (the voxels that both views' masks give its id) and per
slice, one voxel thick: in the plane's coordinates (along the baseline, distance from
it), each view's across-direction ``a`` (unit, perpendicular to the ray from the view
to the slice's centre), the strip's centre ``c`` and half-width ``r`` (the slice's
hull voxels' extreme ``a · q``: the voxel centres of a slice sample its strip's edge
at every offset from the grid, so their extremes lie on the edge, give or take a
small fraction of a voxel; with half a voxel added on each side, a sphere's elliptic
hull mesh held 1.11 times its volume at 8 voxels per radius, 1.01–1.02 without,
``tests/test_mesh_hull.py``). The ellipse ``(q − p)ᵀ M⁻¹ (q − p) = 1`` has
support ``aᵀ M a = r²`` in each view's direction and its centre ``p`` on both strips'
centre lines; with ``M = α I + [[β, γ], [γ, −β]]`` the two support conditions are
linear in (α, β, γ), and the least anisotropy ``β² + γ²`` is the minimum-norm solution.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from surfphase.cameras import Camera


def closest_widths(half_widths: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
    """(2,) half-widths within ``half_widths ± tolerance`` (metres, (2,) each) that are
    as close to equal as the tolerance allows: their mean where the two intervals
    overlap (clipped into the overlap), else each moved its tolerance towards the other.

    The least anisotropy of an ellipse with two given supports grows with the
    difference of their squares, the more the closer the two directions are (views 25°
    apart turn half-widths 10 % apart into axes 26 % apart): a difference the
    silhouettes' pixels can make is no evidence of an elongated cross-section.
    """
    r = np.asarray(half_widths, np.float64)
    tol = np.maximum(np.asarray(tolerance, np.float64), 0.0)
    lo, hi = float(np.max(r - tol)), float(np.min(r + tol))
    if lo <= hi:
        return np.full(2, min(max(float(r.mean()), lo), hi))
    big = int(np.argmax(r))
    out = r.copy()
    out[big] -= tol[big]
    out[1 - big] += tol[1 - big]
    return out


def slice_ellipse(
    dirs: np.ndarray,
    centres: np.ndarray,
    half_widths: np.ndarray,
    tolerance: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The ellipse closest to a circle with the given supports in two directions.

    Args:
        dirs: (2, 2) unit across-directions ``a_k`` in the slice plane (x, z).
        centres: (2,) ``a_k · p`` of the strips' centre lines (metres).
        half_widths: (2,) the strips' half-widths ``r_k`` (metres).
        tolerance: (2,) how far each half-width may be off (metres; the silhouettes'
            pixels): the supports are then :func:`closest_widths`'. None: 0.

    Returns:
        ``(p, M)``: (2,) centre and (2, 2) symmetric positive-definite matrix with
        ``a_kᵀ M a_k = r_k²``; ``None`` when the directions are (nearly) parallel or no
        such ellipse exists.
    """
    if tolerance is not None:
        half_widths = closest_widths(half_widths, tolerance)
    a = np.asarray(dirs, np.float64)
    if abs(float(np.linalg.det(a))) < 1e-3:
        return None
    p = np.linalg.solve(a, np.asarray(centres, np.float64))
    phi = np.arctan2(a[:, 1], a[:, 0])
    c2, s2 = np.cos(2 * phi), np.sin(2 * phi)
    r2 = np.asarray(half_widths, np.float64) ** 2
    d = np.array([c2[0] - c2[1], s2[0] - s2[1]])
    beta, gamma = (r2[0] - r2[1]) * d / float(d @ d)
    alpha = r2[0] - beta * c2[0] - gamma * s2[0]
    if alpha - np.hypot(beta, gamma) <= 0:
        return None
    M = np.array([[alpha + beta, gamma], [gamma, alpha - beta]])
    return p, M


def elliptic_hull_distance(
    origin: np.ndarray,
    shape: tuple[int, int, int],
    voxel: float,
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    centre_slices: int = 0,
    width_tol_px: float = 0.0,
) -> np.ndarray:
    """Approximate signed distance (metres, positive outside) of every voxel centre to
    the elliptic hull of the bubbles the labels show (see the module docstring).

    Args:
        origin: (3,) centre of voxel [0, 0, 0], metres (lab frame).
        shape: (nx, ny, nz) voxels. voxel: edge, metres.
        cameras: the first two input views' undistorted cameras.
        labels: per view, the frame's (H, W) int labels (−1 background, ids ≥ 0).
        centre_slices: the ellipses' centres smoothed over this many slices on each side
            (:func:`smooth_centres`; 0: each slice's own).
        width_tol_px: each strip's half-width taken as known to this many of its view's
            pixels (at the slice's distance from the view): the ellipse is the one
            closest to a circle within that (:func:`closest_widths`); 0: exactly.

    Returns:
        (nx, ny, nz) float64: per voxel that both views give one id, its distance to
        that bubble's ellipse in its epipolar slice,
        ``(√((q − p)ᵀ M⁻¹ (q − p)) − 1)·√(tr M / 2)``; ``+inf`` where the two views
        see two different ids (a ghost crossing of their silhouettes' rays) and outside
        either view's image (seen twice nowhere); ``−inf`` (no constraint) elsewhere and
        in slices where no ellipse fits.
    """
    axes = [np.asarray(origin, np.float64)[i] + voxel * np.arange(shape[i]) for i in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    ids = []
    for cam, lab in zip(cameras[:2], labels[:2], strict=True):
        lab = np.asarray(lab)
        h, w = lab.shape
        z = cam.world_to_camera(X)[:, 2]
        uv = np.round(cam.project(X, distort=False)).astype(np.int64)
        seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        i = np.full(len(X), -2, np.int64)  # −2: outside this view's image
        i[seen] = lab[uv[seen, 1], uv[seen, 0]]
        ids.append(i)
    own = np.where((ids[0] == ids[1]) & (ids[0] >= 0), ids[0], -1)
    out = np.full(len(X), -np.inf)
    # Where the two views see two different bubbles, the rays of one cross the other's:
    # a ghost of the visual hull, inside no bubble.
    out[(ids[0] >= 0) & (ids[1] >= 0) & (ids[0] != ids[1])] = np.inf
    # Outside a view's image nothing is seen twice: no bubble can be reconstructed there
    # (the fused volume is solid where no view sees it).
    out[(ids[0] == -2) | (ids[1] == -2)] = np.inf
    c0, c1 = cameras[0].center, cameras[1].center
    u = (c1 - c0) / np.linalg.norm(c1 - c0)  # the baseline, which every epipolar plane holds
    n1 = np.cross(u, [0.0, 1.0, 0.0])
    if np.linalg.norm(n1) < 1e-6:
        n1 = np.cross(u, [1.0, 0.0, 0.0])
    n1 /= np.linalg.norm(n1)
    n2 = np.cross(u, n1)
    rel = X - c0
    s_along = rel @ u  # in-plane coordinates: along the baseline ...
    perp = rel - s_along[:, None] * u
    rho = np.linalg.norm(perp, axis=1)  # ... and the distance from it
    theta = np.arctan2(perp @ n2, perp @ n1)  # which epipolar plane
    s_cam = np.array([0.0, float((c1 - c0) @ u)])
    # Metres per pixel per metre of distance from each view (its focal length, pixels).
    per_px = np.array([2.0 / (c.K[0, 0] + c.K[1, 1]) for c in cameras[:2]])
    for b in np.unique(own[own >= 0]):
        mine = np.flatnonzero(own == b)
        # Slices one voxel thick where the bubble is.
        dtheta = voxel / max(float(np.median(rho[mine])), 1e-12)
        k = np.round(theta[mine] / dtheta).astype(np.int64)
        slices = []
        for kk in np.unique(k):
            sel = mine[k == kk]
            q = np.stack([s_along[sel], rho[sel]], axis=1)
            mid = q.mean(axis=0)
            dirs, cen, half = [], [], []
            for sc in s_cam:
                ray = mid - np.array([sc, 0.0])
                a = np.array([-ray[1], ray[0]]) / max(float(np.linalg.norm(ray)), 1e-12)
                proj = q @ a
                dirs.append(a)
                cen.append(0.5 * (proj.min() + proj.max()))
                half.append(0.5 * (proj.max() - proj.min()))
            dist = np.array([np.hypot(mid[0] - sc, mid[1]) for sc in s_cam])
            tol = float(width_tol_px) * per_px * dist if width_tol_px > 0 else None
            fit = slice_ellipse(np.array(dirs), np.array(cen), np.array(half), tol)
            if fit is not None:
                slices.append((int(kk), sel, q, *fit))
        centres = smooth_centres(
            np.array([sl[0] for sl in slices]),
            np.array([sl[3] for sl in slices]).reshape(-1, 2),
            np.array([len(sl[1]) for sl in slices], np.float64),
            centre_slices,
        )
        for (_, sel, q, _, M), p in zip(slices, centres, strict=True):
            e = q - p
            qf = np.einsum("ni,ij,nj->n", e, np.linalg.inv(M), e)
            out[sel] = (np.sqrt(qf) - 1.0) * np.sqrt(0.5 * np.trace(M))
    return out.reshape(shape)


def smooth_centres(
    index: np.ndarray, centres: np.ndarray, weights: np.ndarray, half_window: int
) -> np.ndarray:
    """(S, 2) slice ellipse centres (metres, in-plane) smoothed along the slices.

    Each slice's centre is replaced by the weighted (``weights``: (S,) voxel counts)
    straight-line fit, over the slices within ``half_window`` of its ``index`` (S,), at
    its own index: a strip's centre is quantised to the voxels, and two views' strips
    meeting at a small angle turn that into a depth error of the centre several times
    larger, which makes the stacked sections zig-zag in depth. 0 leaves them as they are.
    """
    centres = np.asarray(centres, np.float64).reshape(-1, 2)
    if half_window <= 0 or len(centres) < 3:
        return centres
    out = centres.copy()
    for i, k0 in enumerate(index):
        near = np.abs(index - k0) <= half_window
        if near.sum() < 3:
            continue
        x = (index[near] - k0).astype(np.float64)
        A = np.stack([np.ones_like(x), x], axis=1) * np.sqrt(weights[near])[:, None]
        coef = np.linalg.lstsq(A, centres[near] * np.sqrt(weights[near])[:, None], rcond=None)[0]
        out[i] = coef[0]
    return out


#: The most voxels along the longest side of one bubble's fine grid.
MAX_HULL_VOXELS = 128


#: A piece of the nucleation region one view shows apart while the other fuses it with
#: a neighbour (:func:`hidden_pieces`): least number of the other view's pixels its
#: sphere's image must explain that no agreeing pair's does (a 2 × 2 block; a speck
#: on the plate's edge explains 1–3 anywhere in a large piece) ...
HIDDEN_PIECE_MIN_PX = 4
#: ... and least share of that image they must be.
HIDDEN_PIECE_MIN_SHARE = 0.1
#: ... and its sphere must meet the plate: its bottom at most this many radii above it
#: (an attached bubble sits on it; a speck along the plate's edge fits anywhere).
HIDDEN_PIECE_MAX_LIFT_R = 0.25
#: Depths tried along the piece's ray (:func:`hidden_pieces`).
HIDDEN_PIECE_STEPS = 200


def hidden_pieces(
    cameras: Sequence[Camera],
    lab0: np.ndarray,
    lab1: np.ndarray,
    b: int,
    pairs: Sequence[tuple],
) -> list[tuple[np.ndarray, float, np.ndarray, np.ndarray, int]]:
    """The whole pieces of id ``b`` that
    :func:`~surfphase.masks.anchors.agreeing_pieces` left without a partner,
    where the other view's silhouette fuses them with a piece that has one.

    Two attached bubbles side by side can be two pieces in one view and one in the
    other, where one stands in front of the other: the pair the views agree on is the
    nearer bubble with the fused piece, and the other bubble had no mesh. Along the
    unpaired piece's centroid ray (undistorted ``cameras``; depths over the span its
    triangulations with the other view's id-``b`` box give, :data:`HIDDEN_PIECE_STEPS`),
    the sphere of the piece's equivalent radius there, its centre above the plate (lab
    y > 0) and its bottom within :data:`HIDDEN_PIECE_MAX_LIFT_R` of its radius of it, is
    kept where its image in the other view lies on silhouettes (at least
    :data:`~surfphase.masks.stage.MIN_DISC_ON_SILHOUETTE` of it: whatever hides a
    bubble is a bubble too) and holds id-``b`` pixels that no pair's sphere image
    (``pairs``: ``agreeing_pieces``' output) holds, at least
    :data:`HIDDEN_PIECE_MIN_PX` and :data:`HIDDEN_PIECE_MIN_SHARE` of it; the depth
    where it holds most of them (what of the fused outline no pair explains places
    it). Per piece found: ``(centre (3,) m, radius m, mask in view 0, mask in view 1,
    index of the view that fuses it)``, the fusing view's mask the image's id-``b``
    pixels.
    """
    from surfphase.cameras import triangulate
    from surfphase.masks.anchors import silhouette_pieces, sphere_image
    from surfphase.masks.stage import MIN_DISC_ON_SILHOUETTE

    if not pairs:
        return []
    labs = [np.asarray(lab0), np.asarray(lab1)]
    out = []
    for a in (0, 1):
        o = 1 - a
        used = [m0 if a == 0 else m1 for _, _, m0, m1 in pairs]
        lab_o = labs[o]
        ids_o = lab_o == b
        if not ids_o.any():
            continue
        ca, co = cameras[a], cameras[o]
        h, w = lab_o.shape
        vv, uu = np.mgrid[0:h, 0:w]
        explained = np.zeros((h, w), bool)
        for X, r, _, _ in pairs:
            explained |= _sphere_disc(co, X, r, (h, w))
        rows, cols = np.nonzero(ids_o)
        corners = np.array(
            [[cols.min(), rows.min()], [cols.min(), rows.max()], [cols.max(), rows.min()],
             [cols.max(), rows.max()]], np.float64,
        )  # fmt: skip
        ha, wa = labs[a].shape
        for uv, area, mask in silhouette_pieces(labs[a], b):
            if any((mask & m).any() for m in used):
                continue
            r_rows, r_cols = np.nonzero(mask)
            if (
                r_rows.min() == 0
                or r_cols.min() == 0
                or r_rows.max() == ha - 1
                or r_cols.max() == wa - 1
            ):
                continue  # cut by the border: its centroid is not its centre's image
            pts = triangulate([ca, co], [np.repeat(uv[None], 4, axis=0), corners])
            depth = ca.world_to_camera(pts)[:, 2]
            if not np.all(np.isfinite(depth)) or depth.max() <= 0:
                continue
            lo, hi = max(depth.min(), 1e-6), depth.max()
            ray = ca.R.T @ np.linalg.solve(ca.K, np.array([uv[0], uv[1], 1.0]))
            ray = ray / float((ca.R @ ray)[2])  # one metre of depth
            f = float(np.sqrt(ca.K[0, 0] * ca.K[1, 1]))
            best = None
            for z in np.linspace(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), HIDDEN_PIECE_STEPS):
                X = np.asarray(ca.center, np.float64) + z * ray
                r = float(np.sqrt(area / np.pi)) * z / f
                on_plate = 0 < X[1] <= r * (1.0 + HIDDEN_PIECE_MAX_LIFT_R)
                c = sphere_image(co, X, r) if z > 0 and on_plate else None
                if c is None:
                    continue
                disc = np.hypot(uu - c[0], vv - c[1]) <= c[2]
                n = int(disc.sum())
                if n == 0 or (disc & (lab_o >= 0)).sum() < MIN_DISC_ON_SILHOUETTE * n:
                    continue
                new = int((disc & ids_o & ~explained).sum())
                if new < max(HIDDEN_PIECE_MIN_PX, HIDDEN_PIECE_MIN_SHARE * n):
                    continue
                if best is None or new > best[0]:
                    best = (new, X, r, disc & ids_o)
            if best is None:
                continue
            masks = (mask, best[3]) if a == 0 else (best[3], mask)
            out.append((best[1], best[2], masks[0], masks[1], o))
    return out


def _sphere_disc(cam: Camera, X: np.ndarray, r: float, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool pixel centres inside the image of the sphere (``X`` (3,) m, ``r`` m)
    in the undistorted ``cam`` (all False behind it)."""
    from surfphase.masks.anchors import sphere_image

    c = sphere_image(cam, X, r)
    if c is None:
        return np.zeros(shape, bool)
    vv, uu = np.mgrid[0 : shape[0], 0 : shape[1]]
    return np.hypot(uu - c[0], vv - c[1]) <= c[2]


def bubble_pieces(
    cameras: Sequence[Camera], labels: Sequence[np.ndarray]
) -> list[tuple[int, np.ndarray, float, list[np.ndarray], bool, list[bool]]]:
    """Where each bubble is, roughly, and what of each view's labels is it.

    Per id ≥ 1 that both views' labels show: ``(id, centre, radius, masks, agree)``,
    the (3,) centre (metres) its silhouettes' centroids triangulate to, the radius
    (metres, the silhouettes' mean equivalent radius √(area/π) times depth / focal), its
    two (H, W) bool silhouettes, and whether the two are one object by the rule of the
    nucleation region's pieces (the centroids' point reprojects within
    :data:`~surfphase.masks.anchors.PIECE_REPROJ_R` of each silhouette's equivalent
    radius, the sizes there within :data:`~surfphase.masks.anchors.PIECE_SIZE_RATIO`).
    The nucleation region (:data:`~surfphase.masks.anchors.NUCLEATION_ID`) holds every
    attached bubble, and the two views need not hold the same pieces of it: one entry
    per pair of pieces the two views agree on
    (:func:`surfphase.masks.anchors.agreeing_pieces`), and one per piece left over that
    the other view fuses with a paired one (:func:`hidden_pieces`:
    its sphere's image there); with no such pair, its whole silhouettes as one
    (``agree`` False). The last item, per view, is whether that view's silhouette is
    shared with another entry (a fused piece: its area is not this entry's alone).
    """
    from surfphase.masks.anchors import (
        NUCLEATION_ID,
        agreeing_pieces,
        pair_sphere,
        pieces_agree,
    )

    lab0, lab1 = (np.asarray(lb) for lb in labels[:2])
    out = []
    for b in sorted(set(np.unique(lab0)) & set(np.unique(lab1))):
        if b < 0:
            continue
        found = []
        if b == NUCLEATION_ID:
            pairs = agreeing_pieces(cameras, lab0, lab1, int(b))
            hidden = hidden_pieces(cameras, lab0, lab1, int(b), pairs)
            for X, r, m0, m1 in pairs:
                # A pair whose piece a hidden one's image lies on shares that silhouette,
                # and leaves it what of that image lies outside its own sphere's.
                masks, shared = [m0, m1], [False, False]
                for h in hidden:
                    k = h[4]
                    if (masks[k] & h[2 + k]).any():
                        shared[k] = True
                        masks[k] = masks[k] & ~(
                            h[2 + k] & ~_sphere_disc(cameras[k], X, r, masks[k].shape)
                        )
                found.append((int(b), X, r, masks, True, shared))
            found += [
                (int(b), X, r, [m0, m1], True, [o == 0, o == 1]) for X, r, m0, m1, o in hidden
            ]
        if not found:
            masks = [lab0 == b, lab1 == b]
            uvs, areas = [], []
            for m in masks:
                rr, cc = np.nonzero(m)
                uvs.append(np.array([cc.mean(), rr.mean()]))
                areas.append(float(len(rr)))
            sp = pair_sphere(cameras, uvs, areas)
            if sp is not None and sp[1] > 0:
                agree = pieces_agree(sp)
                found = [
                    (
                        int(b),
                        sp[0],
                        sp[1],
                        masks,
                        bool(agree and b != NUCLEATION_ID),
                        [False, False],
                    )
                ]
        out += found
    return out


def _cube(centre: np.ndarray, half: float, voxel: float) -> tuple[np.ndarray, tuple]:
    n = int(np.ceil(2 * half / voxel)) + 1
    return np.asarray(centre, np.float64) - half, (n, n, n)


def _own_box(
    origin: np.ndarray, shape: tuple, voxel: float, cameras, labels, b: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners (metres) of the voxel centres both views give id ``b``."""
    axes = [origin[i] + voxel * np.arange(shape[i]) for i in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    own = np.ones(len(X), bool)
    for cam, lab in zip(cameras[:2], labels[:2], strict=True):
        lab = np.asarray(lab)
        h, w = lab.shape
        z = cam.world_to_camera(X)[:, 2]
        uv = np.round(cam.project(X, distort=False)).astype(np.int64)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        hit = np.zeros(len(X), bool)
        hit[ok] = lab[uv[ok, 1], uv[ok, 0]] == b
        own &= hit
    if not own.any():
        return None
    return X[own].min(axis=0), X[own].max(axis=0)


def bubble_hull_volume(
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    b: int,
    centre: np.ndarray,
    radius: float,
    voxels_per_radius: float,
    trunc_voxels: float,
    centre_slices: int = 0,
    width_tol_px: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Signed distance volume of one bubble's elliptic hull on its own grid.

    A coarse cube about ``centre`` (half-size the radius over the sine of half the
    views' angle, enough for the visual hull's elongation along their bisector) finds
    the voxels both views give id ``b``; a fine grid (``radius / voxels_per_radius``
    voxels) over their box, with a margin, holds the distance: the elliptic hull's
    (:func:`elliptic_hull_distance`) where both views see ``b``, the distance to the
    silhouettes' visual hull elsewhere, clipped at ``trunc_voxels`` voxels.
    ``centre_slices``, ``width_tol_px``: as :func:`elliptic_hull_distance`'s.

    Returns ``(sdf (nx, ny, nz) float32 m, origin (3,) m, voxel m)``, or None when no
    voxel is seen as ``b`` by both views.
    """
    from surfphase.mesh.surfaces import silhouette_distance

    own_labels = [np.where(np.asarray(lb) == b, b, -1) for lb in labels[:2]]
    rays = [c - cam.center for cam, c in zip(cameras[:2], (centre, centre), strict=True)]
    cosang = float(rays[0] @ rays[1] / (np.linalg.norm(rays[0]) * np.linalg.norm(rays[1])))
    sin_half = np.sqrt(max(0.5 * (1.0 - cosang), 0.01))  # views ≥ 11.5° apart: ≤ 82³ voxels
    coarse = radius / 3.0
    origin, shape = _cube(centre, radius * (1.5 + 1.2 / sin_half), coarse)
    box = _own_box(origin, shape, coarse, cameras, own_labels, b)
    if box is None:
        return None
    # At most MAX_HULL_VOXELS along the box's longest side (a wide nucleation region).
    voxel = max(radius / float(voxels_per_radius), float(np.max(box[1] - box[0])) / MAX_HULL_VOXELS)
    margin = coarse + (float(trunc_voxels) + 2.0) * voxel
    lo, hi = box[0] - margin, box[1] + margin
    shape = tuple(int(np.ceil(s)) + 1 for s in (hi - lo) / voxel)
    vis = silhouette_distance(lo, shape, voxel, list(cameras[:2]), [lb >= 0 for lb in own_labels])
    ell = elliptic_hull_distance(lo, shape, voxel, cameras, own_labels, centre_slices, width_tol_px)
    trunc = float(trunc_voxels) * voxel
    sdf = np.clip(np.maximum(vis, ell), -trunc, trunc).astype(np.float32)
    return sdf, lo, voxel
