"""Differentiable rasterization of 2D Gaussian surfels: the public entry point.

Semantics follow 2D Gaussian Splatting (Huang et al. 2024):

* each pixel's ray meets the surfel's plane at ``(u, v)`` (standard deviations in its
  tangent frame), ``ρ3d = u² + v²``; a screen-space low-pass term
  ``ρ2d = |x − μ2d|² / low_pass²`` keeps sub-pixel surfels visible; ``ρ = min(ρ3d, ρ2d)``
  and the hit depth is the camera z of the ray–plane hit (3D term) or of the centre
  (2D term);
* a pixel is in a surfel's support when ``ρ ≤ 9`` (3σ), the hit is at depth ≥ ``near``
  and the centre's depth lies in ``[near, far]``;
* ``α = min(0.99, o·exp(−ρ/2))``, pairs with ``α < 1/255`` are skipped; surfels are
  blended front to back in order of their centres' depth; a pixel stops as soon as a
  surfel would bring its transmittance under ``1e-4`` (that surfel is not blended).

Pixels follow docs/conventions.md §4: pixel ``(u, v)`` has its centre at integer coordinates.
Differences from 2DGS's CUDA rasterizer, on purpose: its footprint cut-off depends on
16×16 tiles, here the support is exactly ``ρ ≤ 9`` so results do not depend on tiling;
the low-pass term is centred on the projected surfel centre (2DGS: the centre of the
projected 3σ ellipse's box, which differs slightly under perspective).

Backends: ``backend`` names an entry of :data:`BACKENDS` (``"auto"``: the fused numba
backend on the CPU, the sparse PyTorch one on CUDA or when ``viewmats`` / ``Ks`` require
grad). The sparse backend returns raw accumulations (per-pixel sums and per-surfel
buffers) that :func:`finish_outputs` turns into the public outputs; the fused backend
(:func:`surfphase.render.fused.rasterize_fused`) does all of it, projection and output
finishing included, in numba kernels with hand-written gradients.
"""

from __future__ import annotations

import importlib

import torch
from torch import Tensor

from surfphase.cameras import Camera
from surfphase.render.composite import over_background
from surfphase.render.projection import DEFAULT_LOW_PASS

#: Backend name → ``"module:function"`` (imported on first use).
BACKENDS = {
    "torch": "surfphase.render.sparse:rasterize_sparse",
    "sparse": "surfphase.render.sparse:rasterize_sparse",
    "fused": "surfphase.render.fused:rasterize_fused",
}
# The fused backend returns the public outputs itself (its output finishing is fused
# too); the others return raw accumulations for :func:`finish_outputs`.


def rasterize_surfels(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near: float = 1e-3,
    far: float = 1e3,
    backgrounds: Tensor | None = None,
    low_pass: float = DEFAULT_LOW_PASS,
    max_pairs_per_chunk: int = 4_000_000,
    backend: str = "auto",
) -> tuple[Tensor, Tensor, dict]:
    """Render N surfels into C cameras (differentiable).

    Args:
        means: (N, 3) world positions, metres.
        quats: (N, 4) rotations ``(w, x, y, z)``, need not be normalised.
        scales: (N, 2) tangent-plane standard deviations, metres (not log).
        opacities: (N,) in [0, 1].
        colors: (N, D) any number of channels, the same in every camera, or (C, N, D)
            per camera (view-dependent colour, :mod:`surfphase.render.shading`).
        viewmats: (C, 4, 4) world-to-camera ``[R t; 0 1]``.
        Ks: (C, 3, 3) OpenCV intrinsics, pixels (images undistorted).
        width, height: image size, pixels.
        near, far: depth range, metres (camera z). ``far`` also sets the NDC mapping of
            the distortion term, as in 2DGS.
        backgrounds: (C, D) or (D,) colour behind the surfels; ``None`` = black.
        low_pass: screen-space filter standard deviation, pixels (2DGS: 0.707); 0 disables.
        max_pairs_per_chunk: memory bound: images are processed in bands of rows holding
            at most this many candidate (pixel, surfel) pairs (at least one row per band);
            with several bands each is recomputed in the backward pass (checkpointing).
            In float32 a band's peak is roughly 250 (CUDA) to 400 (CPU) bytes per pair.
        backend: ``"auto"`` (default: ``"fused"`` on the CPU, ``"torch"`` on CUDA or
            when ``viewmats`` or ``Ks`` require grad), ``"fused"``
            (:mod:`surfphase.render.fused`, numba kernels, CPU only, about 3× faster than
            sparse on 2 cores; no gradients to the cameras; ``max_pairs_per_chunk``
            unused) or ``"torch"`` (alias ``"sparse"``; :mod:`surfphase.render.sparse`,
            pure PyTorch, CPU or CUDA; the second implementation the tests compare
            against). Both give the same outputs and gradients up to rounding.

    Returns:
        ``render_colors`` (C, H, W, D): Σ w·colour + (1 − alpha)·background;
        ``render_alphas`` (C, H, W, 1): Σ w, with ``w = α·T`` the blending weights;
        ``meta`` dict:

        * ``depth_expected`` (C, H, W, 1): Σ w·z / alpha (camera z, metres), **normalised
          by alpha** (0 where alpha = 0), as 2DGS's ``render_depth_expected / alpha``;
        * ``depth_accum`` (C, H, W, 1): the unnormalised Σ w·z;
        * ``depth_median`` (C, H, W, 1): hit depth of the last blended surfel whose
          incoming transmittance is above 0.5 (0 where none);
        * ``normals_camera`` (C, H, W, 3): Σ w·n, camera frame, each surfel's unit normal
          flipped to face the camera (not renormalised);
        * ``normals_world`` (C, H, W, 3): the same in the world frame;
        * ``normals_from_depth`` (C, H, W, 3): **camera frame**, unit normals of the
          surface through the back-projected ``depth_expected`` points, from central
          differences, oriented towards the camera; zero on the one-pixel border; where
          alpha is 0 the point collapses onto the camera centre, so, as in 2DGS, weight
          these normals by alpha (or mask them) near silhouettes;
        * ``normals_from_depth_world`` (C, H, W, 3): the same in the world frame;
        * ``distortion`` (C, H, W, 1): 2DGS depth distortion
          Σ_i Σ_{j<i} w_i w_j (m_i − m_j)², with ``m = far/(far−near)·(1 − near/z)``;
        * ``radii`` (C, N) int32: half size in pixels of each surfel's screen box
          (0 when culled); ``visible`` (C, N) bool;
        * ``means2d`` (C, N, 2): projected centres, pixels; a non-leaf tensor of the graph
          on which ``retain_grad()`` is called when inputs require grad, so after
          ``backward()`` ``meta["means2d"].grad`` is the screen-space position gradient
          (at fixed depth and tangent axes) that densification uses;
        * ``n_pairs`` (int): candidate (pixel, surfel) pairs the backend processed.
    """
    C, N = _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height)
    if not 0 < near < far:
        raise ValueError(f"rasterize_surfels: need 0 < near < far, got near={near}, far={far}")
    if low_pass < 0:
        raise ValueError(f"rasterize_surfels: low_pass must be ≥ 0, got {low_pass}")
    if max_pairs_per_chunk < 1:
        raise ValueError("rasterize_surfels: max_pairs_per_chunk must be ≥ 1")
    if backend == "auto":
        cpu = means.device.type == "cpu"
        backend = "fused" if cpu and not (viewmats.requires_grad or Ks.requires_grad) else "torch"
    if backend not in BACKENDS:
        raise ValueError(
            f"rasterize_surfels: unknown backend {backend!r}; known: {', '.join(BACKENDS)}"
        )
    if backend == "fused":
        from surfphase.render.fused import rasterize_fused

        return rasterize_fused(
            means, quats, scales, opacities, colors, viewmats, Ks, int(width), int(height),
            float(near), float(far), float(low_pass), backgrounds,
        )  # fmt: skip
    module, func = BACKENDS[backend].split(":")
    backend_fn = getattr(importlib.import_module(module), func)
    out = backend_fn(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        int(width),
        int(height),
        float(near),
        float(far),
        float(low_pass),
        int(max_pairs_per_chunk),
    )
    cols, alphas, meta = finish_outputs(
        out["accum"],
        out["depth_median"],
        viewmats,
        Ks,
        colors.shape[-1],
        backgrounds,
        out["means2d"],
        out["radii"],
        out["visible"],
    )
    meta["n_pairs"] = out["n_pairs"]
    return cols, alphas, meta


def finish_outputs(
    accum: Tensor,
    depth_median: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    n_channels: int,
    backgrounds: Tensor | None,
    means2d: Tensor,
    radii: Tensor,
    visible: Tensor,
) -> tuple[Tensor, Tensor, dict]:
    """Turn a backend's raw accumulations (C, H, W, D + 6) into the public outputs."""
    D = n_channels
    # One split (its backward is one concatenation), not five slices (each of whose
    # backwards writes a full-size zero tensor).
    colors, alphas, depth_accum, normals_cam, distortion = accum.split([D, 1, 1, 3, 1], dim=-1)
    if backgrounds is not None:
        bg = backgrounds.to(colors)
        bg = bg.expand(accum.shape[0], D) if bg.dim() == 1 else bg
        colors = over_background(colors, alphas, bg[:, None, None, :])
    has = alphas > 0
    depth_expected = torch.where(has, depth_accum / torch.where(has, alphas, 1), 0)
    R = viewmats[:, :3, :3]
    normals_world = _rotate_rows(normals_cam, R)
    from_depth = depth_normals(depth_expected, Ks)
    meta = {
        "depth_expected": depth_expected,
        "depth_accum": depth_accum,
        "depth_median": depth_median,
        "normals_camera": normals_cam,
        "normals_world": normals_world,
        "normals_from_depth": from_depth,
        "normals_from_depth_world": _rotate_rows(from_depth, R),
        "distortion": distortion,
        "radii": radii,
        "visible": visible,
        "means2d": means2d,
    }
    if means2d.requires_grad:
        means2d.retain_grad()
    return colors, alphas, meta


def depth_normals(depth: Tensor, Ks: Tensor) -> Tensor:
    """Camera-frame unit normals (C, H, W, 3) from a depth map (C, H, W, 1), metres.

    Back-projects pixel ``(x, y)`` to ``z·K⁻¹(x, y, 1)``, takes central differences along
    rows and columns, and returns ``normalize(∂P/∂y × ∂P/∂x)`` (facing the camera for a
    visible surface). The one-pixel border is zero. On the CPU (when ``Ks`` needs no
    gradient) this runs as numba kernels (:func:`surfphase.render.fused.depth_normals_fused`).
    """
    C, H, W, _ = depth.shape
    dev, dt = depth.device, depth.dtype
    ys, xs = torch.meshgrid(
        torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij"
    )
    Kinv = torch.linalg.inv(Ks.to(dt))  # (C, 3, 3)
    # rays[c, h, w, i] = Σ_j Kinv[c, i, j]·(x, y, 1)_j, written out (a 3-term sum is much
    # cheaper than a batched matmul with k = 3 on the CPU).
    k = Kinv[:, None, None, :, :]
    rays = k[..., 0] * xs[None, :, :, None] + k[..., 1] * ys[None, :, :, None] + k[..., 2]
    if depth.device.type == "cpu" and not Ks.requires_grad:
        from surfphase.render.fused import depth_normals_fused

        return depth_normals_fused(depth, rays)
    pts = rays * depth
    if H < 3 or W < 3:
        return torch.zeros_like(pts)
    dy = (pts[:, 2:, 1:-1] - pts[:, :-2, 1:-1]).unbind(-1)
    dx = (pts[:, 1:-1, 2:] - pts[:, 1:-1, :-2]).unbind(-1)
    n = torch.stack(
        [
            dy[1] * dx[2] - dy[2] * dx[1],
            dy[2] * dx[0] - dy[0] * dx[2],
            dy[0] * dx[1] - dy[1] * dx[0],
        ],
        dim=-1,
    )
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(dt).tiny ** 0.5)
    return torch.nn.functional.pad(n, (0, 0, 1, 1, 1, 1))


def _rotate_rows(v: Tensor, R: Tensor) -> Tensor:
    """``v @ R`` per camera: (C, H, W, 3) row vectors times (C, 3, 3), as 3-term sums."""
    r = R[:, None, None, :, :]
    return v[..., 0:1] * r[..., 0, :] + v[..., 1:2] * r[..., 1, :] + v[..., 2:3] * r[..., 2, :]


def camera_tensors(
    cameras: list[Camera], device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[Tensor, Tensor]:
    """Stack cameras into ``viewmats`` (C, 4, 4) world-to-camera and ``Ks`` (C, 3, 3).

    Lens distortion is ignored: render into undistorted images
    (``Camera.undistorted()``).
    """
    if not cameras:
        raise ValueError("camera_tensors: no cameras given")
    view = torch.zeros(len(cameras), 4, 4, dtype=torch.float64)
    K = torch.zeros(len(cameras), 3, 3, dtype=torch.float64)
    for i, cam in enumerate(cameras):
        view[i, :3, :3] = torch.as_tensor(cam.R, dtype=torch.float64)
        view[i, :3, 3] = torch.as_tensor(cam.t, dtype=torch.float64)
        view[i, 3, 3] = 1.0
        K[i] = torch.as_tensor(cam.K, dtype=torch.float64)
    return view.to(device=device, dtype=dtype), K.to(device=device, dtype=dtype)


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height):
    N = means.shape[0] if means.dim() == 2 else -1
    checks = [
        (means.dim() == 2 and means.shape[1] == 3, "means must be (N, 3)"),
        (quats.shape == (N, 4), "quats must be (N, 4)"),
        (scales.shape == (N, 2), "scales must be (N, 2)"),
        (opacities.shape == (N,), "opacities must be (N,)"),
        (
            (colors.dim() == 2 and colors.shape[0] == N)
            or (colors.dim() == 3 and colors.shape[:2] == (viewmats.shape[0], N)),
            "colors must be (N, D) or (C, N, D)",
        ),
        (viewmats.dim() == 3 and viewmats.shape[1:] == (4, 4), "viewmats must be (C, 4, 4)"),
        (Ks.dim() == 3 and Ks.shape[1:] == (3, 3), "Ks must be (C, 3, 3)"),
        (Ks.shape[0] == viewmats.shape[0], "Ks and viewmats need the same C"),
        (int(width) > 0 and int(height) > 0, "width and height must be positive"),
    ]
    for ok, msg in checks:
        if not ok:
            raise ValueError(f"rasterize_surfels: {msg}")
    return viewmats.shape[0], N
