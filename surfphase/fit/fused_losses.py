"""Fused CPU forms of the fit's losses (numba, hand-written backward passes): the
photometric term (:func:`photometric_fused`), the normal consistency
(:func:`normal_consistency_fused`) and the projection loss (:func:`projection_loss_fused`),
which :mod:`surfphase.fit.losses` takes on the CPU (``backend="auto"``).

The photometric term, per view of two (K, H, W, D) images: ``L1`` (the mean of ``|x − y|``), ``D-SSIM`` (``1 −``
the mean of :func:`surfphase.fit.losses.ssim_map`: an 11-tap Gaussian window, σ = 1.5,
zero padding, ``K1 = 0.01``, ``K2 = 0.03``) and ``(1−λ)·L1 + λ·D-SSIM``, the values
:func:`surfphase.fit.losses.photometric_terms` gives with ``backend="torch"``, with a
hand-written backward (gradient to the rendered image only).

Both passes run over image rows (``(view·channel, row)``, rows interleaved over the
threads). A row takes the window's vertical sums of ``x, y, x², y², xy`` over its 11
rows into a zero-padded row buffer, then the horizontal sums of that buffer: the same
products, taps and order of additions as the PyTorch version's shifted sums (a zero-
padded term adds an exact 0), so in float64 its five blurred maps equal PyTorch's bit for
bit. From them each pixel's SSIM ``s`` and its partial derivatives ``∂s/∂μx``,
``∂s/∂E[x²]``, ``∂s/∂E[xy]`` are kept for the backward, and the row's sums of ``s`` and
``|x − y|`` go to that row's own slot. The backward applies the same window to the three
partial-derivative maps (the zero-padded Gaussian window is its own adjoint: it is
symmetric) and adds ``sign(x − y)`` (0 at 0, as PyTorch's ``abs``) for the L1.

The normal consistency runs over rows the same way (row sums in their own slots); the
projection loss is one serial loop over (view, point) pairs (a few thousand).

No two threads write the same number and every sum adds its terms in a fixed order in
one thread, so the results are bit-for-bit identical for any thread count. The sums are
float64 (the photometric term and the projection loss are float64 throughout); outputs
are in the input's dtype. The kernels compile on
first use and are cached on disk (:func:`compile_kernels`, which
:func:`surfphase.render.fused.compile_kernels` calls).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

#: Gaussian window of the SSIM: taps and σ (pixels).
WINDOW = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03

_KW = dict(cache=True, error_model="numpy")


@functools.cache
def _taps(window: int, sigma: float) -> np.ndarray:
    """The window's taps (float64, read-only), computed as
    :func:`surfphase.fit.losses.ssim_map` computes them for float64 images, so that both
    use the same numbers."""
    from surfphase.fit.losses import _gaussian_window

    g = _gaussian_window(window, sigma, torch.float64, "cpu").numpy().copy()
    g.flags.writeable = False
    return g


def _planes(t: Tensor) -> np.ndarray:
    """(K, H, W, D) → a float64 C-contiguous (K·D, H, W) array."""
    K, H, W, D = t.shape
    p = t.detach().to(torch.float64).permute(0, 3, 1, 2).reshape(K * D, H, W)
    return np.ascontiguousarray(p.numpy())


def photometric_fused(
    rendered: Tensor, observed: Tensor, lambda_dssim: float = 0.2, data_range: float = 1.0
) -> tuple[Tensor, Tensor, Tensor]:
    """``(loss_v, l1_v, dssim_v)``, each (K,), of (K, H, W, D) CPU images (see module).

    Gradients flow to ``rendered`` only; ``observed`` must not require grad.
    """
    if rendered.device.type != "cpu" or observed.device.type != "cpu":
        raise ValueError(
            f"photometric_fused: runs on the CPU only, got tensors on {rendered.device} and "
            f"{observed.device}; use backend='torch' (or 'auto') for CUDA"
        )
    if observed.requires_grad:
        raise ValueError(
            "photometric_fused: computes no gradient to the observed image; use "
            "backend='torch' (backend='auto' does so when it requires grad)"
        )
    if rendered.dim() != 4 or rendered.shape != observed.shape:
        raise ValueError(
            f"photometric_fused: need two (K, H, W, D) images of one shape, got "
            f"{tuple(rendered.shape)} and {tuple(observed.shape)}"
        )
    return _Photometric.apply(rendered, observed, float(lambda_dssim), float(data_range))


class _Photometric(torch.autograd.Function):
    """(rendered, observed) → (loss_v, l1_v, dssim_v), each (K,) in rendered's dtype."""

    @staticmethod
    def forward(ctx, rendered: Tensor, observed: Tensor, lam: float, data_range: float):
        from surfphase.render.fused import _threads

        ctx.set_materialize_grads(False)
        K, H, W, D = rendered.shape
        x, y = _planes(rendered), _planes(observed)
        g = _taps(WINDOW, SIGMA)
        c1 = (K1 * data_range) ** 2
        c2 = (K2 * data_range) ** 2
        P = K * D
        l1_rows = np.empty((P, H))
        s_rows = np.empty((P, H))
        d_mu = np.empty((P, H, W))
        d_xx = np.empty((P, H, W))
        d_xy = np.empty((P, H, W))
        _forward(x, y, g, c1, c2, _threads(), l1_rows, s_rows, d_mu, d_xx, d_xy)
        n = float(H * W * D)
        l1_v = l1_rows.reshape(K, D * H).sum(axis=1) / n
        dssim_v = 1.0 - s_rows.reshape(K, D * H).sum(axis=1) / n
        loss_v = (1 - lam) * l1_v + lam * dssim_v
        ctx.saved = (x, y, g, d_mu, d_xx, d_xy, lam, rendered.shape, rendered.dtype)
        dt = rendered.dtype
        return tuple(torch.from_numpy(v).to(dt) for v in (loss_v, l1_v, dssim_v))

    @staticmethod
    def backward(ctx, g_loss: Tensor | None, g_l1: Tensor | None, g_dssim: Tensor | None):
        from surfphase.render.fused import _threads

        x, y, g, d_mu, d_xx, d_xy, lam, shape, dtype = ctx.saved
        K, H, W, D = shape
        if not ctx.needs_input_grad[0]:
            return None, None, None, None

        def per_view(t: Tensor | None) -> np.ndarray:
            return np.zeros(K) if t is None else t.detach().to(torch.float64).numpy()

        gl, g1, gd = per_view(g_loss), per_view(g_l1), per_view(g_dssim)
        n = float(H * W * D)
        # Per plane: ∂/∂|x − y| and ∂/∂s of every pixel.
        a_l1 = np.repeat(((1 - lam) * gl + g1) / n, D)
        a_s = np.repeat(-(lam * gl + gd) / n, D)
        gx = np.empty(x.shape)
        _backward(x, y, g, d_mu, d_xx, d_xy, a_l1, a_s, _threads(), gx)
        out = torch.from_numpy(gx).reshape(K, D, H, W).permute(0, 2, 3, 1)
        return out.to(dtype).contiguous(), None, None, None


@njit(**_KW, parallel=True)
def _forward(x, y, g, c1, c2, n_threads, l1_rows, s_rows, d_mu, d_xx, d_xy):
    """Per row ``r = (p, i)`` of the (P, H, W) planes ``x``, ``y``: ``l1_rows[p, i] =
    Σ_j |x − y|``, ``s_rows[p, i] = Σ_j s`` (SSIM), and per pixel ``d_mu = ∂s/∂μx``,
    ``d_xx = ∂s/∂E[x²]``, ``d_xy = ∂s/∂E[xy]``."""
    P, H, W = x.shape
    L = g.shape[0]
    h = L // 2
    for th in prange(n_threads):
        # Vertical sums of x, y, x², y², xy (zero-padded by h columns each side) and
        # their horizontal sums.
        v0 = np.zeros(W + 2 * h)
        v1 = np.zeros(W + 2 * h)
        v2 = np.zeros(W + 2 * h)
        v3 = np.zeros(W + 2 * h)
        v4 = np.zeros(W + 2 * h)
        o0 = np.empty(W)
        o1 = np.empty(W)
        o2 = np.empty(W)
        o3 = np.empty(W)
        o4 = np.empty(W)
        for r in range(th, P * H, n_threads):
            p = r // H
            i = r % H
            for j in range(h, h + W):
                v0[j] = 0.0
                v1[j] = 0.0
                v2[j] = 0.0
                v3[j] = 0.0
                v4[j] = 0.0
            for k in range(L):
                rr = i + k - h
                if rr < 0 or rr >= H:
                    continue
                gk = g[k]
                xr = x[p, rr]
                yr = y[p, rr]
                for j in range(W):
                    a = xr[j]
                    b = yr[j]
                    v0[h + j] += gk * a
                    v1[h + j] += gk * b
                    v2[h + j] += gk * (a * a)
                    v3[h + j] += gk * (b * b)
                    v4[h + j] += gk * (a * b)
            for j in range(W):
                o0[j] = 0.0
                o1[j] = 0.0
                o2[j] = 0.0
                o3[j] = 0.0
                o4[j] = 0.0
            for k in range(L):
                gk = g[k]
                for j in range(W):
                    o0[j] += gk * v0[j + k]
                    o1[j] += gk * v1[j + k]
                    o2[j] += gk * v2[j + k]
                    o3[j] += gk * v3[j + k]
                    o4[j] += gk * v4[j + k]
            xr = x[p, i]
            yr = y[p, i]
            sl1 = 0.0
            ss = 0.0
            for j in range(W):
                sl1 += abs(xr[j] - yr[j])
                mx = o0[j]
                my = o1[j]
                var_x = o2[j] - mx * mx
                var_y = o3[j] - my * my
                cov = o4[j] - mx * my
                a1 = 2 * mx * my + c1
                a2 = 2 * cov + c2
                b1 = mx * mx + my * my + c1
                b2 = var_x + var_y + c2
                den = b1 * b2
                s = (a1 * a2) / den
                ss += s
                d_mu[p, i, j] = (2 * my * (a2 - a1) - 2 * mx * (b2 - b1) * s) / den
                d_xx[p, i, j] = -s / b2
                d_xy[p, i, j] = 2 * a1 / den
            l1_rows[p, i] = sl1
            s_rows[p, i] = ss


@njit(**_KW, parallel=True)
def _backward(x, y, g, d_mu, d_xx, d_xy, a_l1, a_s, n_threads, gx):
    """``gx = a_s·(W·d_mu + 2x·W·d_xx + y·W·d_xy) + a_l1·sign(x − y)`` per plane ``p``
    (``a_s[p]``, ``a_l1[p]``), ``W·`` the zero-padded window, row by row."""
    P, H, W = x.shape
    L = g.shape[0]
    h = L // 2
    for th in prange(n_threads):
        v0 = np.zeros(W + 2 * h)
        v1 = np.zeros(W + 2 * h)
        v2 = np.zeros(W + 2 * h)
        o0 = np.empty(W)
        o1 = np.empty(W)
        o2 = np.empty(W)
        for r in range(th, P * H, n_threads):
            p = r // H
            i = r % H
            for j in range(h, h + W):
                v0[j] = 0.0
                v1[j] = 0.0
                v2[j] = 0.0
            for k in range(L):
                rr = i + k - h
                if rr < 0 or rr >= H:
                    continue
                gk = g[k]
                m0 = d_mu[p, rr]
                m1 = d_xx[p, rr]
                m2 = d_xy[p, rr]
                for j in range(W):
                    v0[h + j] += gk * m0[j]
                    v1[h + j] += gk * m1[j]
                    v2[h + j] += gk * m2[j]
            for j in range(W):
                o0[j] = 0.0
                o1[j] = 0.0
                o2[j] = 0.0
            for k in range(L):
                gk = g[k]
                for j in range(W):
                    o0[j] += gk * v0[j + k]
                    o1[j] += gk * v1[j + k]
                    o2[j] += gk * v2[j + k]
            xr = x[p, i]
            yr = y[p, i]
            als = a_s[p]
            al1 = a_l1[p]
            for j in range(W):
                a = xr[j]
                b = yr[j]
                e = a - b
                sg = 1.0 if e > 0 else (-1.0 if e < 0 else 0.0)
                gx[p, i, j] = als * (o0[j] + 2 * a * o1[j] + b * o2[j]) + al1 * sg


# -- geometry losses -----------------------------------------------------------------------
def normal_consistency_fused(
    normals: Tensor, normals_from_depth: Tensor, alphas: Tensor | None = None
) -> Tensor:
    """:func:`surfphase.fit.losses.normal_consistency` on the CPU: ``mean(1 − n·(α ñ))``
    over the (C, H, W) pixels, ``α`` detached; gradients to both normal maps.

    Row-parallel, each row's sum in its own slot, the rows summed in order in one thread
    (bit-for-bit for any thread count); float64 sums, the inputs' dtype out.
    """
    if normals.shape != normals_from_depth.shape or normals.shape[-1:] != (3,):
        raise ValueError(
            f"normal_consistency_fused: need two (C, H, W, 3) normal maps of one shape, got "
            f"{tuple(normals.shape)} and {tuple(normals_from_depth.shape)}"
        )
    if alphas is not None and alphas.shape != (*normals.shape[:-1], 1):
        raise ValueError(
            f"normal_consistency_fused: alphas must be (C, H, W, 1), got {tuple(alphas.shape)}"
        )
    return _NormalConsistency.apply(normals, normals_from_depth, alphas)


def _array(t: Tensor) -> np.ndarray:
    """A detached C-contiguous numpy view (or copy) of a CPU tensor, in its dtype."""
    return t.detach().contiguous().numpy()


class _NormalConsistency(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normals: Tensor, nd: Tensor, alphas: Tensor | None):
        from surfphase.render.fused import _threads

        dt = normals.dtype
        n, m = _array(normals), _array(nd.to(dt))
        a = np.ones((1, 1, 1, 1), n.dtype) if alphas is None else _array(alphas.to(dt))
        C, H, W, _ = n.shape
        rows = np.empty(C * H)
        _normal_rows(n, m, a, alphas is not None, _threads(), rows)
        ctx.saved = (n, m, a, alphas is not None)
        return torch.tensor(1.0 - rows.sum() / max(C * H * W, 1), dtype=dt)

    @staticmethod
    def backward(ctx, g: Tensor):
        from surfphase.render.fused import _threads

        n, m, a, has_a = ctx.saved
        C, H, W, _ = n.shape
        scale = -float(g) / max(C * H * W, 1)
        g_n = np.empty_like(n)
        g_m = np.empty_like(m)
        _normal_grads(n, m, a, has_a, scale, _threads(), g_n, g_m)
        return torch.from_numpy(g_n), torch.from_numpy(g_m), None


@njit(**_KW, parallel=True)
def _normal_rows(n, m, a, has_a, n_threads, rows):
    """``rows[c·H + y] = Σ_x n·(α ñ)`` (float64)."""
    C, H, W, _ = n.shape
    for th in prange(n_threads):
        for r in range(th, C * H, n_threads):
            c = r // H
            y = r % H
            acc = 0.0
            for x in range(W):
                al = np.float64(a[c, y, x, 0]) if has_a else 1.0
                acc += (
                    np.float64(n[c, y, x, 0]) * (np.float64(m[c, y, x, 0]) * al)
                    + np.float64(n[c, y, x, 1]) * (np.float64(m[c, y, x, 1]) * al)
                    + np.float64(n[c, y, x, 2]) * (np.float64(m[c, y, x, 2]) * al)
                )
            rows[r] = acc


@njit(**_KW, parallel=True)
def _normal_grads(n, m, a, has_a, scale, n_threads, g_n, g_m):
    """``g_n = scale·α ñ``, ``g_m = scale·α n`` (``scale = −g / (C·H·W)``)."""
    C, H, W, _ = n.shape
    for th in prange(n_threads):
        for r in range(th, C * H, n_threads):
            c = r // H
            y = r % H
            for x in range(W):
                sa = scale * (np.float64(a[c, y, x, 0]) if has_a else 1.0)
                for i in range(3):
                    g_n[c, y, x, i] = sa * np.float64(m[c, y, x, i])
                    g_m[c, y, x, i] = sa * np.float64(n[c, y, x, i])


def projection_loss_fused(
    points: Tensor,
    depth: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    extent: float,
    threshold: float = 0.1,
) -> Tensor:
    """:func:`surfphase.fit.losses.projection_loss` on the CPU (same arguments and rule):
    each (view, point) in one numba loop, float64 inside, the depth sampled bilinearly
    with zero padding as ``grid_sample(align_corners=True)`` does; the gradient to
    ``points`` only (through their camera depth), none to the cameras or the depth."""
    if viewmats.requires_grad or Ks.requires_grad:
        raise ValueError(
            "projection_loss_fused: computes no gradient to viewmats or Ks; use "
            "backend='torch' (backend='auto' does so when the cameras require grad)"
        )
    if points.dim() != 2 or points.shape[1] != 3 or depth.dim() != 4 or depth.shape[-1] != 1:
        raise ValueError(
            f"projection_loss_fused: need points (N, 3) and depth (C, H, W, 1), got "
            f"{tuple(points.shape)} and {tuple(depth.shape)}"
        )
    return _Projection.apply(points, depth, viewmats, Ks, float(extent), float(threshold))


class _Projection(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, depth, viewmats, Ks, extent, threshold):
        p = _planes_f64(points)
        d = _planes_f64(depth[..., 0])
        V = _planes_f64(viewmats)
        K = _planes_f64(Ks)
        C, N = V.shape[0], p.shape[0]
        sgn = np.zeros((C, N))
        err_sum = np.zeros(1)
        n_keep = _projection(p, d, V, K, extent, threshold, sgn, err_sum)
        ctx.saved = (sgn, V, n_keep, extent, points.dtype)
        if n_keep == 0:
            return torch.zeros((), dtype=points.dtype)
        return torch.tensor(err_sum[0] / n_keep, dtype=points.dtype)

    @staticmethod
    def backward(ctx, g: Tensor):
        sgn, V, n_keep, extent, dtype = ctx.saved
        g_p = np.zeros((sgn.shape[1], 3))
        if n_keep:
            _projection_grad(sgn, V, float(g) / (n_keep * extent), g_p)
        return torch.from_numpy(g_p).to(dtype), None, None, None, None, None


def _planes_f64(t: Tensor) -> np.ndarray:
    """A detached float64 C-contiguous numpy copy (or view) of a CPU tensor."""
    return np.ascontiguousarray(t.detach().to(torch.float64).numpy())


@njit(**_KW)
def _projection(p, d, V, K, extent, threshold, sgn, err_sum):
    """Per view c, point n: camera depth z, pixel (u, v), bilinear depth D(u, v); where
    kept (inside, D > 0, e = |z − D|/L ≤ threshold) ``sgn[c, n] = sign(z − D)`` and
    ``e`` adds to ``err_sum``, in (view, point) order. Returns the number kept."""
    C, H, W = d.shape
    N = p.shape[0]
    kept = 0
    total = 0.0
    for c in range(C):
        for n in range(N):
            x0, x1, x2 = p[n, 0], p[n, 1], p[n, 2]
            px = V[c, 0, 0] * x0 + V[c, 0, 1] * x1 + V[c, 0, 2] * x2 + V[c, 0, 3]
            py = V[c, 1, 0] * x0 + V[c, 1, 1] * x1 + V[c, 1, 2] * x2 + V[c, 1, 3]
            z = V[c, 2, 0] * x0 + V[c, 2, 1] * x1 + V[c, 2, 2] * x2 + V[c, 2, 3]
            zs = max(z, 1e-9)
            u = K[c, 0, 0] * px / zs + K[c, 0, 2]
            v = K[c, 1, 1] * py / zs + K[c, 1, 2]
            if not (u >= 0 and u <= W - 1 and v >= 0 and v <= H - 1 and z > 0):
                continue
            # grid_sample(align_corners=True) with one-pixel images samples pixel 0.
            ix = u if W > 1 else 0.0
            iy = v if H > 1 else 0.0
            xa = int(np.floor(ix))
            ya = int(np.floor(iy))
            wx = ix - xa
            wy = iy - ya
            dv = 0.0
            for yy, wyy in ((ya, 1.0 - wy), (ya + 1, wy)):
                if yy < 0 or yy >= H:
                    continue
                for xx, wxx in ((xa, 1.0 - wx), (xa + 1, wx)):
                    if xx < 0 or xx >= W:
                        continue
                    dv += wyy * wxx * d[c, yy, xx]
            e = abs(z - dv) / extent
            if not (dv > 0 and e <= threshold):
                continue
            kept += 1
            total += e
            sgn[c, n] = 1.0 if z > dv else (-1.0 if z < dv else 0.0)
    err_sum[0] = total
    return kept


@njit(**_KW)
def _projection_grad(sgn, V, scale, g_p):
    """``g_p[n] = scale · Σ_c sgn[c, n]·R_c[2, :]`` (∂z/∂p), views in order."""
    C, N = sgn.shape
    for n in range(N):
        for c in range(C):
            s = sgn[c, n]
            if s != 0.0:
                for i in range(3):
                    g_p[n, i] += scale * s * V[c, 2, i]


def compile_kernels() -> None:
    """Compile (or load from numba's cache) every kernel: one tiny forward and backward
    of each loss (the normal consistency for float32 and float64 maps)."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 12, 13, 1, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 12, 13, 1, generator=g, dtype=torch.float64)
    photometric_fused(x, y)[0].sum().backward()
    cam = torch.eye(4, dtype=torch.float64)[None]
    cam[0, 2, 3] = 1.0
    K = torch.tensor([[[10.0, 0.0, 6.0], [0.0, 10.0, 5.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    pts = (0.1 * torch.rand(5, 3, generator=g, dtype=torch.float64)).requires_grad_()
    projection_loss_fused(pts, 1 + x.detach(), cam, K, 1.0, 1.0).backward()
    for dt in (torch.float32, torch.float64):
        n = torch.rand(1, 3, 4, 3, generator=g, dtype=dt, requires_grad=True)
        a = torch.rand(1, 3, 4, 1, generator=g, dtype=dt)
        normal_consistency_fused(n, n.detach() + 1, a).backward()
        normal_consistency_fused(n, n.detach() + 1).backward()
