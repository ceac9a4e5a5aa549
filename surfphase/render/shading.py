"""View-dependent surfel colour for backlit bubbles: a shading curve of the facing angle.

In a backlit shadowgraph a bubble's brightness at a point depends on where the ray meets
the interface: rays that cross it nearly head-on pass through towards the lens (a bright
core), oblique ones are refracted out of the aperture (a dark rim). The same interface
point is core in one camera and rim in another 35° away, so a colour fixed per surfel
cannot reproduce both views, nor a view between them.

The model here: surfel ``i`` seen from camera ``c`` has colour

    c_ic = colour_i + g(|n_i · d_ic|)

where ``n_i`` is the surfel's unit normal, ``d_ic`` the unit direction from the camera
centre to the surfel centre, and ``g`` one curve per fit (not per surfel): ``K`` values
per channel at ``|n·d| = 0, 1/(K−1), …, 1``, linearly interpolated. ``g`` is learned with
the surfels; a curve of zeros is the view-independent model.
"""

from __future__ import annotations

import torch
from torch import Tensor

from surfphase.render.projection import quat_to_rotmat


def camera_centres(viewmats: Tensor) -> Tensor:
    """(C, 4, 4) world-to-camera ``[R t; 0 1]`` → (C, 3) camera centres ``−Rᵀt`` (world)."""
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    return -torch.einsum("cji,cj->ci", R, t)


def facing_cosines(means: Tensor, quats: Tensor, viewmats: Tensor) -> Tensor:
    """``|n_i · d_ic|`` for N surfels and C cameras.

    Args:
        means: (N, 3) surfel centres, metres (world).
        quats: (N, 4) rotations ``(w, x, y, z)``, any norm; the normal is the third column.
        viewmats: (C, 4, 4) world-to-camera transforms.

    Returns:
        (C, N) in [0, 1]: 1 where the surfel faces the camera, 0 seen edge-on.
    """
    n = quat_to_rotmat(quats)[..., :, 2]  # (N, 3)
    d = means[None] - camera_centres(viewmats)[:, None]  # (C, N, 3)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.einsum("cnk,nk->cn", d, n).abs().clamp(0.0, 1.0)


def shading_curve(cos: Tensor, knots: Tensor) -> Tensor:
    """Piecewise-linear ``g(cos)``.

    Args:
        cos: (...) values in [0, 1].
        knots: (K, D) values of ``g`` at ``cos = k/(K−1)``, K ≥ 2.

    Returns:
        (..., D) interpolated values.
    """
    K = knots.shape[0]
    if K < 2:
        raise ValueError(f"shading_curve: need at least 2 knots, got {K}")
    x = cos.clamp(0.0, 1.0) * (K - 1)
    i0 = x.detach().floor().clamp(max=K - 2).long()
    w = (x - i0.to(x.dtype))[..., None]
    # index_select (backward index_add_, a fixed order), not knots[i0]: see fit/register.
    flat = i0.reshape(-1)
    lo = knots.index_select(0, flat).reshape(*i0.shape, knots.shape[1])
    hi = knots.index_select(0, flat + 1).reshape(*i0.shape, knots.shape[1])
    return lo * (1.0 - w) + hi * w


def monotone_knots(raw: Tensor) -> Tensor:
    """(K, D) knot values that never decrease with ``|n·d|``: ``raw[0]`` plus the
    running sum of ``softplus(raw[1:])`` (a backlit interface is darkest seen edge-on
    and brightest seen head-on)."""
    steps = torch.nn.functional.softplus(raw[1:])
    return torch.cat([raw[:1], raw[:1] + torch.cumsum(steps, dim=0)], dim=0)


def monotone_raw(knots: Tensor, min_step: float = 1e-4) -> Tensor:
    """Inverse of :func:`monotone_knots` (steps below ``min_step`` are raised to it)."""
    steps = (knots[1:] - knots[:-1]).clamp_min(min_step)
    return torch.cat([knots[:1], torch.log(torch.expm1(steps))], dim=0)


def view_colors(
    colors: Tensor, means: Tensor, quats: Tensor, knots: Tensor | None, viewmats: Tensor
) -> Tensor:
    """Per-camera surfel colours ``colour_i + g(|n_i · d_ic|)``.

    Args:
        colors: (N, D) view-independent colours.
        means, quats: (N, 3) centres (metres) and (N, 4) rotations.
        knots: (K, D) shading curve (:func:`shading_curve`), or None for none.
        viewmats: (C, 4, 4) world-to-camera transforms.

    Returns:
        (C, N, D) colours (not clamped); with ``knots`` None, ``colors`` as (1, N, D)
        expanded to C cameras.
    """
    C = viewmats.shape[0]
    if knots is None:
        return colors[None].expand(C, *colors.shape)
    return colors[None] + shading_curve(facing_cosines(means, quats, viewmats), knots)
