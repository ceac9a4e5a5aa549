"""Losses of the stage-1 fit (docs/method.md §5.2).

``λ_app · Σ_c (L1 + D-SSIM) + λ_geo · (L_normal + L_γ + L_proj)``. Images are
(C, H, W, D) tensors in [0, 1]; depths in metres.

The photometric term, the normal consistency and the projection loss take a ``backend``:
these PyTorch ops (``"torch"``, the reference, and the CUDA path) or the numba kernels of
:mod:`surfphase.fit.fused_losses` with hand-written gradients (``"fused"``, float64
inside, the same values to rounding); ``"auto"`` (default) takes the kernels on the CPU,
as :func:`surfphase.render.rasterize_surfels` takes its fused backend there.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from surfphase.fit.model import HALF_OPACITY_GF


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over all elements."""
    return (pred - target).abs().mean()


def _gaussian_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim_map(
    img1: torch.Tensor,
    img2: torch.Tensor,
    window: int = 11,
    sigma: float = 1.5,
    data_range: float = 1.0,
) -> torch.Tensor:
    """Per-pixel SSIM of two (C, H, W, D) images, Gaussian-weighted window.

    Population statistics, ``K1 = 0.01``, ``K2 = 0.03``, zero padding at the border
    (as 3DGS/2DGS do). Away from the border it equals scikit-image's
    ``structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False)``. Returns (C, H, W, D).
    """
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    C, H, W, D = img1.shape
    g = _gaussian_window(window, sigma, img1.dtype, img1.device)
    x = img1.permute(0, 3, 1, 2).reshape(C * D, 1, H, W)
    y = img2.permute(0, 3, 1, 2).reshape(C * D, 1, H, W)
    pad = window // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        # Separable Gaussian, zero padding, as 2 × ``window`` shifted multiply-adds: on
        # the CPU, F.conv2d with an 11×1 kernel and its backward were ~half of a fit
        # step; the sums are ~10× cheaper and add in a fixed order.
        t = F.pad(t, (pad, pad, pad, pad))
        rows = sum(g[k] * t[:, :, k : k + H, :] for k in range(window))
        return sum(g[k] * rows[:, :, :, k : k + W] for k in range(window))

    stacked = blur(torch.cat([x, y, x * x, y * y, x * y], dim=0))
    mu_x, mu_y, xx, yy, xy = stacked.split(C * D, dim=0)
    var_x = xx - mu_x**2
    var_y = yy - mu_y**2
    cov = xy - mu_x * mu_y
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / (
        (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    )
    return s.reshape(C, D, H, W).permute(0, 2, 3, 1)


def ssim(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (C, H, W, D) images in [0, 1]."""
    return ssim_map(img1, img2).mean()


def _backend(backend: str, name: str, fused_ok: bool) -> str:
    """``backend`` resolved: ``"auto"`` → ``"fused"`` where ``fused_ok`` (CPU tensors, no
    gradient the kernels do not compute), else ``"torch"``."""
    if backend == "auto":
        return "fused" if fused_ok else "torch"
    if backend not in ("fused", "torch"):
        raise ValueError(f"{name}: unknown backend {backend!r}; known: auto, fused, torch")
    return backend


def photometric_terms(
    rendered: torch.Tensor,
    observed: torch.Tensor,
    lambda_dssim: float = 0.2,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-view photometric terms of (C, H, W, D) images, for weighted sums over views.

    Returns ``(loss_v, l1_v, dssim_v)``, each (C,): ``(1−λ)·L1 + λ·(1 − SSIM)`` of every
    view, and its two parts (L1 the mean absolute error, D-SSIM ``1 −`` the mean SSIM of
    :func:`ssim_map`).

    ``backend``: ``"torch"`` (these PyTorch ops), ``"fused"`` (the numba kernels of
    :func:`surfphase.fit.fused_losses.photometric_fused`: the same values to rounding,
    float64 inside, gradient to ``rendered`` only) or ``"auto"`` (default: ``"fused"``
    on the CPU when ``observed`` needs no gradient, as the rasterizer picks its fused
    backend on the CPU; ``"torch"`` otherwise, e.g. on CUDA).
    """
    cpu = rendered.device.type == "cpu" and observed.device.type == "cpu"
    if _backend(backend, "photometric_terms", cpu and not observed.requires_grad) == "fused":
        from surfphase.fit.fused_losses import photometric_fused

        return photometric_fused(rendered, observed, lambda_dssim)
    l1_v = (rendered - observed).abs().flatten(1).mean(dim=1)
    dssim_v = 1.0 - ssim_map(rendered, observed).flatten(1).mean(dim=1)
    return (1 - lambda_dssim) * l1_v + lambda_dssim * dssim_v, l1_v, dssim_v


def normal_consistency(
    normals: torch.Tensor,
    normals_from_depth: torch.Tensor,
    alphas: torch.Tensor | None = None,
    backend: str = "auto",
) -> torch.Tensor:
    """2DGS's normal loss: mean over pixels of ``1 − n·ñ``.

    Args:
        normals: (C, H, W, 3) alpha-blended surfel normals (camera frame).
        normals_from_depth: (C, H, W, 3) normals of the rendered depth (camera frame);
            following 2DGS they are scaled by the pixel's alpha when ``alphas`` is given,
            so empty pixels contribute nothing.
        alphas: optional (C, H, W, 1) accumulated opacity (no gradient flows to it).
        backend: ``"torch"``, ``"fused"``
            (:func:`surfphase.fit.fused_losses.normal_consistency_fused`, the same value to
            rounding) or ``"auto"`` (``"fused"`` on the CPU, as :func:`photometric_terms`).
    """
    if _backend(backend, "normal_consistency", normals.device.type == "cpu") == "fused":
        from surfphase.fit.fused_losses import normal_consistency_fused

        return normal_consistency_fused(normals, normals_from_depth, alphas)
    nd = normals_from_depth
    if alphas is not None:
        nd = nd * alphas.detach()
    return (1.0 - (normals * nd).sum(dim=-1)).mean()


def gamma_target(sdf: torch.Tensor) -> torch.Tensor:
    """``γ_m = −ln(3−2√2) / median|f|`` (detached): the γ giving the median surfel o = 1/2."""
    med = sdf.detach().abs().median().clamp_min(1e-12)
    return HALF_OPACITY_GF / med


def gamma_hinge(gamma: torch.Tensor, sdf: torch.Tensor) -> torch.Tensor:
    """``L_γ = max(γ_m − γ, 0)``, with ``γ_m`` from :func:`gamma_target` (a fixed target).

    Both ``γ`` and ``f`` are in the model's extent units, so the loss is dimensionless
    up to that scale; divide by ``γ_m`` when weighting so it stays O(1).
    """
    return torch.relu(gamma_target(sdf) - gamma)


def projection_loss(
    points: torch.Tensor,
    depth: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    extent: float,
    threshold: float = 0.1,
    backend: str = "auto",
) -> torch.Tensor:
    """Depth of each surfel's zero-level point against the rendered depth (detached).

    Every point ``p_i = μ_i − f_i n_i`` (metres) is projected into every view; where it
    lands inside the image, its camera depth ``z_i`` is compared with the rendered
    expected depth ``D(u_i)`` (bilinear, detached). The error is measured in units of
    the scene extent, ``e = |z_i − D(u_i)| / L``; errors above ``threshold`` (in those
    units, i.e. ``threshold·L`` metres) are ignored, as are pixels with no depth.

    Args:
        points: (N, 3) zero-level points, metres.
        depth: (C, H, W, 1) rendered expected depth, metres (0 where nothing rendered).
        viewmats: (C, 4, 4) world-to-camera matrices.
        Ks: (C, 3, 3) intrinsics, pixels.
        extent: scene extent ``L``, metres.
        threshold: largest error kept, in units of ``L``.
        backend: ``"torch"``, ``"fused"``
            (:func:`surfphase.fit.fused_losses.projection_loss_fused`, the same value to
            rounding, no gradient to the cameras) or ``"auto"`` (``"fused"`` on the CPU
            when the cameras need no gradient).

    Returns:
        Scalar mean error (extent units) over kept (point, view) pairs; 0 if none.
    """
    cpu = points.device.type == "cpu" and not (viewmats.requires_grad or Ks.requires_grad)
    if _backend(backend, "projection_loss", cpu) == "fused":
        from surfphase.fit.fused_losses import projection_loss_fused

        return projection_loss_fused(points, depth, viewmats, Ks, extent, threshold)
    C, H, W, _ = depth.shape
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    pc = torch.einsum("cij,nj->cni", R, points) + t[:, None, :]  # (C, N, 3)
    z = pc[..., 2]
    zs = z.clamp_min(1e-9)
    u = Ks[:, None, 0, 0] * pc[..., 0] / zs + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * pc[..., 1] / zs + Ks[:, None, 1, 2]
    # Pixel centres at integers → normalised coordinates for align_corners=True.
    grid = torch.stack([2 * u / max(W - 1, 1) - 1, 2 * v / max(H - 1, 1) - 1], dim=-1)
    d = F.grid_sample(
        depth.detach().permute(0, 3, 1, 2),
        grid.detach()[:, :, None, :],
        mode="bilinear",
        align_corners=True,
        padding_mode="zeros",
    )[:, 0, :, 0]  # (C, N)
    inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1) & (z > 0)
    err = (z - d).abs() / extent
    keep = inside & (d > 0) & (err.detach() <= threshold)
    if not bool(keep.any()):
        return points.sum() * 0.0
    return err[keep].mean()


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1]."""
    mse = float(((pred.detach().clamp(0, 1) - target) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))
