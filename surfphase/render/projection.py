"""Per-surfel projection shared by the rasterizer backends.

A 2D Gaussian surfel (2DGS) is a flat disk: centre ``p`` (world, metres), tangent axes
``t_u``, ``t_v`` and normal ``n`` (the columns of its rotation), standard deviations
``s_u``, ``s_v`` (metres). The point ``p + u·s_u·t_u + v·s_v·t_v`` of its plane, in
units of standard deviations ``(u, v)``, maps to homogeneous pixels by the 3×3 matrix

    M = K · [W s_u t_u,  W s_v t_v,  W p + t]            (columns)

where ``[W | t]`` is the world-to-camera transform. The ray through pixel ``(x, y)``
meets the plane at ``(u, v, 1) ∝ adj(M) · (x, y, 1)``; if ``q = adj(M)·(x, y, 1)``
then ``u = q0/q2``, ``v = q1/q2`` and the camera depth of the hit is ``det(M)/q2``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: Footprint cut-off in standard deviations: a pixel is inside a surfel's support when
#: ``min(ρ3d, ρ2d) ≤ CUTOFF²`` (ρ are squared Mahalanobis distances).
CUTOFF = 3.0
#: 2DGS blending constants.
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
#: 2DGS's screen-space filter: σ = 0.707 px, i.e. ρ2d = 2·|Δ|².
DEFAULT_LOW_PASS = math.sqrt(0.5)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(N, 4) quaternions ``(w, x, y, z)``, any norm → (N, 3, 3) rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def project_surfels(
    means: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor
) -> dict[str, Tensor]:
    """Project N surfels into C cameras.

    Args:
        means: (N, 3) world centres, metres.
        quats: (N, 4) rotations ``(w, x, y, z)``.
        scales: (N, 2) tangent standard deviations, metres.
        viewmats: (C, 4, 4) world-to-camera.
        Ks: (C, 3, 3) intrinsics, pixels.

    Returns a dict of per-(camera, surfel) tensors:
        ``means2d`` (C, N, 2) projected centres, pixels;
        ``depth`` (C, N) camera z of the centre, metres;
        ``M`` (C, N, 3, 3) surfel-plane-to-pixel homography (columns as above);
        ``J`` (C, N, 3, 3) its adjugate, ``det`` (C, N) its determinant;
        ``normals_camera`` (C, N, 3) unit normals in the camera frame, flipped to face it;
        ``flip`` (C, N) the ±1 applied to the world normal to face camera c.
    """
    rot = quat_to_rotmat(quats)  # (N, 3, 3), columns t_u, t_v, n
    R = viewmats[:, :3, :3]  # (C, 3, 3)
    t = viewmats[:, :3, 3]  # (C, 3)
    p_cam = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # (C, N, 3)
    axes = rot * torch.cat([scales, torch.ones_like(scales[:, :1])], dim=1)[:, None, :]
    axes_cam = torch.einsum("cij,njk->cnik", R, axes)  # (C, N, 3, 3): W s_u t_u, W s_v t_v, W n
    tang_pix = torch.einsum("cij,cnjk->cnik", Ks, axes_cam[..., :2])  # (C, N, 3, 2)
    z = p_cam[..., 2]
    proj = torch.einsum("cij,cnj->cni", Ks, p_cam)
    means2d = proj[..., :2] / z[..., None]
    # The centre column is written through means2d so that its gradient is the
    # screen-space position gradient that densification reads.
    centre = torch.cat([means2d * z[..., None], z[..., None]], dim=-1)  # (C, N, 3)
    c0, c1 = tang_pix[..., 0], tang_pix[..., 1]
    M = torch.stack([c0, c1, centre], dim=-1)
    J = torch.stack([_cross(c1, centre), _cross(centre, c0), _cross(c0, c1)], dim=-2)
    det = (c0 * J[..., 0, :]).sum(-1)
    n_cam = axes_cam[..., 2]
    flip = torch.where((n_cam * p_cam).sum(-1) > 0, -1.0, 1.0).to(n_cam.dtype).detach()
    return {
        "means2d": means2d,
        "depth": z,
        "M": M,
        "J": J,
        "det": det,
        "normals_camera": n_cam * flip[..., None],
        "flip": flip,
    }


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """``a × b`` over the last axis, written out (faster than ``linalg.cross`` on the CPU)."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


@torch.no_grad()
def bounding_boxes(
    M: Tensor, means2d: Tensor, low_pass: float, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Integer pixel boxes that hold every pixel of each surfel's support.

    The support is ``ρ3d ≤ 9`` (the image of the 3σ disk, a conic whose bounding box
    follows from its dual, ``D = M diag(9, 9, −1) Mᵀ``) united with ``ρ2d ≤ 9`` (a disk of
    ``3·low_pass`` px about the projected centre). When the 3σ disk reaches the camera
    plane its image is unbounded and the whole image is used.

    Returns ``box`` (C, N, 4) int64 ``(x0, y0, x1, y1)`` inclusive, clipped to the image,
    and ``half`` (C, N, 2) the unclipped half extents in pixels.
    """
    k2 = CUTOFF * CUTOFF
    c0, c1, c2 = M[..., 0], M[..., 1], M[..., 2]
    D = k2 * (c0[..., :, None] * c0[..., None, :] + c1[..., :, None] * c1[..., None, :])
    D = D - c2[..., :, None] * c2[..., None, :]
    d22 = D[..., 2, 2]
    bounded = d22 < 0
    safe = torch.where(bounded, d22, -torch.ones_like(d22))
    cx = D[..., 0, 2] / safe
    cy = D[..., 1, 2] / safe
    hx = (cx * cx - D[..., 0, 0] / safe).clamp_min(0).sqrt()
    hy = (cy * cy - D[..., 1, 1] / safe).clamp_min(0).sqrt()
    r2d = CUTOFF * low_pass
    lo_x = torch.minimum(cx - hx, means2d[..., 0] - r2d)
    hi_x = torch.maximum(cx + hx, means2d[..., 0] + r2d)
    lo_y = torch.minimum(cy - hy, means2d[..., 1] - r2d)
    hi_y = torch.maximum(cy + hy, means2d[..., 1] + r2d)
    big = float(4 * max(width, height))
    lo_x = torch.where(bounded, lo_x, -big).nan_to_num(-big, -big, -big)
    lo_y = torch.where(bounded, lo_y, -big).nan_to_num(-big, -big, -big)
    hi_x = torch.where(bounded, hi_x, big).nan_to_num(big, big, big)
    hi_y = torch.where(bounded, hi_y, big).nan_to_num(big, big, big)
    box = torch.stack(
        [
            lo_x.clamp(-big, big).floor(),
            lo_y.clamp(-big, big).floor(),
            hi_x.clamp(-big, big).ceil(),
            hi_y.clamp(-big, big).ceil(),
        ],
        dim=-1,
    ).long()
    half = torch.stack([(hi_x - lo_x) / 2, (hi_y - lo_y) / 2], dim=-1)
    box[..., 0].clamp_(min=0)
    box[..., 1].clamp_(min=0)
    box[..., 2].clamp_(max=width - 1)
    box[..., 3].clamp_(max=height - 1)
    return box, half
