"""Fused CPU backend of :func:`surfphase.render.rasterize_surfels` (numba).

Every step of a render runs as numba kernels, float64 inside, with hand-written
backward passes; two :class:`torch.autograd.Function` s tie them to autograd:

* :class:`_Project` (means, quats, scales → projected centres ``means2d`` (C, N, 2) and a
  float64 per-(camera, surfel) table: the tangent columns of ``M`` in pixels, the centre
  depth, the camera-facing normal), parallel over surfels. It is its own function so
  that ``means2d.grad`` is the screen-space gradient densification reads, as in the
  sparse backend (at fixed depth and tangent columns).
* :class:`_Raster` (means2d, that table, opacities, colours, backgrounds → every public
  output). Forward: culling and screen boxes
  (:func:`surfphase.render.projection.bounding_boxes`' rule; a surfel is listed only on
  the box rows its support can reach), then per camera a stable radix sort by centre
  depth and a counting sort into per-image-row lists (each row's list in depth order);
  the visible surfels' features
  (adjugate ``J``, ``det``, centre, opacity, normal, colour) sit in a table in (camera,
  box top) order so a row's surfels are close in memory. Then, parallel over bands of
  :data:`BAND` rows (bands interleaved over the threads), each row walks its surfels
  front to back, each over the pixel span that can hold its support (the sparse
  backend's closed form, so the candidate pairs are the sparse backend's), with the
  exact per-pair rules of :mod:`surfphase.render.rasterize`; at the end of a row its
  pixels' outputs are finished in place (background, expected depth, world normals);
  a last pass takes the depth normals. Backward, in the same bands, back to front
  (transmittance recovered as ``T / (1 − α)``, as 2DGS and gsplat do): each (band,
  surfel) has its own gradient slot, written by the one thread that owns the band, in
  row order; a pass parallel over surfels then sums each surfel's slots in band order
  and applies the chain rule of ``J``, ``det`` and the centre (→ ``means2d``), and
  :class:`_Project`'s backward that of the projection and the quaternion.

No two threads ever add into the same number and every sum runs in a fixed order, so
the results are bit-for-bit identical from run to run and for any thread count. Inside
the kernels everything is float64; outputs are written in the inputs' dtype.
Gradients to ``viewmats`` and ``Ks`` are not computed: :func:`rasterize_fused` refuses
cameras that require grad (``backend="auto"`` then takes the sparse backend).

The kernels run on numba's ``workqueue`` threading layer (chosen in :mod:`surfphase`:
its idle workers sleep on a condition variable rather than spin, and it brings no second
OpenMP runtime beside PyTorch's), with as many threads as ``torch.get_num_threads()``
(capped by numba's pool size). They are compiled on first use and cached on disk
(``cache=True``; the first render in a fresh cache compiles for ~25 s, later processes
load them in under a second). :func:`depth_normals_fused` is the CPU form of
:func:`surfphase.render.rasterize.depth_normals` used by the sparse backend.

Why the module and its pair kernels (``_forward``, ``_backward``, ``_project_backward``)
are long: each kernel is one loop nest over a band's rows and their surfels, with the
per-pair state (transmittance, the pixel's running sums, the entry's features) in
local variables; split into functions, numba would pass that state through memory on
every pair, which costs the per-pair time the backend exists to save. The forward and
the backward of one quantity are kept side by side in this one module so that they are
read and changed together.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from surfphase.render.projection import ALPHA_MAX, ALPHA_MIN, CUTOFF, T_MIN

#: Rows per band: the unit of work of a thread, and of a surfel's gradient slot.
BAND = 8

# Columns of the per-(camera, surfel) projection table ``geo`` (float64).
_G_C0, _G_C1, _G_Z, _G_N, _G_MX, _G_MY, _G_FLIP, _G_WIDTH = 0, 3, 6, 7, 10, 11, 12, 13
# Columns of the visible surfels' feature table: adjugate J (row-major), det, centre
# (pixels), centre depth, opacity, normal (camera, facing it), support radius² for the
# spans, the conic's x² coefficient, the tangent columns c0, c1 (for the backward
# pass), colour (D).
_J, _DET, _MX, _MY, _Z, _OPA, _NRM, _R2, _A, _C0, _C1, _COL = (
    0, 9, 10, 11, 12, 13, 14, 17, 18, 19, 22, 25
)  # fmt: skip
# Gradient slots use the same columns up to the normal, then colour at 17.
_GCOL = 17

_KW = dict(cache=True, error_model="numpy")


def _threads() -> int:
    """Numba threads for the kernels: PyTorch's setting, capped by numba's pool."""
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


def _np(t: Tensor) -> np.ndarray:
    """A detached float64 C-contiguous numpy view or copy of ``t``."""
    return np.ascontiguousarray(t.detach().to(torch.float64).numpy())


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
    backgrounds: Tensor | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """Render; returns what :func:`surfphase.render.rasterize_surfels` returns.

    ``n_pairs`` counts the candidate (pixel, surfel) pairs tested (the pixels of each
    row span; the sparse backend's count).
    """
    if means.device.type != "cpu":
        raise ValueError(
            f"rasterize_surfels: the fused backend runs on the CPU only, got tensors on "
            f"{means.device}; use backend='torch' (or 'auto') for CUDA"
        )
    if viewmats.requires_grad or Ks.requires_grad:
        raise ValueError(
            "rasterize_surfels: the fused backend computes no gradients to viewmats or Ks; "
            "use backend='torch' (backend='auto' does so when the cameras require grad)"
        )
    C, N = viewmats.shape[0], means.shape[0]
    D = colors.shape[-1]
    dtype = means.dtype
    V = _np(viewmats)
    K = _np(Ks)
    Kinv = np.ascontiguousarray(np.linalg.inv(K)) if C else K
    if backgrounds is None:
        bg = None
    else:
        bg = backgrounds.to(dtype)
        bg = bg.expand(C, D) if bg.dim() == 1 else bg
    consts = (C, N, D, int(width), int(height), float(near), float(far), float(low_pass), dtype)
    means2d, geo = _Project.apply(means, quats, scales, (V, K))
    info: dict = {}
    outs = _Raster.apply(means2d, geo, opacities, colors, bg, (V, K, Kinv), consts, info)
    cols, alphas, de, da, dm, nc, nw, nfd, nfdw, dist = outs
    if means2d.requires_grad:
        means2d.retain_grad()
    meta = {
        "depth_expected": de,
        "depth_accum": da,
        "depth_median": dm,
        "normals_camera": nc,
        "normals_world": nw,
        "normals_from_depth": nfd,
        "normals_from_depth_world": nfdw,
        "distortion": dist,
        "radii": info["radii"],
        "visible": info["visible"],
        "means2d": means2d,
        "n_pairs": info["n_pairs"],
    }
    return cols, alphas, meta


class _Project(torch.autograd.Function):
    """(means, quats, scales) → means2d (C, N, 2) in their dtype, geo (C, N, 13) float64."""

    @staticmethod
    def forward(ctx, means: Tensor, quats: Tensor, scales: Tensor, cams):
        V, K = cams
        C, N = V.shape[0], means.shape[0]
        m, q, s = _np(means), _np(quats), _np(scales)
        geo = np.empty((C, N, _G_WIDTH))
        _project(m, q, s, V, K, _threads(), geo)
        ctx.saved = (m, q, s, V, K, geo, means.dtype)
        m2d = torch.from_numpy(geo[..., _G_MX : _G_MY + 1].copy()).to(means.dtype)
        return m2d, torch.from_numpy(geo)

    @staticmethod
    def backward(ctx, g_m2d: Tensor | None, g_geo: Tensor | None):
        m, q, s, V, K, geo, dtype = ctx.saved
        C, N = geo.shape[:2]
        gm = np.zeros((C, N, 2)) if g_m2d is None else _np(g_m2d)
        gg = np.zeros((C, N, _G_WIDTH)) if g_geo is None else _np(g_geo)
        g_means = np.empty((N, 3))
        g_quats = np.empty((N, 4))
        g_scales = np.empty((N, 2))
        _project_backward(m, q, s, V, K, geo, gm, gg, _threads(), g_means, g_quats, g_scales)
        return (
            torch.from_numpy(g_means).to(dtype),
            torch.from_numpy(g_quats).to(dtype),
            torch.from_numpy(g_scales).to(dtype),
            None,
        )


_OUT_CHANNELS = (
    "D",
    1,
    1,
    1,
    1,
    3,
    3,
    3,
    3,
    1,
)  # colours, alpha, de, da, dm, nc, nw, nfd, nfdw, dist


class _Raster(torch.autograd.Function):
    """(means2d, geo, opacities, colours, backgrounds) → the ten image outputs."""

    @staticmethod
    def forward(ctx, means2d, geo, opacities, colors, bg, cams, consts, info):
        ctx.set_materialize_grads(False)
        V, K, Kinv = cams
        C, N, D, W, H, near, far, low_pass, dtype = consts
        npdt = np.float64 if dtype == torch.float64 else np.float32
        nth = _threads()
        g = geo.detach().numpy()
        opa = _np(opacities)
        col = _np(colors).reshape(1 if colors.dim() == 2 else C, N, D)
        bg64 = np.zeros((C, D)) if bg is None else _np(bg)
        # Row 0: ones, rows 1…C: the backgrounds, in the outputs' dtype.
        bg_out = np.ones((1 + C, D), dtype=npdt)
        bg_out[1:] = bg64
        # Culling, boxes, sorting and row lists.
        box = np.empty((C, N, 4), dtype=np.int64)
        vis = np.empty((C, N), dtype=np.bool_)
        radii = np.empty((C, N), dtype=np.int32)
        _cull(g, opa, W, H, near, far, low_pass, nth, box, vis, radii)
        tix, row_off, row_surf, tab_cn, sbase = _bin(g, vis, box, H, BAND)
        S = tab_cn.shape[0]
        f = np.empty((S, _COL + D))
        _table(g, opa, col, tab_cn, N, nth, f)
        tab_box = box.reshape(C * N, 4)[tab_cn] if S else np.zeros((0, 4), dtype=np.int64)
        E = row_surf.shape[0]
        span = np.empty((E, 2), dtype=np.int32)
        sv = np.empty((C, H, W, 6))
        six = np.empty((C, H, W, 2), dtype=np.int32)
        outs = [np.empty((C, H, W, D if k == "D" else k), dtype=npdt) for k in _OUT_CHANNELS]
        pairs = np.zeros(nth, dtype=np.int64)
        inv_lp2 = 1.0 / (low_pass * low_pass) if low_pass > 0 else 0.0
        _forward(
            f, row_off, row_surf, tab_box, C, W, H, D, near, far, inv_lp2, low_pass,
            CUTOFF * CUTOFF, ALPHA_MIN, ALPHA_MAX, T_MIN, bg is not None, bg_out, V, nth, BAND,
            span, sv, six, *outs[:7], outs[9], pairs,
        )  # fmt: skip
        eps = float(torch.finfo(dtype).tiny ** 0.5)
        _depth_normals_out(sv, Kinv, V, eps, nth, outs[7], outs[8])
        info["radii"] = torch.from_numpy(radii)
        info["visible"] = torch.from_numpy(vis)
        info["n_pairs"] = int(pairs.sum())
        ctx.saved = (g, f, tix, row_off, row_surf, tab_cn, sbase, tab_box, span, sv, six, vis)
        ctx.misc = (bg64, V, Kinv, consts, eps, col.shape[0], bg is not None)
        return tuple(torch.from_numpy(o) for o in outs)

    @staticmethod
    def backward(ctx, *grads):
        g, f, tix, row_off, row_surf, tab_cn, sbase, tab_box, span, sv, six, vis = ctx.saved
        bg64, V, Kinv, consts, eps, n_col_cams, has_bg = ctx.misc
        C, N, D, W, H, near, far, low_pass, dtype = consts
        nth = _threads()
        gargs, flags = [], np.zeros(len(grads), dtype=np.int64)
        for i, (gr, k) in enumerate(zip(grads, _OUT_CHANNELS, strict=True)):
            arr, flags[i] = _grad_arg(gr, D if k == "D" else k)
            gargs.append(arr)
        # Depth normals' share of the expected depth's gradient.
        g_de_n = np.zeros((C, H, W))
        if flags[7] or flags[8]:
            gdy = np.empty((C, H, W, 3))
            gdx = np.empty((C, H, W, 3))
            _depth_normals_grad(
                sv, Kinv, V, eps, gargs[7], flags[7], gargs[8], flags[8], nth, gdy, gdx, g_de_n
            )
        n_slots = sbase[-1] if sbase.shape[0] else 0
        gslot = np.empty((n_slots, _GCOL + D))
        row_bg = np.empty((C * H, D))
        inv_lp2 = 1.0 / (low_pass * low_pass) if low_pass > 0 else 0.0
        _backward(
            f, row_off, row_surf, span, tab_box, sbase, C, W, H, D, near, far, inv_lp2,
            low_pass > 0, CUTOFF * CUTOFF, ALPHA_MIN, ALPHA_MAX, bg64, V, sv, six, g_de_n,
            *gargs[:7], gargs[9], flags, nth, BAND, gslot, row_bg,
        )  # fmt: skip
        g_geo = np.empty(g.shape)
        g_m2d = np.empty((C, N, 2))
        g_opa = np.empty(N)
        g_col = np.empty((n_col_cams, N, D))
        g_tab = np.empty((tab_cn.shape[0], 13 + D))
        _reduce(gslot, sbase, tab_cn, tix, f, D, nth, g_tab, g_geo, g_m2d, g_opa, g_col)
        g_bg = None
        if has_bg and ctx.needs_input_grad[4]:
            g_bg = torch.from_numpy(row_bg.reshape(C, H, D).sum(axis=1)).to(dtype)
        return (
            torch.from_numpy(g_m2d).to(dtype),
            torch.from_numpy(g_geo),
            torch.from_numpy(g_opa).to(dtype),
            torch.from_numpy(g_col.reshape(-1, D) if n_col_cams == 1 else g_col).to(dtype)
            if ctx.needs_input_grad[3]
            else None,
            g_bg,
            None,
            None,
            None,
        )


def _grad_arg(g: Tensor | None, k: int) -> tuple[np.ndarray, int]:
    """An output's gradient as a (C, H, W, k) float64 array and an indexing flag: 1 for
    a full array, 0 for one value per channel broadcast over pixels (an expanded
    gradient, as ``.sum()`` gives, or zeros for ``None``)."""
    if g is None:
        return np.zeros((1, 1, 1, k)), 0
    if g.dim() == 4 and g.stride()[:3] == (0, 0, 0):
        return _np(g[:1, :1, :1]), 0
    return _np(g), 1


# exp(x) for x in [−4.5, 0] (x = −ρ/2 with ρ ≤ 9), inlined in the per-pair loops (a libm
# call there spills every live register): x = −i·ln2/32 + r, |r| ≤ ln2/64, exp(x) =
# 2^(−i/32)·p(r) with p the degree-6 Taylor polynomial (truncation < 4e-18); within
# 2 ulp of the correctly rounded value. ln2/32 is split in two so that i·_LN2_32_HI is
# exact.
_EXP_TABLE = np.exp2(-np.arange(224) / 32.0)
_LN2_32_HI = 0.021660849452018738
_LN2_32_LO = -5.952044687368025e-11
_INV_LN2_32 = 46.16624130844683


@njit(**_KW, inline="always")
def _exp_neg(x):
    """exp(x) for −4.5 ≤ x ≤ 0 (see above)."""
    i = int(-x * _INV_LN2_32 + 0.5)
    r = x + i * _LN2_32_HI + i * _LN2_32_LO
    p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6 + r * (1.0 / 24 + r * (1.0 / 120 + r / 720)))))
    return _EXP_TABLE[i] * p


# -- projection ---------------------------------------------------------------------------
@njit(**_KW, inline="always")
def _rotmat(q0, q1, q2, q3):
    """Unit quaternion (w, x, y, z) → rotation matrix entries, row-major."""
    return (
        1.0 - 2.0 * (q2 * q2 + q3 * q3),
        2.0 * (q1 * q2 - q0 * q3),
        2.0 * (q1 * q3 + q0 * q2),
        2.0 * (q1 * q2 + q0 * q3),
        1.0 - 2.0 * (q1 * q1 + q3 * q3),
        2.0 * (q2 * q3 - q0 * q1),
        2.0 * (q1 * q3 - q0 * q2),
        2.0 * (q2 * q3 + q0 * q1),
        1.0 - 2.0 * (q1 * q1 + q2 * q2),
    )


@njit(**_KW, parallel=True)
def _project(means, quats, scales, V, K, n_threads, geo):
    """Per (camera c, surfel n): ``geo[c, n]`` = tangent columns ``c0 = K·R·s_u·t_u`` and
    ``c1`` (pixels), centre depth z, unit normal in the camera frame facing it, projected
    centre (pixels) and the ±1 flip applied to the normal (see
    :func:`surfphase.render.projection.project_surfels`)."""
    N = means.shape[0]
    for th in prange(n_threads):
        p = np.empty(3)
        a = np.empty(3)
        b = np.empty(3)
        nn = np.empty(3)
        for n in range(th, N, n_threads):
            _project_one(means, quats, scales, V, K, n, geo, p, a, b, nn)


@njit(**_KW, inline="always")
def _project_one(means, quats, scales, V, K, n, geo, p, a, b, nn):
    C = V.shape[0]
    w, x, y, z = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
    inv = 1.0 / max(np.sqrt(w * w + x * x + y * y + z * z), 1e-12)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotmat(w * inv, x * inv, y * inv, z * inv)
    su, sv = scales[n, 0], scales[n, 1]
    mx, my, mz = means[n, 0], means[n, 1], means[n, 2]
    for c in range(C):
        for i in range(3):
            Ri0, Ri1, Ri2 = V[c, i, 0], V[c, i, 1], V[c, i, 2]
            p[i] = Ri0 * mx + Ri1 * my + Ri2 * mz + V[c, i, 3]
            a[i] = (Ri0 * r00 + Ri1 * r10 + Ri2 * r20) * su
            b[i] = (Ri0 * r01 + Ri1 * r11 + Ri2 * r21) * sv
            nn[i] = Ri0 * r02 + Ri1 * r12 + Ri2 * r22
        for i in range(3):
            geo[c, n, _G_C0 + i] = K[c, i, 0] * a[0] + K[c, i, 1] * a[1] + K[c, i, 2] * a[2]
            geo[c, n, _G_C1 + i] = K[c, i, 0] * b[0] + K[c, i, 1] * b[1] + K[c, i, 2] * b[2]
        zc = p[2]
        geo[c, n, _G_Z] = zc
        geo[c, n, _G_MX] = (K[c, 0, 0] * p[0] + K[c, 0, 1] * p[1] + K[c, 0, 2] * p[2]) / zc
        geo[c, n, _G_MY] = (K[c, 1, 0] * p[0] + K[c, 1, 1] * p[1] + K[c, 1, 2] * p[2]) / zc
        flip = -1.0 if nn[0] * p[0] + nn[1] * p[1] + nn[2] * p[2] > 0 else 1.0
        geo[c, n, _G_FLIP] = flip
        for i in range(3):
            geo[c, n, _G_N + i] = nn[i] * flip


@njit(**_KW, parallel=True)
def _project_backward(means, quats, scales, V, K, geo, g_m2d, g_geo, n_threads, gm, gq, gs):
    """Backward of :func:`_project`: per surfel, the cameras' shares in camera order."""
    C = V.shape[0]
    N = means.shape[0]
    for th in prange(n_threads):
        grot = np.empty(9)
        g_mean = np.empty(3)
        gp = np.empty(3)
        ga = np.empty(3)
        gb = np.empty(3)
        for n in range(th, N, n_threads):
            w0, x0, y0, z0 = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
            length = np.sqrt(w0 * w0 + x0 * x0 + y0 * y0 + z0 * z0)
            inv = 1.0 / max(length, 1e-12)
            w, x, y, z = w0 * inv, x0 * inv, y0 * inv, z0 * inv
            r = _rotmat(w, x, y, z)
            su, sv = scales[n, 0], scales[n, 1]
            for k in range(9):
                grot[k] = 0.0
            g_su = 0.0
            g_sv = 0.0
            for k in range(3):
                g_mean[k] = 0.0
            for c in range(C):
                zc = geo[c, n, _G_Z]
                # means2d = (K·p)[:2] / z, z = p[2].
                gx, gy = g_m2d[c, n, 0], g_m2d[c, n, 1]
                gpx, gpy = gx / zc, gy / zc
                gz = g_geo[c, n, _G_Z] - (gx * geo[c, n, _G_MX] + gy * geo[c, n, _G_MY]) / zc
                for i in range(3):
                    gp[i] = K[c, 0, i] * gpx + K[c, 1, i] * gpy
                    # c0 = K·a, c1 = K·b → g_a = Kᵀ·g_c0, g_b = Kᵀ·g_c1.
                    ga[i] = (
                        K[c, 0, i] * g_geo[c, n, _G_C0]
                        + K[c, 1, i] * g_geo[c, n, _G_C0 + 1]
                        + K[c, 2, i] * g_geo[c, n, _G_C0 + 2]
                    )
                    gb[i] = (
                        K[c, 0, i] * g_geo[c, n, _G_C1]
                        + K[c, 1, i] * g_geo[c, n, _G_C1 + 1]
                        + K[c, 2, i] * g_geo[c, n, _G_C1 + 2]
                    )
                gp[2] += gz
                flip = geo[c, n, _G_FLIP]
                for j in range(3):
                    # p = R·mean + t, a = R·rot[:, 0]·s_u, b = R·rot[:, 1]·s_v, n = flip·R·rot[:, 2].
                    rp = V[c, 0, j] * gp[0] + V[c, 1, j] * gp[1] + V[c, 2, j] * gp[2]
                    ra = V[c, 0, j] * ga[0] + V[c, 1, j] * ga[1] + V[c, 2, j] * ga[2]
                    rb = V[c, 0, j] * gb[0] + V[c, 1, j] * gb[1] + V[c, 2, j] * gb[2]
                    rn = (
                        V[c, 0, j] * g_geo[c, n, _G_N]
                        + V[c, 1, j] * g_geo[c, n, _G_N + 1]
                        + V[c, 2, j] * g_geo[c, n, _G_N + 2]
                    )
                    g_mean[j] += rp
                    grot[3 * j] += ra * su
                    grot[3 * j + 1] += rb * sv
                    grot[3 * j + 2] += rn * flip
                    g_su += ra * r[3 * j]
                    g_sv += rb * r[3 * j + 1]
            G00, G01, G02, G10, G11, G12, G20, G21, G22 = (
                grot[0], grot[1], grot[2], grot[3], grot[4], grot[5], grot[6], grot[7], grot[8]
            )  # fmt: skip
            gw = 2.0 * (-z * G01 + y * G02 + z * G10 - x * G12 - y * G20 + x * G21)
            gx_ = 2.0 * (
                y * G01
                + z * G02
                + y * G10
                - 2.0 * x * G11
                - w * G12
                + z * G20
                + w * G21
                - 2.0 * x * G22
            )
            gy_ = 2.0 * (
                -2.0 * y * G00
                + x * G01
                + w * G02
                + x * G10
                + z * G12
                - w * G20
                + z * G21
                - 2.0 * y * G22
            )
            gz_ = 2.0 * (
                -2.0 * z * G00
                - w * G01
                + x * G02
                + w * G10
                - 2.0 * z * G11
                + y * G12
                + x * G20
                + y * G21
            )
            if length > 1e-12:
                dot = w * gw + x * gx_ + y * gy_ + z * gz_
                gq[n, 0] = (gw - w * dot) * inv
                gq[n, 1] = (gx_ - x * dot) * inv
                gq[n, 2] = (gy_ - y * dot) * inv
                gq[n, 3] = (gz_ - z * dot) * inv
            else:
                gq[n, 0] = gw * inv
                gq[n, 1] = gx_ * inv
                gq[n, 2] = gy_ * inv
                gq[n, 3] = gz_ * inv
            gm[n, 0] = g_mean[0]
            gm[n, 1] = g_mean[1]
            gm[n, 2] = g_mean[2]
            gs[n, 0] = g_su
            gs[n, 1] = g_sv


# -- culling, sorting, row lists ---------------------------------------------------------
@njit(**_KW, inline="always")
def _lo(a, b, big):
    """torch.minimum(a, b) then nan_to_num(−big, −big, −big)."""
    v = a if a < b else b
    if np.isnan(a) or np.isnan(b) or np.isinf(v):
        return -big
    return v


@njit(**_KW, inline="always")
def _hi(a, b, big):
    """torch.maximum(a, b) then nan_to_num(big, big, big)."""
    v = a if a > b else b
    if np.isnan(a) or np.isnan(b) or np.isinf(v):
        return big
    return v


@njit(**_KW, inline="always")
def _support_rows(a0, a1, a2, b0, b1, b2, e0, e1, e2, r2, my, low_pass, y0, y1):
    """Rows [ya, yb] ⊆ [y0, y1] on which a surfel's row spans (:func:`_span`) can be
    non-empty (yb < ya when none).

    With ``q = J·(x, y, 1)`` (J the adjugate of ``M = [c0 c1 centre]``) the 3D support
    ``q0² + q1² − r² q2² ≤ 0`` meets row y iff the discriminant of its quadratic in x,
    ``α y² + 2β y + γ``, is ≥ 0; with ``A > 0`` (bounded in x) and ``α < 0`` that is an
    interval of y, padded by 1e-3 px for rounding, joined with the low-pass disk's rows
    ``|y − μy| ≤ r·low_pass``. Otherwise (unbounded or degenerate conic) the box rows
    are kept.
    """
    # Rows of J: c1 × centre, centre × c0, c0 × c1; columns x, y, 1.
    jx0, jy0, j10 = b1 * e2 - b2 * e1, b2 * e0 - b0 * e2, b0 * e1 - b1 * e0
    jx1, jy1, j11 = e1 * a2 - e2 * a1, e2 * a0 - e0 * a2, e0 * a1 - e1 * a0
    jx2, jy2, j12 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    A = jx0 * jx0 + jx1 * jx1 - r2 * jx2 * jx2
    qxy = jx0 * jy0 + jx1 * jy1 - r2 * jx2 * jy2
    qx1 = jx0 * j10 + jx1 * j11 - r2 * jx2 * j12
    qyy = jy0 * jy0 + jy1 * jy1 - r2 * jy2 * jy2
    qy1 = jy0 * j10 + jy1 * j11 - r2 * jy2 * j12
    q11 = j10 * j10 + j11 * j11 - r2 * j12 * j12
    al = qxy * qxy - A * qyy
    be = qxy * qx1 - A * qy1
    ga = qx1 * qx1 - A * q11
    if not (A > 0.0 and al < 0.0):
        return y0, y1
    lo = np.inf
    hi = -np.inf
    d = be * be - al * ga
    if d >= 0.0:
        root = np.sqrt(d)
        lo = (-be + root) / al
        hi = (-be - root) / al
    if low_pass > 0.0:
        h = np.sqrt(r2) * low_pass
        lo = min(lo, my - h)
        hi = max(hi, my + h)
    if not (lo <= hi):  # empty, or NaN from a degenerate surfel: keep the box rows
        return (y0, y1) if np.isnan(lo) or np.isnan(hi) else (y0, y0 - 1)
    lo -= 1e-3 + 1e-6 * abs(lo)
    hi += 1e-3 + 1e-6 * abs(hi)
    ya = max(y0, int(np.ceil(min(max(lo, y0 - 1.0), y1 + 1.0))))
    yb = min(y1, int(np.floor(max(min(hi, y1 + 1.0), y0 - 1.0))))
    return (ya, yb) if ya <= yb else (y0, y0 - 1)


@njit(**_KW, parallel=True)
def _cull(geo, opa, W, H, near, far, low_pass, n_threads, box, vis, radii):
    """Screen boxes (:func:`surfphase.render.projection.bounding_boxes`), visibility and
    radii per (camera, surfel)."""
    C, N = geo.shape[0], geo.shape[1]
    big = 4.0 * max(W, H)
    k2 = CUTOFF * CUTOFF
    r2d = CUTOFF * low_pass
    for i in prange(C * N):
        c = i // N
        n = i % N
        a0, a1, a2 = geo[c, n, _G_C0], geo[c, n, _G_C0 + 1], geo[c, n, _G_C0 + 2]
        b0, b1, b2 = geo[c, n, _G_C1], geo[c, n, _G_C1 + 1], geo[c, n, _G_C1 + 2]
        zc, mx, my = geo[c, n, _G_Z], geo[c, n, _G_MX], geo[c, n, _G_MY]
        e0, e1, e2 = mx * zc, my * zc, zc
        d00 = k2 * (a0 * a0 + b0 * b0) - e0 * e0
        d11 = k2 * (a1 * a1 + b1 * b1) - e1 * e1
        d22 = k2 * (a2 * a2 + b2 * b2) - e2 * e2
        d02 = k2 * (a0 * a2 + b0 * b2) - e0 * e2
        d12 = k2 * (a1 * a2 + b1 * b2) - e1 * e2
        if d22 < 0:
            cx = d02 / d22
            cy = d12 / d22
            hx = np.sqrt(max(cx * cx - d00 / d22, 0.0))
            hy = np.sqrt(max(cy * cy - d11 / d22, 0.0))
            lo_x = _lo(cx - hx, mx - r2d, big)
            lo_y = _lo(cy - hy, my - r2d, big)
            hi_x = _hi(cx + hx, mx + r2d, big)
            hi_y = _hi(cy + hy, my + r2d, big)
        else:
            lo_x = lo_y = -big
            hi_x = hi_y = big
        x0 = max(int(np.floor(min(max(lo_x, -big), big))), 0)
        y0 = max(int(np.floor(min(max(lo_y, -big), big))), 0)
        x1 = min(int(np.ceil(min(max(hi_x, -big), big))), W - 1)
        y1 = min(int(np.ceil(min(max(hi_y, -big), big))), H - 1)
        v = zc >= near and zc <= far and x0 <= x1 and y0 <= y1 and opa[n] >= ALPHA_MIN
        vis[c, n] = v
        radii[c, n] = int(np.ceil(max((hi_x - lo_x) / 2, (hi_y - lo_y) / 2))) if v else 0
        if v:
            # Only the rows the support can reach get (row, surfel) entries.
            r2 = min(2.0 * np.log(255.0 * opa[n]), CUTOFF * CUTOFF) * (1 + 1e-6) + 1e-6
            y0, y1 = _support_rows(a0, a1, a2, b0, b1, b2, e0, e1, e2, r2, my, low_pass, y0, y1)
        box[c, n, 0] = x0
        box[c, n, 1] = y0
        box[c, n, 2] = x1
        box[c, n, 3] = y1


@njit(**_KW)
def _radix_order(keys):
    """Stable ascending order of non-negative int64 ``keys`` (LSD radix, 8-bit digits)."""
    n = keys.shape[0]
    order = np.arange(n)
    tmp = np.empty(n, dtype=np.int64)
    count = np.empty(257, dtype=np.int64)
    for shift in range(0, 64, 8):
        first = (keys[order[0]] >> shift) & 255 if n else 0
        same = True
        for i in range(n):
            if ((keys[i] >> shift) & 255) != first:
                same = False
                break
        if same:
            continue
        for d in range(257):
            count[d] = 0
        for i in range(n):
            count[((keys[i] >> shift) & 255) + 1] += 1
        for d in range(256):
            count[d + 1] += count[d]
        for i in range(n):
            k = order[i]
            d = (keys[k] >> shift) & 255
            tmp[count[d]] = k
            count[d] += 1
        order, tmp = tmp, order
    return order


@njit(**_KW, parallel=True)
def _bin(geo, vis, box, H, band):
    """Visible surfels in a table in (camera, box top) order, and per image row the list
    of their table rows in order of centre depth (stable on ties).

    Returns ``tix`` (C·N,) table row of each (camera, surfel) (−1 if not visible),
    ``row_off`` (C·H + 1,) CSR offsets over rows ``c·H + y``, ``row_surf`` (E,) table rows
    per row in depth order, ``tab_cn`` (S,) the ``c·N + n`` of each table row, ``sbase``
    (S + 1,) offsets of each table row's gradient slots (one per band its box meets).
    """
    C, N = vis.shape
    cnt = np.zeros(C + 1, dtype=np.int64)
    for c in range(C):
        for n in range(N):
            if vis[c, n]:
                cnt[c + 1] += 1
    for c in range(C):
        cnt[c + 1] += cnt[c]
    S = cnt[C]
    tix = np.full(C * N, -1, dtype=np.int64)
    tab_cn = np.empty(S, dtype=np.int64)
    depth_order = np.empty(S, dtype=np.int64)
    row_cnt = np.zeros(C * H + 1, dtype=np.int64)
    for c in prange(C):
        base = cnt[c]
        m = cnt[c + 1] - base
        idx = np.empty(m, dtype=np.int64)
        k = 0
        for n in range(N):
            if vis[c, n]:
                idx[k] = n
                k += 1
        # Depth order: positive float64 bit patterns sort as integers.
        zs = np.empty(m)
        for i in range(m):
            zs[i] = geo[c, idx[i], _G_Z]
        keys = zs.view(np.int64)
        od = idx[_radix_order(keys)]
        # Table order: by box top (counting sort, stable: depth order within a row).
        tops = np.zeros(H + 1, dtype=np.int64)
        for i in range(m):
            tops[box[c, od[i], 1] + 1] += 1
        for y in range(H):
            tops[y + 1] += tops[y]
        for i in range(m):
            n = od[i]
            t = base + tops[box[c, n, 1]]
            tops[box[c, n, 1]] += 1
            tab_cn[t] = c * N + n
            tix[c * N + n] = t
        for i in range(m):
            n = od[i]
            depth_order[base + i] = tix[c * N + n]
            for y in range(box[c, n, 1], box[c, n, 3] + 1):
                row_cnt[c * H + y + 1] += 1
    for r in range(C * H):
        row_cnt[r + 1] += row_cnt[r]
    row_off = row_cnt
    E = row_off[C * H]
    row_surf = np.empty(E, dtype=np.int64)
    for c in prange(C):
        fill = row_off[c * H : (c + 1) * H].copy()
        for i in range(cnt[c], cnt[c + 1]):
            t = depth_order[i]
            cn = tab_cn[t]
            n = cn - c * N
            for y in range(box[c, n, 1], box[c, n, 3] + 1):
                row_surf[fill[y]] = t
                fill[y] += 1
    sbase = np.empty(S + 1, dtype=np.int64)
    sbase[0] = 0
    for t in range(S):
        cn = tab_cn[t]
        c = cn // N
        n = cn - c * N
        rows = box[c, n, 3] // band - box[c, n, 1] // band + 1
        sbase[t + 1] = sbase[t] + (rows if box[c, n, 3] >= box[c, n, 1] else 0)
    return tix, row_off, row_surf, tab_cn, sbase


@njit(**_KW, parallel=True)
def _table(geo, opa, col, tab_cn, N, n_threads, f):
    """The visible surfels' features (see the module's column layout) in table order."""
    S = tab_cn.shape[0]
    D = col.shape[2]
    per_cam = col.shape[0] > 1
    for t in prange(S):
        c = tab_cn[t] // N
        n = tab_cn[t] - c * N
        a0, a1, a2 = geo[c, n, _G_C0], geo[c, n, _G_C0 + 1], geo[c, n, _G_C0 + 2]
        b0, b1, b2 = geo[c, n, _G_C1], geo[c, n, _G_C1 + 1], geo[c, n, _G_C1 + 2]
        zc = geo[c, n, _G_Z]
        e0, e1, e2 = geo[c, n, _G_MX] * zc, geo[c, n, _G_MY] * zc, zc
        # J rows: c1 × centre, centre × c0, c0 × c1.
        f[t, 0] = b1 * e2 - b2 * e1
        f[t, 1] = b2 * e0 - b0 * e2
        f[t, 2] = b0 * e1 - b1 * e0
        f[t, 3] = e1 * a2 - e2 * a1
        f[t, 4] = e2 * a0 - e0 * a2
        f[t, 5] = e0 * a1 - e1 * a0
        f[t, 6] = a1 * b2 - a2 * b1
        f[t, 7] = a2 * b0 - a0 * b2
        f[t, 8] = a0 * b1 - a1 * b0
        f[t, _DET] = a0 * f[t, 0] + a1 * f[t, 1] + a2 * f[t, 2]
        f[t, _MX] = geo[c, n, _G_MX]
        f[t, _MY] = geo[c, n, _G_MY]
        f[t, _Z] = zc
        o = opa[n]
        f[t, _OPA] = o
        f[t, _NRM] = geo[c, n, _G_N]
        f[t, _NRM + 1] = geo[c, n, _G_N + 1]
        f[t, _NRM + 2] = geo[c, n, _G_N + 2]
        # Support radius² for the spans, slightly widened: min(9, 2 ln(255·o)).
        r2 = min(2.0 * np.log(255.0 * o), CUTOFF * CUTOFF) * (1 + 1e-6) + 1e-6
        f[t, _R2] = r2
        f[t, _A] = f[t, 0] * f[t, 0] + f[t, 3] * f[t, 3] - r2 * f[t, 6] * f[t, 6]
        for i in range(3):
            f[t, _C0 + i] = geo[c, n, _G_C0 + i]
            f[t, _C1 + i] = geo[c, n, _G_C1 + i]
        cc = c if per_cam else 0
        for k in range(D):
            f[t, _COL + k] = col[cc, n, k]


# -- compositing ---------------------------------------------------------------------------
@njit(**_KW, inline="always")
def _span(f, s, y, bx0, bx1, low_pass):
    """Inclusive pixel x-range on row ``y`` that can hold the support of a surfel with
    row ``s`` of the feature table ``f`` and box columns [bx0, bx1] (x1 < x0 when empty).

    The 3D support ``ρ3d ≤ r²`` is ``A x² + 2 B x + Cq ≤ 0`` with ``q = J·(x, y, 1)``; its
    root interval is padded for rounding and joined with the low-pass disk; where the
    conic is not an interval (``A ≤ 0``) the whole box is kept.
    """
    A = f[s, _A]
    if not A > 0.0:
        return bx0, bx1
    r2 = f[s, _R2]
    q0 = f[s, 1] * y + f[s, 2]
    q1 = f[s, 4] * y + f[s, 5]
    q2 = f[s, 7] * y + f[s, 8]
    B = f[s, 0] * q0 + f[s, 3] * q1 - r2 * f[s, 6] * q2
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
        dy = f[s, _MY] - y
        h2 = r2 * low_pass * low_pass - dy * dy
        if h2 >= 0.0:
            h = np.sqrt(h2) + 1e-6
            lo = min(lo, f[s, _MX] - h)
            hi = max(hi, f[s, _MX] + h)
    if lo > hi:
        return 0, -1
    return max(int(np.ceil(max(lo, bx0 - 1.0))), bx0), min(int(np.floor(min(hi, bx1 + 1.0))), bx1)


@njit(**_KW, parallel=True)
def _forward(
    f, row_off, row_surf, tab_box, C, W, H, D, near, far, inv_lp2, low_pass, r2max, a_min,
    a_max, t_min, has_bg, bg_out, V, n_threads, band, span, sv, six, o_col, o_alpha, o_de,
    o_da, o_dm, o_nc, o_nw, o_dist, pairs,
):  # fmt: skip
    """Front-to-back compositing per band of rows, bands interleaved over the threads.

    Each row walks its surfels in depth order, each over its span (written to ``span``),
    so every pixel sees its surfels front to back; at the row's end its outputs are
    finished: ``o_col`` Σw·colour (+ (1 − alpha)·background when ``has_bg``; ``bg_out``
    holds ones, then the backgrounds, in the outputs' dtype), ``o_alpha`` Σw, ``o_de``
    Σw·z / Σw, ``o_da`` Σw·z, ``o_dm`` median depth, ``o_nc`` Σw·n, ``o_nw`` the same · R,
    ``o_dist`` distortion. Kept for the backward pass: ``sv`` (C, H, W, 6) = final
    transmittance, Σw, Σw·z, Σw·m, Σw·m², Σw·z / Σw (0 where Σw = 0) and ``six`` (C, H, W, 2) = end of the pixel's
    blended run (entry index, exclusive) and its median entry (−1 if none).
    """
    n_bpc = (H + band - 1) // band
    n_bands = C * n_bpc
    mscale = far / (far - near)
    use_lp = low_pass > 0.0
    NA = D + 6
    for th in prange(n_threads):
        acc = np.empty((W, NA))
        st = np.empty((W, 3))
        med = np.empty(W)
        done = np.empty(W, dtype=np.bool_)
        end = np.empty(W, dtype=np.int64)
        mid = np.empty(W, dtype=np.int64)
        cnt = 0
        for b in range(th, n_bands, n_threads):
            c = b // n_bpc
            ya = (b % n_bpc) * band
            for py in range(ya, min(ya + band, H)):
                r = c * H + py
                y = float(py)
                e0 = row_off[r]
                for px in range(W):
                    for k in range(NA):
                        acc[px, k] = 0.0
                    st[px, 0] = 1.0
                    st[px, 1] = 0.0
                    st[px, 2] = 0.0
                    med[px] = 0.0
                    done[px] = False
                    end[px] = e0
                    mid[px] = -1
                for e in range(e0, row_off[r + 1]):
                    s = row_surf[e]
                    x0, x1 = _span(f, s, y, tab_box[s, 0], tab_box[s, 2], low_pass)
                    span[e, 0] = x0
                    span[e, 1] = x1
                    if x1 < x0:
                        continue
                    cnt += x1 - x0 + 1
                    j0, j3, j6 = f[s, 0], f[s, 3], f[s, 6]
                    b0 = f[s, 1] * y + f[s, 2]
                    b1 = f[s, 4] * y + f[s, 5]
                    b2 = f[s, 7] * y + f[s, 8]
                    det, mx, zc, opa = f[s, _DET], f[s, _MX], f[s, _Z], f[s, _OPA]
                    dy2 = (f[s, _MY] - y) * (f[s, _MY] - y) * inv_lp2
                    nx, ny, nz = f[s, _NRM], f[s, _NRM + 1], f[s, _NRM + 2]
                    # 1/depth = q2/det (or 1/z): no division per pair for m.
                    idet = 1.0 / det if det != 0.0 else 0.0
                    izc = 1.0 / zc
                    for px in range(x0, x1 + 1):
                        if done[px]:
                            continue
                        x = float(px)
                        q2 = j6 * x + b2
                        if q2 == 0.0:
                            continue
                        inv = 1.0 / q2
                        u = (j0 * x + b0) * inv
                        v = (j3 * x + b1) * inv
                        rho = u * u + v * v
                        depth = det * inv
                        rd = q2 * idet
                        if use_lp:
                            dx = mx - x
                            rho2 = dx * dx * inv_lp2 + dy2
                            if not rho <= rho2:
                                rho = rho2
                                depth = zc
                                rd = izc
                        if rho > r2max or depth < near:
                            continue
                        alpha = min(opa * _exp_neg(-0.5 * rho), a_max)
                        if alpha < a_min:
                            continue
                        T = st[px, 0]
                        after = T * (1.0 - alpha)
                        if after < t_min:
                            done[px] = True
                            continue
                        w = alpha * T
                        m = mscale * (1.0 - near * rd)
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
                            mid[px] = e
                            med[px] = depth
                        st[px, 0] = after
                        end[px] = e + 1
                # Finish the row.
                for px in range(W):
                    a = acc[px, D]
                    for k in range(D):
                        o_col[c, py, px, k] = acc[px, k]
                    o_alpha[c, py, px, 0] = a
                    if has_bg:
                        # over_background in the outputs' dtype: the same bits as the
                        # formula applied to the bare render.
                        for k in range(D):
                            o_col[c, py, px, k] = (
                                o_col[c, py, px, k]
                                + (bg_out[0, k] - o_alpha[c, py, px, 0]) * bg_out[1 + c, k]
                            )
                    de = acc[px, D + 1] / a if a > 0 else 0.0
                    o_de[c, py, px, 0] = de
                    o_da[c, py, px, 0] = acc[px, D + 1]
                    o_dm[c, py, px, 0] = med[px]
                    for i in range(3):
                        o_nc[c, py, px, i] = acc[px, D + 2 + i]
                        o_nw[c, py, px, i] = (
                            acc[px, D + 2] * V[c, 0, i]
                            + acc[px, D + 3] * V[c, 1, i]
                            + acc[px, D + 4] * V[c, 2, i]
                        )
                    o_dist[c, py, px, 0] = acc[px, D + 5]
                    sv[c, py, px, 0] = st[px, 0]
                    sv[c, py, px, 1] = a
                    sv[c, py, px, 2] = acc[px, D + 1]
                    sv[c, py, px, 3] = st[px, 1]
                    sv[c, py, px, 4] = st[px, 2]
                    sv[c, py, px, 5] = de
                    six[c, py, px, 0] = end[px]
                    six[c, py, px, 1] = mid[px]
        pairs[th] = cnt


@njit(**_KW, inline="always")
def _expected_depth(sv, c, y, x):
    return sv[c, y, x, 5]


@njit(**_KW, inline="always")
def _ray(Kinv, c, x, y, i):
    return Kinv[c, i, 0] * x + Kinv[c, i, 1] * y + Kinv[c, i, 2]


@njit(**_KW, inline="always")
def _normal_diffs(sv, Kinv, c, y, x):
    """Central differences ``(P↓ − P↑, P→ − P←)`` of the back-projected expected depth."""
    du = _expected_depth(sv, c, y - 1, x)
    dd = _expected_depth(sv, c, y + 1, x)
    dl = _expected_depth(sv, c, y, x - 1)
    dr = _expected_depth(sv, c, y, x + 1)
    fx, fy = float(x), float(y)
    dy0 = dd * _ray(Kinv, c, fx, fy + 1, 0) - du * _ray(Kinv, c, fx, fy - 1, 0)
    dy1 = dd * _ray(Kinv, c, fx, fy + 1, 1) - du * _ray(Kinv, c, fx, fy - 1, 1)
    dy2 = dd * _ray(Kinv, c, fx, fy + 1, 2) - du * _ray(Kinv, c, fx, fy - 1, 2)
    dx0 = dr * _ray(Kinv, c, fx + 1, fy, 0) - dl * _ray(Kinv, c, fx - 1, fy, 0)
    dx1 = dr * _ray(Kinv, c, fx + 1, fy, 1) - dl * _ray(Kinv, c, fx - 1, fy, 1)
    dx2 = dr * _ray(Kinv, c, fx + 1, fy, 2) - dl * _ray(Kinv, c, fx - 1, fy, 2)
    return dy0, dy1, dy2, dx0, dx1, dx2


@njit(**_KW, parallel=True)
def _depth_normals_out(sv, Kinv, V, eps, n_threads, o_n, o_nw):
    """Depth normals (camera and world frame) of the expected depth, as
    :func:`surfphase.render.rasterize.depth_normals` (zero on the one-pixel border)."""
    C, H, W = sv.shape[0], sv.shape[1], sv.shape[2]
    for r in prange(C * H):
        c = r // H
        y = r % H
        for x in range(W):
            if y < 1 or y > H - 2 or x < 1 or x > W - 2:
                for i in range(3):
                    o_n[c, y, x, i] = 0.0
                    o_nw[c, y, x, i] = 0.0
                continue
            dy0, dy1, dy2, dx0, dx1, dx2 = _normal_diffs(sv, Kinv, c, y, x)
            n0 = dy1 * dx2 - dy2 * dx1
            n1 = dy2 * dx0 - dy0 * dx2
            n2 = dy0 * dx1 - dy1 * dx0
            norm = max(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), eps)
            n0 /= norm
            n1 /= norm
            n2 /= norm
            o_n[c, y, x, 0] = n0
            o_n[c, y, x, 1] = n1
            o_n[c, y, x, 2] = n2
            for i in range(3):
                o_nw[c, y, x, i] = n0 * V[c, 0, i] + n1 * V[c, 1, i] + n2 * V[c, 2, i]


@njit(**_KW, parallel=True)
def _depth_normals_grad(sv, Kinv, V, eps, g_n, f_n, g_nw, f_nw, n_threads, g_dy, g_dx, g_de):
    """Gradient of the depth normals (both frames) w.r.t. the expected depth, into
    ``g_de`` (C, H, W): each interior pixel's gradients of its two differences, then each
    pixel gathers its share from its four neighbours (no two threads write one number)."""
    C, H, W = sv.shape[0], sv.shape[1], sv.shape[2]
    for r in prange(C * H):
        c = r // H
        y = r % H
        if y < 1 or y > H - 2:
            continue
        for x in range(1, W - 1):
            dy0, dy1, dy2, dx0, dx1, dx2 = _normal_diffs(sv, Kinv, c, y, x)
            n0 = dy1 * dx2 - dy2 * dx1
            n1 = dy2 * dx0 - dy0 * dx2
            n2 = dy0 * dx1 - dy1 * dx0
            length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            norm = max(length, eps)
            g = np.empty(3)
            for i in range(3):
                g[i] = g_n[c * f_n, y * f_n, x * f_n, i] + (
                    g_nw[c * f_nw, y * f_nw, x * f_nw, 0] * V[c, i, 0]
                    + g_nw[c * f_nw, y * f_nw, x * f_nw, 1] * V[c, i, 1]
                    + g_nw[c * f_nw, y * f_nw, x * f_nw, 2] * V[c, i, 2]
                )
            g0, g1, g2 = g[0], g[1], g[2]
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
        fy = float(y)
        for x in range(W):
            fx = float(x)
            acc = 0.0
            for i in range(3):
                gp = 0.0
                if y >= 2:  # pixel (y − 1, x) is interior only if 1 ≤ y − 1 ≤ H − 2
                    if 1 <= x <= W - 2:
                        gp += g_dy[c, y - 1, x, i]
                if y + 1 <= H - 2:
                    if 1 <= x <= W - 2:
                        gp -= g_dy[c, y + 1, x, i]
                if x >= 2 and 1 <= y <= H - 2:
                    gp += g_dx[c, y, x - 1, i]
                if x + 1 <= W - 2 and 1 <= y <= H - 2:
                    gp -= g_dx[c, y, x + 1, i]
                acc += gp * _ray(Kinv, c, fx, fy, i)
            a = sv[c, y, x, 1]
            g_de[c, y, x] = acc if a > 0 else 0.0


@njit(**_KW, parallel=True)
def _backward(
    f, row_off, row_surf, span, tab_box, sbase, C, W, H, D, near, far, inv_lp2, use_lp,
    r2max, a_min, a_max, bg, V, sv, six, g_de_n, g_col, g_alpha, g_de, g_da, g_dm, g_nc,
    g_nw, g_dist, flags, n_threads, band, gslot, row_bg,
):  # fmt: skip
    """Back-to-front gradients, in the forward pass's bands.

    Per row, the outputs' gradients are first turned into those of the accumulations
    (background, expected depth with the depth normals' share ``g_de_n``, world
    normals); then the row walks its surfels in reverse depth order, a pixel's
    transmittance before a pair recovered as ``T / (1 − α)`` from the final one, and
    ``suffix`` carrying Σ_{later k} (∂L/∂w_k)·w_k for the transmittance's share of ∂L/∂α.
    Each (band, surfel) sums its pairs' gradients of the features into its slot of
    ``gslot``, rows in order (the first row of the band that meets the surfel writes,
    later ones add); ``row_bg`` (C·H, D) gets each row's gradient of the background.
    """
    n_bpc = (H + band - 1) // band
    n_bands = C * n_bpc
    mscale = far / (far - near)
    NA = D + 6
    fc, fa, fe, fz, fm, fn, fw, fd = (
        flags[0], flags[1], flags[2], flags[3], flags[4], flags[5], flags[6], flags[9]
    )  # fmt: skip
    for th in prange(n_threads):
        T = np.empty(W)
        suffix = np.empty(W)
        gr = np.empty((W, NA))
        gmed = np.empty(W)
        for b in range(th, n_bands, n_threads):
            c = b // n_bpc
            ya = (b % n_bpc) * band
            for py in range(ya, min(ya + band, H)):
                r = c * H + py
                y = float(py)
                for k in range(D):
                    row_bg[r, k] = 0.0
                for px in range(W):
                    T[px] = sv[c, py, px, 0]
                    suffix[px] = 0.0
                    a = sv[c, py, px, 1]
                    ga = g_alpha[c * fa, py * fa, px * fa, 0]
                    for k in range(D):
                        gck = g_col[c * fc, py * fc, px * fc, k]
                        gr[px, k] = gck
                        ga -= gck * bg[c, k]
                        row_bg[r, k] += gck * (1.0 - a)
                    gz = g_da[c * fz, py * fz, px * fz, 0]
                    if a > 0:
                        gde = g_de[c * fe, py * fe, px * fe, 0] + g_de_n[c, py, px]
                        gz += gde / a
                        ga -= gde * sv[c, py, px, 2] / (a * a)
                    gr[px, D] = ga
                    gr[px, D + 1] = gz
                    for i in range(3):
                        gr[px, D + 2 + i] = g_nc[c * fn, py * fn, px * fn, i] + (
                            g_nw[c * fw, py * fw, px * fw, 0] * V[c, i, 0]
                            + g_nw[c * fw, py * fw, px * fw, 1] * V[c, i, 1]
                            + g_nw[c * fw, py * fw, px * fw, 2] * V[c, i, 2]
                        )
                    gr[px, D + 5] = g_dist[c * fd, py * fd, px * fd, 0]
                    gmed[px] = g_dm[c * fm, py * fm, px * fm, 0]
                for e in range(row_off[r + 1] - 1, row_off[r] - 1, -1):
                    s = row_surf[e]
                    slot = sbase[s] + py // band - tab_box[s, 1] // band
                    first = py == max(tab_box[s, 1], ya)
                    if first:
                        for k in range(_GCOL + D):
                            gslot[slot, k] = 0.0
                    x0, x1 = span[e, 0], span[e, 1]
                    if x1 < x0:
                        continue
                    j0, j3, j6 = f[s, 0], f[s, 3], f[s, 6]
                    b0 = f[s, 1] * y + f[s, 2]
                    b1 = f[s, 4] * y + f[s, 5]
                    b2 = f[s, 7] * y + f[s, 8]
                    det, mx, my, zc, opa = f[s, _DET], f[s, _MX], f[s, _MY], f[s, _Z], f[s, _OPA]
                    dy2 = (my - y) * (my - y) * inv_lp2
                    nx, ny, nz = f[s, _NRM], f[s, _NRM + 1], f[s, _NRM + 2]
                    gq0x = gq0 = gq1x = gq1 = gq2x = gq2 = 0.0
                    g_det = g_mx = g_my = g_zc = g_opa = gn0 = gn1 = gn2 = 0.0
                    idet = 1.0 / det if det != 0.0 else 0.0
                    izc = 1.0 / zc
                    for px in range(x0, x1 + 1):
                        if e >= six[c, py, px, 0]:
                            continue
                        x = float(px)
                        q2 = j6 * x + b2
                        if q2 == 0.0:
                            continue
                        inv = 1.0 / q2
                        u = (j0 * x + b0) * inv
                        v = (j3 * x + b1) * inv
                        rho = u * u + v * v
                        depth3 = det * inv
                        depth = depth3
                        rd = q2 * idet
                        use3 = True
                        if use_lp:
                            dx = mx - x
                            rho2 = dx * dx * inv_lp2 + dy2
                            if not rho <= rho2:
                                use3 = False
                                rd = izc
                                rho = rho2
                                depth = zc
                        if rho > r2max or depth < near:
                            continue
                        gauss = _exp_neg(-0.5 * rho)
                        raw = opa * gauss
                        alpha = min(raw, a_max)
                        if alpha < a_min:
                            continue
                        one_a = 1.0 / (1.0 - alpha)
                        Ti = T[px] * one_a  # transmittance before this pair
                        T[px] = Ti
                        w = alpha * Ti
                        m = mscale * (1.0 - near * rd)
                        sw = sv[c, py, px, 1]
                        m1 = sv[c, py, px, 3]
                        m2 = sv[c, py, px, 4]
                        g_z = gr[px, D + 1]
                        g_d = gr[px, D + 5]
                        # dL/dw with the other pairs' weights fixed.
                        g_w = gr[px, D] + g_z * depth + g_d * (m * m * sw + m2 - 2.0 * m * m1)
                        g_w += gr[px, D + 2] * nx + gr[px, D + 3] * ny + gr[px, D + 4] * nz
                        for k in range(D):
                            g_w += gr[px, k] * f[s, _COL + k]
                            gslot[slot, _GCOL + k] += gr[px, k] * w
                        gn0 += gr[px, D + 2] * w
                        gn1 += gr[px, D + 3] * w
                        gn2 += gr[px, D + 4] * w
                        g_alpha_ = Ti * g_w - suffix[px] * one_a
                        suffix[px] += g_w * w
                        dm = mscale * near * rd * rd
                        g_depth = g_z * w + g_d * 2.0 * w * (m * sw - m1) * dm
                        if e == six[c, py, px, 1]:
                            g_depth += gmed[px]
                        # alpha = min(o·exp(−ρ/2), 0.99): no gradient past the cap.
                        g_raw = g_alpha_ if raw <= a_max else 0.0
                        g_opa += g_raw * gauss
                        g_rho = -0.5 * raw * g_raw
                        if use3:
                            g_u = 2.0 * u * g_rho
                            g_v = 2.0 * v * g_rho
                            g_q0 = g_u * inv
                            g_q1 = g_v * inv
                            g_q2 = -(g_u * u + g_v * v) * inv - g_depth * depth3 * inv
                            g_det += g_depth * inv
                            gq0x += g_q0 * x
                            gq0 += g_q0
                            gq1x += g_q1 * x
                            gq1 += g_q1
                            gq2x += g_q2 * x
                            gq2 += g_q2
                        else:
                            g_mx += g_rho * 2.0 * (mx - x) * inv_lp2
                            g_my += g_rho * 2.0 * (my - y) * inv_lp2
                            g_zc += g_depth
                    gslot[slot, 0] += gq0x
                    gslot[slot, 1] += gq0 * y
                    gslot[slot, 2] += gq0
                    gslot[slot, 3] += gq1x
                    gslot[slot, 4] += gq1 * y
                    gslot[slot, 5] += gq1
                    gslot[slot, 6] += gq2x
                    gslot[slot, 7] += gq2 * y
                    gslot[slot, 8] += gq2
                    gslot[slot, _DET] += g_det
                    gslot[slot, _MX] += g_mx
                    gslot[slot, _MY] += g_my
                    gslot[slot, _Z] += g_zc
                    gslot[slot, _OPA] += g_opa
                    gslot[slot, _NRM] += gn0
                    gslot[slot, _NRM + 1] += gn1
                    gslot[slot, _NRM + 2] += gn2


@njit(**_KW, parallel=True)
def _reduce(gslot, sbase, tab_cn, tix, f, D, n_threads, g_tab, g_geo, g_m2d, g_opa, g_col):
    """Per surfel: its slots summed in band order per camera, then the chain rule of the
    adjugate ``J``, ``det`` and the centre ``(μx z, μy z, z)`` → gradients of ``geo``
    (tangent columns, depth, normal) and of ``means2d``; opacity and colour summed over
    the cameras in camera order. First in table order (slots and features are read in
    memory order) into ``g_tab`` (S, 13 + D): g_c0, g_c1, g_z, g_n, g_means2d, g_opacity,
    g_colour; then per surfel, gathering its cameras' rows."""
    S = tab_cn.shape[0]
    C = g_geo.shape[0]
    N = g_geo.shape[1]
    per_cam = g_col.shape[0] > 1
    for th in prange(n_threads):
        gs = np.empty(_GCOL + D)
        for t in range(th * S // n_threads, (th + 1) * S // n_threads):
            for k in range(_GCOL + D):
                gs[k] = 0.0
            for j in range(sbase[t], sbase[t + 1]):
                for k in range(_GCOL + D):
                    gs[k] += gslot[j, k]
            a0, a1, a2 = f[t, _C0], f[t, _C0 + 1], f[t, _C0 + 2]
            b0, b1, b2 = f[t, _C1], f[t, _C1 + 1], f[t, _C1 + 2]
            zc, mx, my = f[t, _Z], f[t, _MX], f[t, _MY]
            e0, e1, e2 = mx * zc, my * zc, zc
            gd = gs[_DET]
            # det = c0 · J0 with J0 = c1 × centre: gJ0 += gd·c0, g_c0 += gd·J0.
            p0, p1, p2 = gs[0] + gd * a0, gs[1] + gd * a1, gs[2] + gd * a2
            q0, q1, q2 = gs[3], gs[4], gs[5]
            r0, r1, r2 = gs[6], gs[7], gs[8]
            # J0 = c1 × e: g_c1 += e × gJ0, g_e += gJ0 × c1.
            # J1 = e × c0: g_e += c0 × gJ1, g_c0 += gJ1 × e.
            # J2 = c0 × c1: g_c0 += c1 × gJ2, g_c1 += gJ2 × c0.
            g_tab[t, 0] = gd * f[t, 0] + (q1 * e2 - q2 * e1) + (b1 * r2 - b2 * r1)
            g_tab[t, 1] = gd * f[t, 1] + (q2 * e0 - q0 * e2) + (b2 * r0 - b0 * r2)
            g_tab[t, 2] = gd * f[t, 2] + (q0 * e1 - q1 * e0) + (b0 * r1 - b1 * r0)
            g_tab[t, 3] = (e1 * p2 - e2 * p1) + (r1 * a2 - r2 * a1)
            g_tab[t, 4] = (e2 * p0 - e0 * p2) + (r2 * a0 - r0 * a2)
            g_tab[t, 5] = (e0 * p1 - e1 * p0) + (r0 * a1 - r1 * a0)
            ge0 = (p1 * b2 - p2 * b1) + (a1 * q2 - a2 * q1)
            ge1 = (p2 * b0 - p0 * b2) + (a2 * q0 - a0 * q2)
            ge2 = (p0 * b1 - p1 * b0) + (a0 * q1 - a1 * q0)
            g_tab[t, 6] = gs[_Z] + ge0 * mx + ge1 * my + ge2
            g_tab[t, 7] = gs[_NRM]
            g_tab[t, 8] = gs[_NRM + 1]
            g_tab[t, 9] = gs[_NRM + 2]
            g_tab[t, 10] = gs[_MX] + ge0 * zc
            g_tab[t, 11] = gs[_MY] + ge1 * zc
            g_tab[t, 12] = gs[_OPA]
            for k in range(D):
                g_tab[t, 13 + k] = gs[_GCOL + k]
    for th in prange(n_threads):
        for n in range(th * N // n_threads, (th + 1) * N // n_threads):
            go = 0.0
            if not per_cam:
                for k in range(D):
                    g_col[0, n, k] = 0.0
            for c in range(C):
                t = tix[c * N + n]
                for k in range(_G_WIDTH):
                    g_geo[c, n, k] = 0.0
                if t < 0:
                    g_m2d[c, n, 0] = 0.0
                    g_m2d[c, n, 1] = 0.0
                    if per_cam:
                        for k in range(D):
                            g_col[c, n, k] = 0.0
                    continue
                for k in range(10):
                    g_geo[c, n, k] = g_tab[t, k]
                g_m2d[c, n, 0] = g_tab[t, 10]
                g_m2d[c, n, 1] = g_tab[t, 11]
                go += g_tab[t, 12]
                for k in range(D):
                    if per_cam:
                        g_col[c, n, k] = g_tab[t, 13 + k]
                    else:
                        g_col[0, n, k] += g_tab[t, 13 + k]
            g_opa[n] = go


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


def compile_kernels() -> None:
    """Compile every kernel of this backend, or load them from numba's on-disk cache:
    one small render forward and backward for float32 and for float64 inputs (about
    30 s once, under a second when cached), then the fit's fused photometric loss
    (:func:`surfphase.fit.fused_losses.compile_kernels`). ``make test`` and ``make demo``
    call it first, so that the test workers and the workflow's parallel jobs load the
    cache instead of each compiling the same kernels side by side."""
    from surfphase.fit import fused_losses
    from surfphase.render.rasterize import rasterize_surfels
    from surfphase.render.scenes import sphere_scene

    for dtype in (torch.float32, torch.float64):
        scene = sphere_scene(60, 2, 32, seed=0, dtype=dtype)
        for k in ("means", "quats", "scales", "opacities", "colors"):
            scene[k].requires_grad_()
        colors, alphas, meta = rasterize_surfels(**scene, backend="fused")
        loss = colors.sum() + alphas.sum()
        for k in ("depth_expected", "depth_median", "normals_world", "normals_from_depth"):
            loss = loss + meta[k].sum()
        loss = loss + meta["distortion"].sum()
        loss.backward()
    fused_losses.compile_kernels()
