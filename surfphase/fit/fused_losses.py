"""Fused CPU form of the fit's photometric term (numba), :func:`photometric_fused`.

Per view of two (K, H, W, D) images: ``L1`` (the mean of ``|x − y|``), ``D-SSIM`` (``1 −``
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

No two threads write the same number and the per-view sums add the row slots in row
order in one thread, so the results are bit-for-bit identical for any thread count.
Everything inside is float64; outputs are in the input's dtype. The kernels compile on
first use and are cached on disk (:func:`compile_kernels`, which
:func:`surfphase.render.fused.compile_kernels` calls).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

#: Gaussian window of the SSIM: taps and σ (pixels).
WINDOW = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03

_KW = dict(cache=True, error_model="numpy")


def _taps(window: int, sigma: float) -> np.ndarray:
    """The window's taps (float64), computed as :func:`surfphase.fit.losses.ssim_map`
    computes them for float64 images, so that both use the same numbers."""
    from surfphase.fit.losses import _gaussian_window

    return _gaussian_window(window, sigma, torch.float64, "cpu").numpy().copy()


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


def compile_kernels() -> None:
    """Compile (or load from numba's cache) both kernels: one tiny forward and backward."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 12, 13, 1, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 12, 13, 1, generator=g, dtype=torch.float64)
    photometric_fused(x, y)[0].sum().backward()
