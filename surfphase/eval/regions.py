"""The bubbles' region of a view: where the true bubbles project, for region metrics.

A held-out view is mostly the heated plate and the backlight, which the fit does not
reconstruct (it reconstructs bubbles; the input views' backgrounds are composited
behind them) and which every other camera sees differently. Image metrics inside the
bubbles' region judge the reconstruction itself.

Region of a frame in a camera: the union of the silhouettes of spheres centred on the
true bubble centroids with radius ``scale · r_eq`` (``r_eq``: the bubble's equivalent
radius, metres; default ``scale`` 1.5, so the region holds each bubble's whole rim and
a margin for a misplaced reconstruction). The silhouettes are exact: a pixel is inside
when its viewing ray (through the pixel centre, the camera's distortion undone) passes
within the radius of the centre, in front of the camera. Projected spheres rather than
bounding boxes: a box around a tall bubble column would be mostly background again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from surfphase.cameras import Camera

#: Region radius as a multiple of the true equivalent radius.
REGION_SCALE = 1.5


def pixel_ray_grid(camera: Camera) -> np.ndarray:
    """(H, W, 3) unit world directions of the rays through every pixel centre."""
    vv, uu = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    return camera.pixel_rays(uv, distorted=True).reshape(camera.height, camera.width, 3)


def sphere_silhouettes(
    camera: Camera,
    centres: np.ndarray,
    radii: np.ndarray,
    rays: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels whose ray meets at least one of the spheres.

    Args:
        camera: the view.
        centres: (N, 3) sphere centres, metres, world frame.
        radii: (N,) sphere radii, metres.
        rays: (H, W, 3) :func:`pixel_ray_grid` of ``camera``, if already computed.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(radii) != len(centres):
        raise ValueError(f"{len(centres)} sphere centres but {len(radii)} radii")
    if rays is None:
        rays = pixel_ray_grid(camera)
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    for c, r in zip(centres - camera.center, radii, strict=True):
        if not (np.all(np.isfinite(c)) and np.isfinite(r) and r > 0):
            continue
        dist2 = float(c @ c)
        if dist2 <= r * r:  # the camera is inside the sphere: it sees only the sphere
            mask[:] = True
            break
        along = rays @ c  # (H, W) distance along each ray to the closest approach
        mask |= (along > 0) & (dist2 - along**2 <= r * r)
    return mask


def bubble_region(
    camera: Camera,
    bubbles: pd.DataFrame,
    scale: float = REGION_SCALE,
    rays: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool region of the true bubbles of one frame in ``camera``.

    Args:
        bubbles: rows of one frame with ``x, y, z`` (centroid, m) and ``r_eq`` (m).
        scale: sphere radius as a multiple of ``r_eq``.
        rays: :func:`pixel_ray_grid` of ``camera``, if already computed.
    """
    if not scale > 0:
        raise ValueError(f"region scale must be positive, got {scale}")
    xyz = bubbles[["x", "y", "z"]].to_numpy(np.float64)
    r = scale * bubbles["r_eq"].to_numpy(np.float64)
    return sphere_silhouettes(camera, xyz, r, rays)


def region_masks(
    camera: Camera,
    truth: pd.DataFrame,
    frames: Sequence[int],
    scale: float = REGION_SCALE,
) -> dict[int, np.ndarray]:
    """``{frame: (H, W) bool}`` bubble regions of ``camera`` for each of ``frames`` that
    has at least one true bubble (``truth``: ``frame, x, y, z, r_eq``)."""
    rays = pixel_ray_grid(camera)
    out = {}
    for f in frames:
        rows = truth[truth["frame"] == int(f)]
        if len(rows):
            out[int(f)] = bubble_region(camera, rows, scale, rays)
    return out
