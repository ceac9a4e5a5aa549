"""Truncated signed distance fusion of rendered surfel depth, then marching cubes.

Each view's depth is the renderer's median depth (the hit depth of the surfel where the
transmittance crosses 0.5) where the pixel's alpha exceeds 0.5; other pixels are empty
space. A voxel centre X projected into a view gets the projective signed distance
``d = depth(u, v) − z_cam(X)`` (metres; positive in front of the surface, i.e. outside
the bubble), truncated to ``[−τ, τ]``; voxels more than ``τ`` behind the surface are
left out of that view's average, as in KinectFusion. A voxel that no view averages
(behind the surface, or unknown, in every view that sees it) is inside: it gets −τ.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from surfphase.cameras import Camera

if TYPE_CHECKING:  # torch is imported where the depths are rendered: the hull meshes need none
    import torch


def render_depths(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity: np.ndarray,
    cameras: Sequence[Camera],
    device: str | torch.device = "cpu",
    alpha_min: float = 0.5,
    silhouette_alpha: float = 0.05,
) -> np.ndarray:
    """Depth maps of N surfels seen by C cameras (undistorted pinhole).

    Args:
        means: (N, 3) centres, metres. quats: (N, 4) (w, x, y, z). log_scales: (N, 2)
            ln of the tangent standard deviations (metres). opacity: (N,) in [0, 1].
        cameras: C cameras of one size.
        alpha_min: pixels with accumulated alpha above this get the median depth.
        silhouette_alpha: the silhouette is the pixels with alpha above this, closed
            (3×3) and with its holes filled; silhouette pixels without a depth are
            unknown (fitted bubbles are often transparent in the middle, as their
            shadowgraph images are bright there), pixels outside it are empty.

    Returns:
        (C, H, W) float64 camera-z depth in metres; ``inf`` where the pixel is empty
        (free space), NaN where unknown.
    """
    import torch
    from scipy import ndimage

    from surfphase.render import camera_tensors, rasterize_surfels

    dev = torch.device(device)
    viewmats, Ks = camera_tensors(list(cameras), dev, torch.float32)
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=dev)  # noqa: E731
    n = len(means)
    with torch.no_grad():
        _, alpha, meta = rasterize_surfels(
            t(means),
            t(quats),
            torch.exp(t(log_scales)),
            t(opacity),
            torch.ones(n, 1, device=dev),
            viewmats,
            Ks,
            cameras[0].width,
            cameras[0].height,
        )
    depth = meta["depth_median"][..., 0].double().cpu().numpy()
    alpha = alpha[..., 0].cpu().numpy()
    ok = (alpha > alpha_min) & (depth > 0)
    out = np.where(ok, depth, np.inf)
    for c in range(len(out)):
        sil = ndimage.binary_closing(alpha[c] > silhouette_alpha, np.ones((3, 3), bool))
        sil = ndimage.binary_fill_holes(sil | ok[c])
        out[c][sil & ~ok[c]] = np.nan
    return out


def voxel_grid(
    points: np.ndarray, voxel: float, margin: float
) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Axis-aligned grid over the bounding box of (N, 3) points (metres) grown by
    ``margin`` (metres); returns the origin (3,) (centre of voxel [0, 0, 0], metres) and
    the shape (nx, ny, nz) for a voxel edge ``voxel`` (metres)."""
    if voxel <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    lo = points.min(0) - margin
    hi = points.max(0) + margin
    shape = tuple(int(s) for s in np.ceil((hi - lo) / voxel).astype(int) + 1)
    return lo.astype(np.float64), shape  # type: ignore[return-value]


def fuse_depths(
    depths: np.ndarray,
    cameras: Sequence[Camera],
    origin: np.ndarray,
    shape: tuple[int, int, int],
    voxel: float,
    trunc: float,
) -> np.ndarray:
    """Fuse C depth maps into a truncated signed distance volume.

    Args:
        depths: (C, H, W) camera-z depth, metres, ``inf`` where empty, NaN where
            unknown (left out of the average; see :func:`render_depths`).
        cameras: the C cameras the depths were rendered in.
        origin: (3,) centre of voxel [0, 0, 0], metres. shape: (nx, ny, nz).
        voxel: voxel edge, metres. trunc: truncation distance τ, metres.

    Returns:
        (nx, ny, nz) float32 signed distance in metres, in [−τ, τ]; positive outside.
    """
    axes = [origin[k] + voxel * np.arange(shape[k]) for k in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    acc = np.zeros(len(X))
    wsum = np.zeros(len(X))
    for depth, cam in zip(depths, cameras, strict=True):
        xc = X @ cam.R.T + cam.t
        z = xc[:, 2]
        front = z > 1e-9
        uv = np.full((len(X), 2), -1.0)
        uv[front] = xc[front, :2] / z[front, None] @ cam.K[:2, :2].T + cam.K[:2, 2]
        u = np.rint(uv[:, 0]).astype(np.int64)
        v = np.rint(uv[:, 1]).astype(np.int64)
        seen = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        d = np.full(len(X), -np.inf)
        d[seen] = depth[v[seen], u[seen]] - z[seen]
        use = seen & (d >= -trunc)
        acc[use] += np.minimum(d[use], trunc)
        wsum[use] += 1.0
    sdf = np.where(wsum > 0, acc / np.maximum(wsum, 1), -trunc)
    return sdf.reshape(shape).astype(np.float32)


def marching_cubes_mesh(
    sdf: np.ndarray, origin: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of a signed distance volume (positive outside).

    Returns (V, 3) float64 vertices in metres and (F, 3) int64 faces, wound so that the
    normals point outwards; empty arrays when the volume has no zero crossing.
    """
    from skimage.measure import marching_cubes

    if not (sdf.min() < 0 < sdf.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    # A voxel exactly on the level is outside: marching cubes meshes a plateau of exact
    # zeros (a silhouette's distance is 0 one grown pixel out) as sheets of spurious
    # surface, not as the boundary of the negative region.
    sdf = np.where(sdf == 0, np.asarray(1e-6 * voxel, sdf.dtype), sdf)
    verts, faces, _, _ = marching_cubes(
        sdf, level=0.0, spacing=(voxel, voxel, voxel), gradient_direction="descent"
    )
    return verts.astype(np.float64) + origin, faces.astype(np.int64)
