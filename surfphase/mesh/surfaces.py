"""What a frame's mesh is made of (config ``mesh: surface``): the surfels' depth maps
fused into a TSDF and carved by the masks' hulls (:func:`mesh_frame`, ``fused``), or
each bubble's elliptic hull on its own grid (:func:`hull_mesh_frame`, ``hull``), and the
vertices' velocities. Pure functions of one frame; :mod:`surfphase.mesh.stage` runs them
over a session.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from surfphase.cameras import Camera, orbit_cameras
from surfphase.masks.anchors import NUCLEATION_ID, pair_sphere
from surfphase.mesh.cleanup import clean_mesh, drop_fragments
from surfphase.mesh.fuse import fuse_depths, marching_cubes_mesh, render_depths, voxel_grid
from surfphase.mesh.hull import bubble_hull_volume, bubble_pieces, elliptic_hull_distance


def vertex_velocities(
    verts: np.ndarray, surfel_means: np.ndarray, surfel_velocity: np.ndarray
) -> np.ndarray:
    """(V, 3) velocity (m/s) of each vertex: that of the nearest surfel ((N, 3) metres,
    (N, 3) m/s)."""
    if len(verts) == 0:
        return np.zeros((0, 3))
    _, idx = cKDTree(surfel_means).query(verts)
    return np.asarray(surfel_velocity, np.float64)[idx]


def view_cameras(inputs: list[Camera], center: np.ndarray, p: dict) -> list[Camera]:
    """Input cameras plus orbit views about ``center``, all scaled by ``render_scale``."""
    cams = [c.undistorted() for c in inputs]
    if int(p["n_orbit"]) > 0:
        cams += orbit_cameras(cams[0], center, int(p["n_orbit"]), float(p["orbit_step_deg"]))
    return [c.scaled(float(p["render_scale"])) for c in cams]


def mesh_frame(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity: np.ndarray,
    inputs: list[Camera],
    p: dict,
    device: str = "cpu",
    labels: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh of one frame's surfels ((N, 3) m, (N, 4), (N, 2) ln m, (N,)) seen by the
    input cameras; returns (V, 3) vertices (metres) and (F, 3) faces. ``labels``: per
    input camera, the frame's (H, W) int masks (−1 background), for ``carve_px`` and
    ``ellipse_hull``."""
    extent = float(np.ptp(means, axis=0).max())
    voxel = float(p["voxel_m"]) if p["voxel_m"] else extent / float(p["voxels"])
    trunc = float(p["trunc_voxels"]) * voxel
    cams = view_cameras(inputs, means.mean(0), p)
    keep = opacity >= float(p["opacity_min"])
    if keep.sum() < 4:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    depths = render_depths(
        means[keep],
        quats[keep],
        log_scales[keep] + np.log(float(p["scale_factor"])),
        np.ones(int(keep.sum())) if p["solid"] else opacity[keep],
        cams,
        device,
        p["alpha_min"],
        p["silhouette_alpha"],
    )
    origin, shape = voxel_grid(means, voxel, float(p["margin_voxels"]) * voxel)
    sdf = fuse_depths(depths, cams, origin, shape, voxel, trunc)
    if p["floor_y"] is not None:
        sdf = cut_below(sdf, origin, voxel, float(p["floor_y"]), trunc)
    if labels is not None and p["carve_px"] is not None:
        views = [c.undistorted() for c in inputs]
        hull = silhouette_distance(
            origin, sdf.shape, voxel, views, [np.asarray(m) >= 0 for m in labels],
            float(p["carve_px"]),
        )  # fmt: skip
        if p["ellipse_hull"] and len(views) >= 2:
            hull = np.maximum(hull, elliptic_hull_distance(origin, sdf.shape, voxel, views, labels))
        sdf = np.maximum(sdf, np.clip(hull, -trunc, trunc).astype(sdf.dtype))
    verts, faces = marching_cubes_mesh(sdf, origin, voxel)
    return clean_mesh(
        verts,
        faces,
        float(p["min_component_m"]),
        int(p["smooth_steps"]),
        int(p["max_hole_edges"]),
    )


def hull_mesh_frame(
    inputs: list[Camera],
    labels: list[np.ndarray],
    p: dict,
    hints: dict[int, tuple[np.ndarray, float]] | None = None,
    centres: dict[int, np.ndarray] | None = None,
    areas: dict[int, list[float]] | None = None,
    hidden: dict[int, list[np.ndarray | None]] | None = None,
    spared: set[int] | frozenset[int] = frozenset(),
    pieces: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mesh of one frame's bubbles as their elliptic hulls (``mesh: surface: hull``).

    Every id that both input views' (H, W) labels show (with ``hull_agreeing``, an id
    ≥ 1 only where its two silhouettes are one object,
    :func:`surfphase.mesh.hull.bubble_pieces`, or it is in ``spared``,
    :func:`surfphase.mesh.stage.spared_ids`, or has a ``centres`` entry) is meshed on
    its own grid
    (:func:`surfphase.mesh.hull.bubble_hull_volume`, ``hull_voxels_per_radius``), cut at
    the plate (``floor_y``) and cleaned; an id in several pieces (the nucleation region,
    id 0, can hold different pieces in each view) once per pair of pieces the two views
    agree on and per piece one view fuses with a paired one, as its sphere's image there
    (:func:`surfphase.mesh.hull.bubble_pieces`). Where the silhouettes'
    centroids triangulate to no point both views see, ``hints`` (id → (3,) centre m,
    radius m; e.g. from the fit's surfels) place the search instead. A bubble (id ≥ 1)
    with a ``centres`` entry (id → (3,) m: its reported centre, the triangulated
    sub-pixel silhouette centres smoothed along its track) has its hull moved, before
    the cut at the plate, so that the centroid of its inside voxels is there: the
    hull's own centre comes from voxel-quantised strips, whose error two views at a
    small angle multiply in depth. A bubble (id ≥ 1) with an ``areas`` entry (id → per
    view, the area in pixels of its silhouette at the recording's native resolution,
    counted in these views' pixels) has its mesh scaled about its centre so that its
    images have those areas (:func:`scale_to_silhouettes`, ``hull_native_area``): the
    labels the hull is made from are the fit's, and a bubble a few of their pixels
    across loses a part of its volume to their pixels and the hull's slices. A bubble
    with a ``hidden`` entry (id → per view, the (H, W) bool pixels it covers behind
    other bubbles there, or None) has those pixels added to its silhouette in that view,
    and that view's area left out of the scaling; so has each piece of the nucleation
    region, of ``hidden[0]``'s pixels, those that touch it (:func:`_touching`). With ``pieces`` (per view, (N, 3)
    centroid column, row and native area, pixels, of the nucleation region's whole
    pieces), each hull of the nucleation region is scaled in the same way to the areas
    of the pieces whose centroids lie on its silhouette in each view, a view whose
    piece it shares with another hull left out: a bubble growing on the plate is a few
    pixels across for most of its growth. Returns (V, 3) vertices
    (m), (F, 3) faces and (V,) each vertex's bubble id.
    """
    views = [c.undistorted() for c in inputs]
    verts, faces, ids, n = [], [], [], 0
    for b, centre, radius, masks, agree, shared in bubble_pieces(views, labels):
        behind = (hidden or {}).get(b) if b >= 1 else _touching(hidden, b, masks)
        known = b in spared or (bool(centres) and b in centres) or behind is not None
        if p["hull_agreeing"] and b >= 1 and not (agree or known):
            continue  # never one object in both views: a hull would be a ghost
        if behind is not None:
            masks = [m if h is None else m | h for m, h in zip(masks, behind, strict=True)]
            uvs = [np.argwhere(m).mean(axis=0)[::-1] for m in masks]  # (column, row)
            sp = pair_sphere(views, uvs, [float(m.sum()) for m in masks])
            if sp is not None and sp[1] > 0:  # where the whole silhouettes put it
                centre, radius = sp[0], sp[1]
        own = [np.where(m, b, -1) for m in masks]
        vol = None
        for c, r in [(centre, radius)] + ([hints[b]] if hints and b in hints else []):
            vol = bubble_hull_volume(
                views, own, b, c, r,
                float(p["hull_voxels_per_radius"]), float(p["trunc_voxels"]),
                int(p["hull_centre_slices"]), float(p["hull_width_tol_px"]),
            )  # fmt: skip
            if vol is not None:
                break
        if vol is None:
            continue
        sdf, origin, voxel = vol
        if centres and b >= 1 and b in centres and (sdf < 0).any():
            inside = np.argwhere(sdf < 0).mean(axis=0)
            origin = np.asarray(centres[b], np.float64) - voxel * inside
        if p["floor_y"] is not None:
            trunc = float(p["trunc_voxels"]) * voxel
            sdf = cut_below(sdf, origin, voxel, float(p["floor_y"]), trunc)
        v, f = marching_cubes_mesh(sdf, origin, voxel)
        v, f = clean_mesh(
            v, f, float(p["min_component_m"]), int(p["smooth_steps"]), int(p["max_hole_edges"])
        )
        v, f = drop_fragments(v, f, float(p["min_piece_frac"]))
        # The views whose silhouette is this hull's own: none behind others, none shared.
        seen = [
            k for k in range(len(views))
            if (behind is None or behind[k] is None) and not shared[k]
        ]  # fmt: skip
        if len(f) and areas and b >= 1 and b in areas:
            centre_b = centres[b] if centres and b in centres else v.mean(axis=0)
            v = scale_to_silhouettes(
                v, f, [views[k] for k in seen], [areas[b][k] for k in seen], centre_b,
                tuple(p["hull_area_limits"]),
            )  # fmt: skip
            if p["floor_y"] is not None:
                v[:, 1] = np.maximum(v[:, 1], float(p["floor_y"]))
        elif len(f) and pieces is not None and b == NUCLEATION_ID:
            native = [_area_on(m, pc) for m, pc in zip(masks, pieces, strict=False)]
            if len(native) == len(views) and all(native[k] > 0 for k in seen):
                v = scale_to_silhouettes(
                    v, f, [views[k] for k in seen], [native[k] for k in seen], v.mean(axis=0),
                    tuple(p["hull_area_limits"]),
                )  # fmt: skip
                if p["floor_y"] is not None:
                    v[:, 1] = np.maximum(v[:, 1], float(p["floor_y"]))
        if len(f):
            verts.append(v)
            faces.append(f + n)
            ids.append(np.full(len(v), b, np.int64))
            n += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(ids)


def _touching(
    hidden: dict[int, list[np.ndarray | None]] | None, b: int, masks: list[np.ndarray]
) -> list[np.ndarray | None] | None:
    """For a piece of the nucleation region (id ``b``, its (H, W) bool ``masks`` per
    view), the parts of ``hidden[b]`` (per view, bubbles' pixels that hide attached
    bubbles, or None) that touch the piece's silhouette in each view (8-connected
    pieces of it sharing an edge or corner with it); None where no view has any."""
    per_view = (hidden or {}).get(b)
    if per_view is None:
        return None
    out: list[np.ndarray | None] = []
    for m, h in zip(masks, per_view, strict=True):
        if h is None or not h.any():
            out.append(None)
            continue
        comp, n = ndi.label(h, structure=np.ones((3, 3), bool))
        near = ndi.binary_dilation(m, structure=np.ones((3, 3), bool))
        keep = np.unique(comp[near & (comp > 0)])
        out.append(np.isin(comp, keep) if len(keep) else None)
    return out if any(x is not None for x in out) else None


def _area_on(mask: np.ndarray, pieces: np.ndarray) -> float:
    """Summed area (third column) of the ``pieces`` ((N, 3) centroid column, row, area)
    whose centroids fall on the (H, W) bool ``mask``; 0 where none does."""
    pc = np.asarray(pieces, np.float64).reshape(-1, 3)
    h, w = mask.shape
    col, row = np.rint(pc[:, 0]).astype(int), np.rint(pc[:, 1]).astype(int)
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    on = np.zeros(len(pc), bool)
    on[ok] = mask[row[ok], col[ok]]
    return float(pc[on, 2].sum())


def projected_area(cam: Camera, verts: np.ndarray, faces: np.ndarray) -> float:
    """Area (pixels) of the image of a closed mesh in a camera (no distortion).

    Every ray through the image of a closed surface crosses it an even number of
    times, twice where the body is convex along the ray, so half the summed areas of
    the projected triangles is the image's area, exactly for a convex body (a bubble's
    hull; more where a ray crosses four times).

    Args:
        cam: the (undistorted) camera. verts: (V, 3) m. faces: (F, 3) vertex indices.
    """
    if len(faces) == 0:
        return 0.0
    uv = cam.project(np.asarray(verts, np.float64), distort=False)
    a, b, c = uv[faces[:, 0]], uv[faces[:, 1]], uv[faces[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return float(0.25 * np.abs(cross).sum())


def scale_to_silhouettes(
    verts: np.ndarray,
    faces: np.ndarray,
    views: list[Camera],
    areas: list[float],
    centre: np.ndarray,
    limits: tuple[float, float],
) -> np.ndarray:
    """A bubble's mesh scaled about ``centre`` ((3,) m) so that its images have the
    silhouettes' areas: by the geometric mean over the views of √(area / projected
    area) (:func:`projected_area`), when that factor lies within ``limits``; otherwise
    (the masks and the hull disagree on more than a size) unchanged.

    Args:
        verts: (V, 3) m. faces: (F, 3). views: the cameras the areas are seen in.
        areas: per view, the silhouette's area (pixels of that camera).
    """
    ratios = []
    for cam, area in zip(views, areas, strict=True):
        proj = projected_area(cam, verts, faces)
        if not (proj > 0 and area > 0):
            return verts
        ratios.append(area / proj)
    if not ratios:
        return verts
    k = float(np.prod(ratios) ** (0.5 / len(ratios)))
    if not limits[0] <= k <= limits[1]:
        return verts
    c = np.asarray(centre, np.float64)
    return c + k * (np.asarray(verts, np.float64) - c)


def surfel_spheres(means: np.ndarray, bubble: np.ndarray) -> dict[int, tuple[np.ndarray, float]]:
    """Per bubble id with surfels ((N, 3) m, (N,) ids): the (3,) centre of their box
    and half its diagonal (metres)."""
    out = {}
    for b in np.unique(bubble):
        m = np.asarray(means)[np.asarray(bubble) == b]
        lo, hi = m.min(axis=0), m.max(axis=0)
        out[int(b)] = (0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 1e-5))
    return out


def bubble_vertex_velocities(
    verts: np.ndarray,
    vertex_bubble: np.ndarray,
    surfel_means: np.ndarray,
    surfel_bubble: np.ndarray,
    surfel_velocity: np.ndarray,
) -> np.ndarray:
    """(V, 3) velocity (m/s) of each vertex: that of the nearest surfel of its own bubble
    ((V,) ids; surfels (N, 3) m, (N,) ids, (N, 3) m/s); NaN for a bubble the fit gave
    no surfels (its speed is unknown, not zero)."""
    out = np.full((len(verts), 3), np.nan)
    for b in np.unique(vertex_bubble):
        mine = np.flatnonzero(np.asarray(surfel_bubble) == b)
        if mine.size:
            sel = np.flatnonzero(vertex_bubble == b)
            out[sel] = vertex_velocities(verts[sel], surfel_means[mine], surfel_velocity[mine])
    return out


def cut_below(
    sdf: np.ndarray, origin: np.ndarray, voxel: float, floor_y: float, trunc: float
) -> np.ndarray:
    """(nx, ny, nz) signed distance volume (metres, positive outside, voxel [0, 0, 0]
    centred at ``origin``) intersected with the half-space y ≥ ``floor_y``: the
    maximum of the two signed distances, the half-space's truncated at ``trunc``."""
    y = np.asarray(origin, np.float64)[1] + voxel * np.arange(sdf.shape[1])
    below = np.clip(floor_y - y, -trunc, trunc).astype(sdf.dtype)
    return np.maximum(sdf, below[None, :, None])


def silhouette_distance(
    origin: np.ndarray,
    shape: tuple[int, int, int],
    voxel: float,
    cameras: list[Camera],
    silhouettes: list[np.ndarray],
    grow_px: float = 0.0,
) -> np.ndarray:
    """Approximate signed distance (metres, positive outside) of every voxel centre of
    a grid (``shape``, voxel [0, 0, 0] centred at ``origin``, edge ``voxel`` m) to the
    visual hull of ``silhouettes`` ((H, W) bool per camera, grown by ``grow_px``).

    Per view: the image's signed distance to its silhouette (pixels, Euclidean distance
    transform, positive outside) at the pixel the voxel projects to, times depth / focal
    length; the hull's is the largest over the views. A voxel outside a view's image or
    behind it is not constrained by that view.
    """
    from scipy import ndimage as ndi

    axes = [np.asarray(origin, np.float64)[i] + voxel * np.arange(shape[i]) for i in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    out = np.full(len(X), -np.inf)
    for cam, sil in zip(cameras, silhouettes, strict=True):
        sil = np.asarray(sil, bool)
        signed = ndi.distance_transform_edt(~sil) - ndi.distance_transform_edt(sil) - grow_px
        z = cam.world_to_camera(X)[:, 2]
        uv = cam.project(X, distort=False)
        h, w = sil.shape
        col, row = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        seen = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
        d = np.full(len(X), -np.inf)
        d[seen] = signed[row[seen], col[seen]] * z[seen] / f
        out = np.maximum(out, d)
    return out.reshape(shape)
