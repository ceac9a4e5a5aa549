"""Initial surfels inside the visual hull of the bubble masks, in metres.

1. Each bubble id seen in at least two views is triangulated from its mask centroids;
   its equivalent radius is the mask's equivalent-disk radius back-projected at that
   depth (``r = sqrt(area/π) · z / f``), averaged over views. These spheres bound the
   scene.
2. A voxel grid over the (padded) union of the spheres is carved: a voxel is kept when
   it projects onto the bubble's mask (or any foreground, for a whole frame) in every
   view.
3. Surfels are placed on the hull's surface voxels, facing outwards (the gradient of the
   smoothed occupancy), with the mean colour of the pixels they project onto.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from surfphase.cameras import Camera, triangulate


@dataclass
class HullSurfels:
    """Surfel seeds: ``points`` (N, 3) m, ``normals`` (N, 3), ``colors`` (N, D), ``spacing`` m."""

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    spacing: float


def bubble_spheres(
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    min_pixels: int = 4,
    radius: str = "mean",
) -> dict[int, tuple[np.ndarray, float]]:
    """``{bubble: (centre (3,) m, radius m)}`` of every bubble id seen in ≥ 2 views.

    Args:
        cameras: undistorted cameras, one per view.
        labels: per view an (H, W) int mask (``-1`` background).
        min_pixels: smallest mask (pixels) that counts as seen.
        radius: ``"mean"`` or ``"max"`` over the views of the mask's equivalent radius
            at the centre's depth (``"max"`` is not fooled by a bubble half hidden in
            one view).
    """
    if radius not in ("mean", "max"):
        raise ValueError(f"radius must be 'mean' or 'max', not {radius!r}")
    ids: set[int] = set()
    for lab in labels:
        ids.update(int(b) for b in np.unique(lab[lab >= 0]))
    out: dict[int, tuple[np.ndarray, float]] = {}
    for b in sorted(ids):
        cams, uvs, areas = [], [], []
        for cam, lab in zip(cameras, labels, strict=True):
            rows, cols = np.nonzero(lab == b)
            if rows.size < min_pixels:
                continue
            cams.append(cam)
            uvs.append(np.array([[cols.mean(), rows.mean()]]))
            areas.append(rows.size)
        if len(cams) < 2:
            continue
        c = triangulate(cams, uvs)[0]
        radii = []
        for cam, a in zip(cams, areas, strict=True):
            z = cam.world_to_camera(c[None])[0, 2]
            if z <= 0:
                continue
            f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
            radii.append(np.sqrt(a / np.pi) * z / f)
        if radii and np.all(np.isfinite(c)):
            out[b] = (c, float(np.mean(radii) if radius == "mean" else np.max(radii)))
    return out


def scene_extent(spheres: dict[int, tuple[np.ndarray, float]]) -> float:
    """Scene extent ``L`` (m): radius of the sphere about the bubbles' bounding-box centre
    that holds every bubble sphere. The unit of the fit's normalised quantities."""
    if not spheres:
        raise ValueError("scene_extent: no bubble is seen in two views")
    lo = np.min([c - r for c, r in spheres.values()], axis=0)
    hi = np.max([c + r for c, r in spheres.values()], axis=0)
    centre = 0.5 * (lo + hi)
    return float(max(np.linalg.norm(c - centre) + r for c, r in spheres.values()))


def _sample_colors(
    points: np.ndarray, cameras: Sequence[Camera], images: Sequence[np.ndarray]
) -> np.ndarray:
    cols = []
    for cam, img in zip(cameras, images, strict=True):
        uv = cam.project(points, distort=False)
        H, W = img.shape[:2]
        c = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
        r = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
        v = img[r, c]
        cols.append(v.reshape(points.shape[0], -1))
    return np.mean(cols, axis=0).astype(np.float64)


def visual_hull_surfels(
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    images: Sequence[np.ndarray],
    bubble: int | None = None,
    spheres: dict[int, tuple[np.ndarray, float]] | None = None,
    grid: int = 48,
    pad: float = 1.5,
    occlusion: bool = False,
    occlusion_ratio: float = 0.75,
) -> HullSurfels:
    """Surfel seeds on the surface of the visual hull of the masks.

    Args:
        cameras: undistorted cameras, one per view.
        labels: per view an (H, W) int mask (``-1`` background).
        images: per view an (H, W[, D]) image in [0, 1].
        bubble: carve this bubble id only (a newly appearing bubble); ``None`` carves
            all foreground (the first frame).
        spheres: precomputed :func:`bubble_spheres`.
        grid: voxels along the longest side of the bounding box.
        pad: bounding spheres are enlarged by this factor before carving.
        occlusion: with ``bubble``, a pixel of another bubble ``o`` does not carve a
            voxel that ``o`` can hide there: one behind ``o``'s sphere centre (depth along
            that camera's axis) and outside ``o``'s sphere. Without it a bubble partly
            hidden behind another in one view loses the hidden part from its hull.
            The nucleation region (id 0) is neither an occluder nor occluded: it sits on
            the plate and is not a sphere, so neither its size nor "outside its sphere"
            says anything about what is hidden.
        occlusion_ratio: occlusion applies only in the views where the bubble's mask has
            fewer than this fraction of the pixels of its largest mask over the views: a
            sphere's silhouette is about the same size from cameras at the same distance,
            so only a mask much smaller than in another view shows a hidden part. A
            bubble seen whole in every view (a split, a false merge, a bubble leaving the
            nucleation region) keeps its plain hull. ``inf``: every view.

    Returns:
        :class:`HullSurfels` (possibly empty when nothing is carved).
    """
    if spheres is None:
        spheres = bubble_spheres(cameras, labels)
    use = {bubble: spheres[bubble]} if bubble is not None else spheres
    if bubble is not None and bubble not in spheres:
        D = images[0].shape[2] if images[0].ndim == 3 else 1
        return HullSurfels(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, D)), 0.0)
    if not use:
        raise ValueError("visual hull: no bubble mask is seen in two views")
    lo = np.min([c - pad * r for c, r in use.values()], axis=0)
    hi = np.max([c + pad * r for c, r in use.values()], axis=0)
    spacing = float((hi - lo).max() / grid)
    n = np.maximum(np.ceil((hi - lo) / spacing).astype(int) + 1, 2)
    axes = [lo[k] + spacing * np.arange(n[k]) for k in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    inside = np.ones(pts.shape[0], dtype=bool)
    # Other bubbles that may hide this one: (id, centre, voxels outside their sphere).
    occluders = (
        [(o, co, np.linalg.norm(pts - co, axis=1) > ro) for o, (co, ro) in spheres.items()
         if o not in (bubble, 0)]
        if bubble not in (None, 0) and occlusion
        else []
    )  # fmt: skip
    if occluders:
        areas = np.array([np.count_nonzero(lab == bubble) for lab in labels], dtype=np.float64)
        hiding = areas < occlusion_ratio * areas.max()
    else:
        hiding = np.zeros(len(labels), dtype=bool)
    for cam, lab, hides in zip(cameras, labels, hiding, strict=True):
        H, W = lab.shape
        z = cam.world_to_camera(pts)[:, 2]
        uv = cam.project(pts, distort=False)
        c = np.rint(uv[:, 0]).astype(np.int64)
        r = np.rint(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (c >= 0) & (c < W) & (r >= 0) & (r < H)
        hit = np.zeros(pts.shape[0], dtype=bool)
        lv = lab[r[ok], c[ok]]
        hit[ok] = (lv == bubble) if bubble is not None else (lv >= 0)
        for o, co, outside in occluders if hides else ():
            on_o = np.zeros(pts.shape[0], dtype=bool)
            on_o[ok] = lv == o
            hit |= on_o & outside & (z > cam.world_to_camera(co[None])[0, 2])
        inside &= hit
    occ = inside.reshape(X.shape)
    surface = occ & ~ndimage.binary_erosion(occ, border_value=0)
    smooth = ndimage.gaussian_filter(occ.astype(np.float64), sigma=1.0)
    grads = np.stack(np.gradient(smooth), axis=-1)  # (nx, ny, nz, 3) per voxel
    pts_s = pts[surface.ravel()]
    nrm = -grads[surface]
    norm = np.linalg.norm(nrm, axis=1, keepdims=True)
    # A voxel with no occupancy gradient (a 1-voxel-thin sliver) faces the first camera.
    fallback = -cameras[0].view_dir
    nrm = np.where(norm > 1e-9, nrm / np.maximum(norm, 1e-12), fallback)
    colors = _sample_colors(pts_s, cameras, images) if len(pts_s) else np.zeros((0, 1))
    return HullSurfels(pts_s, nrm, colors, spacing)
