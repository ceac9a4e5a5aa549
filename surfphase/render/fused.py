"""Fused CPU backend of :func:`surfphase.render.rasterize_surfels` (numba).

The projection and culling are the sparse backend's, in PyTorch
(:func:`surfphase.render.sparse.prepare_surfels`), so their gradients come from autograd;
only the per-(pixel, surfel) work is fused, in a :class:`torch.autograd.Function` whose
forward and backward are numba kernels:

* **binning** (serial): every visible surfel, in (camera, centre depth) order, is listed
  in each image row its screen box meets, so each row's list is in depth order; per
  (row, surfel) entry the pixel span that can hold its support is solved in closed form
  (the sparse backend's conic and low-pass disk), so the candidates are the sparse
  backend's;
* **forward** (parallel over rows): each row walks its surfels in depth order, each over
  its span, so every pixel sees its surfels front to back, with the exact per-pair rules
  of :mod:`surfphase.render.rasterize` (support ``ρ ≤ 9``, near plane, ``α ≥ 1/255``,
  ``α ≤ 0.99``, termination under ``T = 1e-4``), accumulating colour, alpha, depth,
  normals and distortion; it keeps per pixel the final transmittance, the end of its
  blended run, the median pair and the distortion's sums;
* **backward** (parallel over rows): each row walks its surfels in reverse, recovering a
  pixel's transmittance before each pair as ``T / (1 − α)`` (as 2DGS and gsplat do), and
  sums each (row, surfel) entry's gradient of the packed features over its pixels into
  that entry's slot — every slot belongs to one row, so to one thread; a serial loop
  then sums the entries into the per-surfel gradient in entry order.

The kernels read the visible surfels' features from a float64 table in (camera, box top,
box left) order, so one row's surfels sit close together in memory (the row lists keep
depth order). :func:`depth_normals_fused` is the CPU form of
:func:`surfphase.render.rasterize.depth_normals` (both CPU backends use it).

No two threads ever add into the same number, and every sum runs in a fixed order, so the
results are bit-for-bit identical from run to run and for any thread count. Inside the
kernels everything is float64 (float32 inputs are widened, the outputs narrowed), so
there is one compiled specialisation per kernel, cached on disk (``cache=True``).

The support is decided per pair, exactly as in the sparse backend; spans only bound the
candidates. Memory is linear in pixels plus (row, surfel) entries, so
``max_pairs_per_chunk`` is not needed here (accepted, unused).

The kernels run on numba's ``workqueue`` threading layer (chosen in
:mod:`surfphase`: its idle workers sleep on a condition variable rather than spin, and it
brings no second OpenMP runtime beside PyTorch's), with as many threads as
``torch.get_num_threads()`` (capped by numba's pool size).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from surfphase.render.projection import ALPHA_MAX, ALPHA_MIN, CUTOFF, T_MIN
from surfphase.render.sparse import prepare_surfels

# Column layout of the packed feature table (as in surfphase.render.sparse).
_DET, _MX, _MY, _Z, _OPA, _NRM, _COL = 9, 10, 11, 12, 13, 14, 17


def rasterize_fused(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    low_pass: float,
    max_pairs_per_chunk: int,
) -> dict:
    """Render; returns raw accumulations (as :func:`surfphase.render.sparse.rasterize_sparse`).

    ``n_pairs`` counts the candidate (pixel, surfel) pairs tested (the pixels of each
    row span). ``max_pairs_per_chunk`` is ignored (see the module's docstring).
    """
    if means.device.type != "cpu":
        raise ValueError(
            f"rasterize_surfels: the fused backend runs on the CPU only, got tensors on "
            f"{means.device}; use backend='torch' (or 'auto') for CUDA"
        )
    C, N = viewmats.shape[0], means.shape[0]
    D = colors.shape[-1]
    prep = prepare_surfels(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, low_pass
    )
    feats = prep["feats"]
    vis = prep["vis_idx"].numpy().astype(np.int64)
    vbox = np.ascontiguousarray(prep["vbox"].numpy().astype(np.int64))
    # The kernels read the visible surfels' features from a table in (camera, box top,
    # box left) order, so a row's surfels sit close together in memory; the row lists
    # keep depth order.
    store = np.lexsort((vbox[:, 0], vbox[:, 1], vis // max(N, 1))).astype(np.int64)
    loc = np.empty_like(store)
    loc[store] = np.arange(store.shape[0])
    rows = vis[store]  # feature row (c·N + n) of each table row
    f64 = np.ascontiguousarray(feats.detach().to(torch.float64)[torch.from_numpy(rows)].numpy())
    # Support radius² per surfel, slightly widened: min(9, 2 ln(255·o)).
    with np.errstate(divide="ignore", invalid="ignore"):
        r2s = np.minimum(2.0 * np.log(255.0 * f64[:, _OPA]), CUTOFF * CUTOFF) * (1 + 1e-6) + 1e-6
    row_off, row_surf, span = _bin_rows(
        vis // max(N, 1), vbox, loc, f64, r2s, C, int(height), float(low_pass)
    )
    n_pairs = int(np.maximum(span[:, 1] - span[:, 0] + 1, 0).sum())
    consts = (
        C,
        int(width),
        int(height),
        int(D),
        float(near),
        float(far),
        1.0 / (low_pass * low_pass) if low_pass > 0 else 0.0,
        bool(low_pass > 0),
    )
    accum, median = _FusedComposite.apply(feats, f64, rows, row_off, row_surf, span, consts)
    return {
        "n_pairs": n_pairs,
        "accum": accum,
        "depth_median": median,
        "means2d": prep["proj"]["means2d"],
        "radii": prep["radii"],
        "visible": prep["visible"],
    }


def _threads() -> int:
    """Numba threads for the kernels: PyTorch's setting, capped by numba's pool."""
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


class _FusedComposite(torch.autograd.Function):
    """feats (C·N, 17 + D) → accum (C, H, W, D + 6), median depth (C, H, W, 1)."""

    @staticmethod
    def forward(ctx, feats: Tensor, f64, rows, row_off, row_surf, span, consts):
        C, W, H, D, near, far, inv_lp2, use_lp = consts
        # Allocated here, not in the kernel: each array numba builds inside a parallel
        # function is one more parallel region (one more wake-up of its workers).
        accum = np.zeros((C, H, W, D + 6))
        median = np.zeros((C, H, W, 1))
        state = np.zeros((C, H, W, 3))
        idx = np.zeros((C, H, W, 2), dtype=np.int64)
        _forward(
            f64,
            row_off,
            row_surf,
            span,
            C,
            W,
            H,
            D,
            near,
            far,
            inv_lp2,
            use_lp,
            CUTOFF * CUTOFF,
            ALPHA_MIN,
            ALPHA_MAX,
            T_MIN,
            _threads(),
            accum,
            median,
            state,
            idx,
        )
        ctx.fused = (f64, row_off, row_surf, span, consts, accum, state, idx)
        ctx.feat_rows = (rows, feats.shape[0], feats.dtype)
        out_accum = torch.from_numpy(accum).to(feats.dtype)
        out_median = torch.from_numpy(median).to(feats.dtype)
        return out_accum, out_median

    @staticmethod
    def backward(ctx, g_accum: Tensor, g_median: Tensor):
        f64, row_off, row_surf, span, consts, accum, state, idx = ctx.fused
        rows, n_feat_rows, dtype = ctx.feat_rows
        C, W, H, D, near, far, inv_lp2, use_lp = consts
        ga = _as_f64(g_accum, accum.shape)
        gm = _as_f64(g_median, (C, H, W, 1))
        g_entry = np.zeros((row_surf.shape[0], f64.shape[1]))
        _backward(
            f64,
            row_off,
            row_surf,
            span,
            accum,
            state,
            idx,
            ga,
            gm,
            C,
            W,
            H,
            D,
            near,
            far,
            inv_lp2,
            use_lp,
            CUTOFF * CUTOFF,
            ALPHA_MIN,
            ALPHA_MAX,
            _threads(),
            g_entry,
        )
        g_feats = _reduce_entries(g_entry, row_surf, rows, n_feat_rows)
        return torch.from_numpy(g_feats).to(dtype), None, None, None, None, None, None


def _as_f64(g: Tensor | None, shape) -> np.ndarray:
    if g is None:
        return np.zeros(shape, dtype=np.float64)
    return np.ascontiguousarray(g.detach().to(torch.float64).numpy())


@njit(cache=True, parallel=True)
def _bin_rows(cam, vbox, loc, f, r2s, C, H, low_pass):
    """Per-image-row lists of the visible surfels, in depth order, with their pixel spans.

    ``cam`` (S,), ``vbox`` (S, 4) and ``loc`` (S,) give each visible surfel's camera, box
    and row of the feature table ``f``, in (camera, depth) order; ``r2s`` (S,) is r² per
    table row. Returns ``row_off`` (C·H + 1,) CSR offsets over rows ``c·H + y``,
    ``row_surf`` (E,) the table row of each (row, surfel) entry and ``span`` (E, 2) its
    inclusive pixel x-range that can hold support (x1 < x0 when empty).

    On row ``y`` the 3D support ``ρ3d ≤ r²`` (``r² = min(9, 2 ln(255·o))``: beyond it
    α < 1/255, slightly widened) is ``A x² + 2 B x + Cq ≤ 0`` with ``q = J·(x, y, 1)``; its
    root interval is padded for rounding and joined with the low-pass disk; where the
    conic is not an interval (``A ≤ 0``) the whole box is kept. The span is clipped to the
    box; the exact per-pair test decides later.
    """
    # Cameras touch disjoint rows: one thread per camera, each in depth order.
    first = np.searchsorted(cam, np.arange(C + 1))
    count = np.zeros(C * H + 1, dtype=np.int64)
    for c in prange(C):
        for k in range(first[c], first[c + 1]):
            for y in range(vbox[k, 1], vbox[k, 3] + 1):
                count[c * H + y + 1] += 1
    off = np.cumsum(count)
    fill = off[:-1].copy()
    surf = np.empty(off[-1], dtype=np.int64)
    span = np.empty((off[-1], 2), dtype=np.int64)
    for c in prange(C):
        for k in range(first[c], first[c + 1]):
            _bin_one(k, cam, vbox, loc, f, r2s, H, low_pass, fill, surf, span)
    return off, surf, span


@njit(cache=True, inline="always")
def _bin_one(k, cam, vbox, loc, f, r2s, H, low_pass, fill, surf, span):
    """List visible surfel ``k`` in the rows of its box, with each row's span."""
    s = loc[k]
    base = cam[k] * H
    bx0 = vbox[k, 0]
    bx1 = vbox[k, 2]
    r2 = r2s[s]
    a0, a1, a2 = f[s, 0], f[s, 3], f[s, 6]
    A = a0 * a0 + a1 * a1 - r2 * a2 * a2
    mx, my = f[s, _MX], f[s, _MY]
    for y in range(vbox[k, 1], vbox[k, 3] + 1):
        e = fill[base + y]
        fill[base + y] += 1
        surf[e] = s
        if not A > 0.0:
            span[e, 0] = bx0
            span[e, 1] = bx1
            continue
        yf = float(y)
        q0 = f[s, 1] * yf + f[s, 2]
        q1 = f[s, 4] * yf + f[s, 5]
        q2 = f[s, 7] * yf + f[s, 8]
        B = a0 * q0 + a1 * q1 - r2 * a2 * q2
        Cq = q0 * q0 + q1 * q1 - r2 * q2 * q2
        disc = B * B - A * Cq
        if disc >= 0.0:
            root = np.sqrt(disc)
            lo = (-B - root) / A
            hi = (-B + root) / A
            lo -= 1e-6 + 1e-6 * abs(lo)
            hi += 1e-6 + 1e-6 * abs(hi)
        else:
            lo = np.inf
            hi = -np.inf
        if low_pass > 0.0:
            dy = my - yf
            h2 = r2 * low_pass * low_pass - dy * dy
            if h2 >= 0.0:
                h = np.sqrt(h2) + 1e-6
                lo = min(lo, mx - h)
                hi = max(hi, mx + h)
        if lo > hi:
            span[e, 0] = 0
            span[e, 1] = -1
            continue
        span[e, 0] = max(int(np.ceil(max(lo, bx0 - 1.0))), bx0)
        span[e, 1] = min(int(np.floor(min(hi, bx1 + 1.0))), bx1)


@njit(cache=True, inline="always")
def _pair(x, j0, j3, j6, b0, b1, b2, det, mx, dy2, zc, opa, inv_lp2, use_lp, near, r2max):
    """One pair's geometry: (ok, alpha_raw, rho, depth, use3, u, v, inv, depth3).

    Per entry (surfel on row ``y``): ``q = (j0, j3, j6)·x + (b0, b1, b2)`` is
    ``J·(x, y, 1)``, ``dy2 = (μy − y)²·inv_lp2``. ``alpha_raw`` = o·exp(−ρ/2) before the
    0.99 cap; ``ok`` is the support, hit and near-plane test (the 1/255 test is the
    caller's, on the capped alpha).
    """
    q2 = j6 * x + b2
    if q2 == 0.0:
        return False, 0.0, 0.0, 1.0, True, 0.0, 0.0, 0.0, 0.0
    inv = 1.0 / q2
    u = (j0 * x + b0) * inv
    v = (j3 * x + b1) * inv
    rho = u * u + v * v
    depth3 = det * inv
    depth = depth3
    use3 = True
    if use_lp:
        dx = mx - x
        rho2 = dx * dx * inv_lp2 + dy2
        if not rho <= rho2:
            use3 = False
            rho = rho2
            depth = zc
    if rho > r2max or depth < near:
        return False, 0.0, rho, depth, use3, u, v, inv, depth3
    return True, opa * np.exp(-0.5 * rho), rho, depth, use3, u, v, inv, depth3


@njit(cache=True, parallel=True)
def _forward(
    f,
    row_off,
    row_surf,
    span,
    C,
    W,
    H,
    D,
    near,
    far,
    inv_lp2,
    use_lp,
    r2max,
    a_min,
    a_max,
    t_min,
    n_threads,
    accum,
    median,
    state,
    idx,
):
    """Front-to-back compositing, one thread per interleaved set of image rows.

    Each row walks its surfels in depth order, each over its span of pixels, so every
    pixel sees its surfels front to back. Returns ``accum`` (C, H, W, D + 6), ``median``
    (C, H, W, 1), ``state`` (C, H, W, 3) = final transmittance, Σw·m, Σw·m², and ``idx``
    (C, H, W, 2) int64 = end of the pixel's blended run (entry index, exclusive; the
    row's first entry if none) and its median entry (−1 if none); all zero on entry.
    """
    n_rows = C * H
    mscale = far / (far - near)
    for th in prange(n_threads):
        done = np.zeros(W, dtype=np.bool_)
        for r in range(th, n_rows, n_threads):
            c = r // H
            py = r % H
            y = float(py)
            acc = accum[c, py]
            st = state[c, py]
            ix = idx[c, py]
            for px in range(W):
                st[px, 0] = 1.0
                ix[px, 0] = row_off[r]
                ix[px, 1] = -1
                done[px] = False
            for e in range(row_off[r], row_off[r + 1]):
                s = row_surf[e]
                j0, j3, j6 = f[s, 0], f[s, 3], f[s, 6]
                b0 = f[s, 1] * y + f[s, 2]
                b1 = f[s, 4] * y + f[s, 5]
                b2 = f[s, 7] * y + f[s, 8]
                det, mx, my, zc, opa = f[s, _DET], f[s, _MX], f[s, _MY], f[s, _Z], f[s, _OPA]
                dy2 = (my - y) * (my - y) * inv_lp2
                nx, ny, nz = f[s, _NRM], f[s, _NRM + 1], f[s, _NRM + 2]
                for px in range(span[e, 0], span[e, 1] + 1):
                    if done[px]:
                        continue
                    ok, raw, rho, depth, use3, u, v, inv, d3 = _pair(
                        float(px),
                        j0,
                        j3,
                        j6,
                        b0,
                        b1,
                        b2,
                        det,
                        mx,
                        dy2,
                        zc,
                        opa,
                        inv_lp2,
                        use_lp,
                        near,
                        r2max,
                    )
                    if not ok:
                        continue
                    alpha = min(raw, a_max)
                    if alpha < a_min:
                        continue
                    T = st[px, 0]
                    after = T * (1.0 - alpha)
                    if after < t_min:
                        done[px] = True
                        continue
                    w = alpha * T
                    m = mscale * (1.0 - near / depth)
                    m1 = st[px, 1]
                    m2 = st[px, 2]
                    acc[px, D + 5] += (m * m * acc[px, D] + m2 - 2.0 * m * m1) * w
                    for k in range(D):
                        acc[px, k] += w * f[s, _COL + k]
                    acc[px, D] += w
                    acc[px, D + 1] += w * depth
                    acc[px, D + 2] += w * nx
                    acc[px, D + 3] += w * ny
                    acc[px, D + 4] += w * nz
                    st[px, 1] = m1 + w * m
                    st[px, 2] = m2 + w * m * m
                    if T > 0.5:
                        ix[px, 1] = e
                        median[c, py, px, 0] = depth
                    st[px, 0] = after
                    ix[px, 0] = e + 1


@njit(cache=True, parallel=True)
def _backward(
    f,
    row_off,
    row_surf,
    span,
    accum,
    state,
    idx,
    ga,
    gm,
    C,
    W,
    H,
    D,
    near,
    far,
    inv_lp2,
    use_lp,
    r2max,
    a_min,
    a_max,
    n_threads,
    g,
):
    """Back-to-front gradients of the packed features per (row, surfel) entry, into
    ``g`` (E, F), zero on entry.

    Each row walks its surfels in reverse depth order; a pixel's transmittance before a
    pair is recovered as ``T / (1 − α)`` from the final one, and ``suffix`` carries
    Σ_{later k} (∂L/∂w_k)·w_k for the transmittance's share of ∂L/∂α.
    """
    n_rows = C * H
    mscale = far / (far - near)
    for th in prange(n_threads):
        T = np.empty(W)
        suffix = np.empty(W)
        for r in range(th, n_rows, n_threads):
            c = r // H
            py = r % H
            y = float(py)
            acc = accum[c, py]
            st = state[c, py]
            ix = idx[c, py]
            gac = ga[c, py]
            for px in range(W):
                T[px] = st[px, 0]
                suffix[px] = 0.0
            for e in range(row_off[r + 1] - 1, row_off[r] - 1, -1):
                s = row_surf[e]
                j0, j3, j6 = f[s, 0], f[s, 3], f[s, 6]
                b0 = f[s, 1] * y + f[s, 2]
                b1 = f[s, 4] * y + f[s, 5]
                b2 = f[s, 7] * y + f[s, 8]
                det, mx, my, zc, opa = f[s, _DET], f[s, _MX], f[s, _MY], f[s, _Z], f[s, _OPA]
                dy2 = (my - y) * (my - y) * inv_lp2
                nx, ny, nz = f[s, _NRM], f[s, _NRM + 1], f[s, _NRM + 2]
                gj0 = gj1 = gj2 = gj3 = gj4 = gj5 = gj6 = gj7 = gj8 = 0.0
                g_det = g_mx = g_my = g_zc = g_opa = gn0 = gn1 = gn2 = 0.0
                hit_any = False
                for px in range(span[e, 0], span[e, 1] + 1):
                    if e >= ix[px, 0]:
                        continue
                    x = float(px)
                    ok, raw, rho, depth, use3, u, v, inv, d3 = _pair(
                        x,
                        j0,
                        j3,
                        j6,
                        b0,
                        b1,
                        b2,
                        det,
                        mx,
                        dy2,
                        zc,
                        opa,
                        inv_lp2,
                        use_lp,
                        near,
                        r2max,
                    )
                    if not ok:
                        continue
                    alpha = min(raw, a_max)
                    if alpha < a_min:
                        continue
                    hit_any = True
                    Ti = T[px] / (1.0 - alpha)  # transmittance before this pair
                    T[px] = Ti
                    w = alpha * Ti
                    m = mscale * (1.0 - near / depth)
                    sw = acc[px, D]
                    m1 = st[px, 1]
                    m2 = st[px, 2]
                    g_a = gac[px, D]
                    g_z = gac[px, D + 1]
                    g_d = gac[px, D + 5]
                    # dL/dw with the other pairs' weights fixed.
                    g_w = g_a + g_z * depth + g_d * (m * m * sw + m2 - 2.0 * m * m1)
                    g_w += gac[px, D + 2] * nx + gac[px, D + 3] * ny + gac[px, D + 4] * nz
                    for k in range(D):
                        g_w += gac[px, k] * f[s, _COL + k]
                        g[e, _COL + k] += gac[px, k] * w
                    gn0 += gac[px, D + 2] * w
                    gn1 += gac[px, D + 3] * w
                    gn2 += gac[px, D + 4] * w
                    g_alpha = Ti * g_w - suffix[px] / (1.0 - alpha)
                    suffix[px] += g_w * w
                    dm = mscale * near / (depth * depth)
                    g_depth = g_z * w + g_d * 2.0 * w * (m * sw - m1) * dm
                    if e == ix[px, 1]:
                        g_depth += gm[c, py, px, 0]
                    # alpha = min(o·exp(−ρ/2), 0.99): no gradient past the cap.
                    g_raw = g_alpha if raw <= a_max else 0.0
                    g_opa += g_raw * np.exp(-0.5 * rho)
                    g_rho = -0.5 * raw * g_raw
                    if use3:
                        g_u = 2.0 * u * g_rho
                        g_v = 2.0 * v * g_rho
                        g_q0 = g_u * inv
                        g_q1 = g_v * inv
                        g_q2 = -(g_u * u + g_v * v) * inv - g_depth * d3 * inv
                        g_det += g_depth * inv
                        gj0 += g_q0 * x
                        gj1 += g_q0 * y
                        gj2 += g_q0
                        gj3 += g_q1 * x
                        gj4 += g_q1 * y
                        gj5 += g_q1
                        gj6 += g_q2 * x
                        gj7 += g_q2 * y
                        gj8 += g_q2
                    else:
                        g_mx += g_rho * 2.0 * (mx - x) * inv_lp2
                        g_my += g_rho * 2.0 * (my - y) * inv_lp2
                        g_zc += g_depth
                if hit_any:
                    ge = g[e]
                    ge[0] = gj0
                    ge[1] = gj1
                    ge[2] = gj2
                    ge[3] = gj3
                    ge[4] = gj4
                    ge[5] = gj5
                    ge[6] = gj6
                    ge[7] = gj7
                    ge[8] = gj8
                    ge[_DET] = g_det
                    ge[_MX] = g_mx
                    ge[_MY] = g_my
                    ge[_Z] = g_zc
                    ge[_OPA] = g_opa
                    ge[_NRM] = gn0
                    ge[_NRM + 1] = gn1
                    ge[_NRM + 2] = gn2


@njit(cache=True)
def _reduce_entries(g_entry, row_surf, rows, n_rows):
    """Σ of entry gradients per feature row (``rows`` maps table rows to them), serially
    in entry order."""
    F = g_entry.shape[1]
    out = np.zeros((n_rows, F))
    for e in range(row_surf.shape[0]):
        s = rows[row_surf[e]]
        for j in range(F):
            out[s, j] += g_entry[e, j]
    return out


def depth_normals_fused(depth: Tensor, rays: Tensor) -> Tensor:
    """:func:`surfphase.render.rasterize.depth_normals` on the CPU, as numba kernels.

    ``depth`` (C, H, W, 1), metres; ``rays`` (C, H, W, 3) ``K⁻¹·(x, y, 1)`` per pixel (no
    gradient flows to them). Same rule and the same gradient as the PyTorch version
    (float64 inside, including its ``|n| ≥ sqrt(tiny)`` clamp for the input's dtype).
    """
    eps = torch.finfo(depth.dtype).tiny ** 0.5
    return _DepthNormals.apply(depth, rays.detach(), eps)


class _DepthNormals(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth: Tensor, rays: Tensor, eps: float):
        d64 = np.ascontiguousarray(depth.detach().to(torch.float64)[..., 0].numpy())
        r64 = np.ascontiguousarray(rays.to(torch.float64).numpy())
        out = np.zeros(r64.shape)
        _threads()
        _depth_normals_forward(d64, r64, eps, out)
        ctx.fused = (d64, r64, eps, depth.dtype)
        return torch.from_numpy(out).to(depth.dtype)

    @staticmethod
    def backward(ctx, g_out: Tensor):
        d64, r64, eps, dtype = ctx.fused
        g = np.ascontiguousarray(g_out.detach().to(torch.float64).numpy())
        g_dy = np.zeros(r64.shape)
        g_dx = np.zeros(r64.shape)
        g_d = np.zeros(d64.shape)
        _threads()
        _depth_normals_backward(d64, r64, eps, g, g_dy, g_dx, g_d)
        return torch.from_numpy(g_d).to(dtype)[..., None], None, None


@njit(cache=True, parallel=True)
def _depth_normals_forward(d, rays, eps, out):
    """``out[c, y, x] = normalize((P↓ − P↑) × (P→ − P←))`` with ``P = d·ray``, interior."""
    C, H, W = d.shape
    for r in prange(C * H):
        c = r // H
        y = r % H
        if y < 1 or y > H - 2:
            continue
        for x in range(1, W - 1):
            du, dd = d[c, y - 1, x], d[c, y + 1, x]
            dl, dr = d[c, y, x - 1], d[c, y, x + 1]
            dy0 = dd * rays[c, y + 1, x, 0] - du * rays[c, y - 1, x, 0]
            dy1 = dd * rays[c, y + 1, x, 1] - du * rays[c, y - 1, x, 1]
            dy2 = dd * rays[c, y + 1, x, 2] - du * rays[c, y - 1, x, 2]
            dx0 = dr * rays[c, y, x + 1, 0] - dl * rays[c, y, x - 1, 0]
            dx1 = dr * rays[c, y, x + 1, 1] - dl * rays[c, y, x - 1, 1]
            dx2 = dr * rays[c, y, x + 1, 2] - dl * rays[c, y, x - 1, 2]
            n0 = dy1 * dx2 - dy2 * dx1
            n1 = dy2 * dx0 - dy0 * dx2
            n2 = dy0 * dx1 - dy1 * dx0
            norm = max(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), eps)
            out[c, y, x, 0] = n0 / norm
            out[c, y, x, 1] = n1 / norm
            out[c, y, x, 2] = n2 / norm


@njit(cache=True, parallel=True)
def _depth_normals_backward(d, rays, eps, g, g_dy, g_dx, g_d):
    """Gradient of the depth normals w.r.t. the depth, in two row-parallel passes: each
    interior pixel's gradients of its two differences, then each pixel gathers its share
    from its four neighbours (no two threads write the same number)."""
    C, H, W = d.shape
    for r in prange(C * H):
        c = r // H
        y = r % H
        if y < 1 or y > H - 2:
            continue
        for x in range(1, W - 1):
            du, dd = d[c, y - 1, x], d[c, y + 1, x]
            dl, dr = d[c, y, x - 1], d[c, y, x + 1]
            dy0 = dd * rays[c, y + 1, x, 0] - du * rays[c, y - 1, x, 0]
            dy1 = dd * rays[c, y + 1, x, 1] - du * rays[c, y - 1, x, 1]
            dy2 = dd * rays[c, y + 1, x, 2] - du * rays[c, y - 1, x, 2]
            dx0 = dr * rays[c, y, x + 1, 0] - dl * rays[c, y, x - 1, 0]
            dx1 = dr * rays[c, y, x + 1, 1] - dl * rays[c, y, x - 1, 1]
            dx2 = dr * rays[c, y, x + 1, 2] - dl * rays[c, y, x - 1, 2]
            n0 = dy1 * dx2 - dy2 * dx1
            n1 = dy2 * dx0 - dy0 * dx2
            n2 = dy0 * dx1 - dy1 * dx0
            length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            norm = max(length, eps)
            g0, g1, g2 = g[c, y, x, 0], g[c, y, x, 1], g[c, y, x, 2]
            # out = n / max(|n|, eps): the norm's share only where it is not clamped.
            gn0, gn1, gn2 = g0 / norm, g1 / norm, g2 / norm
            if length >= eps and length > 0.0:
                k = (g0 * n0 + g1 * n1 + g2 * n2) / (norm * norm * length)
                gn0 -= k * n0
                gn1 -= k * n1
                gn2 -= k * n2
            # n = dy × dx: ∂/∂dy = dx × g_n, ∂/∂dx = g_n × dy.
            g_dy[c, y, x, 0] = dx1 * gn2 - dx2 * gn1
            g_dy[c, y, x, 1] = dx2 * gn0 - dx0 * gn2
            g_dy[c, y, x, 2] = dx0 * gn1 - dx1 * gn0
            g_dx[c, y, x, 0] = gn1 * dy2 - gn2 * dy1
            g_dx[c, y, x, 1] = gn2 * dy0 - gn0 * dy2
            g_dx[c, y, x, 2] = gn0 * dy1 - gn1 * dy0
    for r in prange(C * H):
        c = r // H
        y = r % H
        for x in range(W):
            acc = 0.0
            for i in range(3):
                gp = 0.0
                if y >= 2:  # pixel (y − 1, x) is interior only if 1 ≤ y − 1 ≤ H − 2
                    gp += g_dy[c, y - 1, x, i]
                if y + 1 <= H - 2:
                    gp -= g_dy[c, y + 1, x, i]
                if x >= 2:
                    gp += g_dx[c, y, x - 1, i]
                if x + 1 <= W - 2:
                    gp -= g_dx[c, y, x + 1, i]
                acc += gp * rays[c, y, x, i]
            g_d[c, y, x] = acc
