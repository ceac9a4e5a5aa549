"""Brute-force reference renderer: every pixel against every surfel.

Obviously-right and slow, for tests and benchmarks only. It shares no geometry code with
the sparse backend: each ray is intersected with each surfel's plane in world space
(ray–plane intersection), not through the homography the fast path uses; it keeps no
bounding boxes; and it blends surfel after surfel, in depth order, over the whole image,
with the same culling, 1/255 skip, 0.99 cap and 1e-4 termination rules.

:func:`rasterize_surfels_reference` is one function of about 100 lines on purpose: the
reference the fast backends are tested against is read top to bottom as one loop, with
every rule next to the others.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from surfphase.render.projection import DEFAULT_LOW_PASS


def _rotation(q: Tensor) -> Tensor:
    """(4,) quaternion (w, x, y, z) → (3, 3) rotation, written out independently."""
    w, x, y, z = (q / torch.sqrt((q * q).sum())).unbind()
    return torch.stack(
        [
            torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)]),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]),
        ]
    )


def rasterize_surfels_reference(
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
) -> dict[str, Tensor]:
    """Dense reference of :func:`surfphase.render.rasterize_surfels` (same arguments).

    Returns a dict with ``colors`` (C, H, W, D), ``alphas``, ``depth_expected``,
    ``depth_median``, ``distortion`` (C, H, W, 1), ``normals_camera``,
    ``normals_world``, ``normals_from_depth`` (C, H, W, 3).
    """
    C, N, D = viewmats.shape[0], means.shape[0], colors.shape[-1]
    if colors.dim() == 2:
        colors = colors[None].expand(C, N, D)
    dt, dev = means.dtype, means.device
    H, W = height, width
    out = {
        k: torch.zeros(C, H, W, n, dtype=dt, device=dev)
        for k, n in [
            ("colors", D),
            ("alphas", 1),
            ("depth_accum", 1),
            ("depth_median", 1),
            ("distortion", 1),
            ("normals_camera", 3),
        ]
    }
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=dt, device=dev), torch.arange(W, dtype=dt, device=dev), indexing="ij"
    )
    for c in range(C):
        Rc, tc, K = viewmats[c, :3, :3], viewmats[c, :3, 3], Ks[c]
        origin = -Rc.T @ tc
        # Camera-frame ray with unit z, so the ray parameter is the camera depth.
        d_cam = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ torch.linalg.inv(K).T
        d_world = d_cam @ Rc  # Rcᵀ applied to row vectors
        centre_z = means @ Rc[2] + tc[2]
        order = sorted(range(N), key=lambda i: (float(centre_z[i]), i))
        T = torch.ones(H, W, dtype=dt, device=dev)
        done = torch.zeros(H, W, dtype=torch.bool, device=dev)
        acc_w = torch.zeros(H, W, dtype=dt, device=dev)
        acc_m = torch.zeros_like(acc_w)
        acc_m2 = torch.zeros_like(acc_w)
        for i in order:
            zc = centre_z[i]
            if not near <= float(zc) <= far:
                continue
            rot = _rotation(quats[i])
            tu, tv, n = rot[:, 0], rot[:, 1], rot[:, 2]
            p = means[i]
            denom = d_world @ n
            hit = denom != 0
            tray = torch.where(hit, ((p - origin) @ n) / torch.where(hit, denom, 1.0), 0.0)
            X = origin + tray[..., None] * d_world
            u = ((X - p) @ tu) / scales[i, 0]
            v = ((X - p) @ tv) / scales[i, 1]
            rho3 = u * u + v * v
            pc = Rc @ p + tc
            uv = K @ pc
            mx, my = uv[0] / uv[2], uv[1] / uv[2]
            if low_pass > 0:
                rho2 = ((xs - mx) ** 2 + (ys - my) ** 2) / low_pass**2
            else:
                rho2 = torch.full_like(rho3, float("inf"))
            use3 = rho3 <= rho2
            rho = torch.where(use3, rho3, rho2)
            depth = torch.where(use3, tray, zc.expand_as(tray))
            alpha = torch.clamp(opacities[i] * torch.exp(-0.5 * rho), max=0.99)
            ok = hit & (rho <= 9.0) & (depth >= near) & (alpha >= 1.0 / 255.0) & ~done
            after = T * (1 - alpha)
            stop = ok & (after < 1e-4)
            done = done | stop
            ok = ok & ~stop
            w = torch.where(ok, alpha * T, 0.0)
            m = far / (far - near) * (1 - near / depth)
            dist = (m * m * acc_w + acc_m2 - 2 * m * acc_m) * w
            n_cam = Rc @ n
            if float(n_cam @ pc) > 0:
                n_cam = -n_cam
            median_now = ok & (T > 0.5)
            o = out
            o["colors"][c] += w[..., None] * colors[c, i]
            o["alphas"][c, ..., 0] += w
            o["depth_accum"][c, ..., 0] += w * depth
            o["distortion"][c, ..., 0] += dist
            o["normals_camera"][c] += w[..., None] * n_cam
            o["depth_median"][c, ..., 0] = torch.where(
                median_now, depth, o["depth_median"][c, ..., 0]
            )
            acc_w = acc_w + w
            acc_m = acc_m + w * m
            acc_m2 = acc_m2 + w * m * m
            T = torch.where(ok, after, T)
        if backgrounds is not None:
            bg = backgrounds if backgrounds.dim() == 1 else backgrounds[c]
            out["colors"][c] += (1 - out["alphas"][c]) * bg
    a = out["alphas"]
    out["depth_expected"] = torch.where(a > 0, out["depth_accum"] / torch.where(a > 0, a, 1), 0)
    out["normals_world"] = torch.einsum(
        "chwi,cij->chwj", out["normals_camera"], viewmats[:, :3, :3]
    )
    out["normals_from_depth"] = _normals_from_depth(out["depth_expected"], Ks)
    return out


def _normals_from_depth(depth: Tensor, Ks: Tensor) -> Tensor:
    """Per-pixel loop version of the depth-normal rule (camera frame, facing the camera)."""
    C, H, W, _ = depth.shape
    d = depth.detach().cpu().numpy()
    out = np.zeros((C, H, W, 3), dtype=d.dtype)
    for c in range(C):
        Kinv = np.linalg.inv(Ks[c].detach().cpu().numpy().astype(d.dtype))

        def point(y: int, x: int, c: int = c, Kinv: np.ndarray = Kinv) -> np.ndarray:
            return d[c, y, x, 0] * (Kinv @ np.array([x, y, 1.0], dtype=d.dtype))

        for y in range(1, H - 1):
            for x in range(1, W - 1):
                down = point(y + 1, x) - point(y - 1, x)
                right = point(y, x + 1) - point(y, x - 1)
                n = np.cross(down, right)
                norm = np.linalg.norm(n)
                if norm > 0:
                    out[c, y, x] = n / norm
    return torch.from_numpy(out).to(depth.device)
