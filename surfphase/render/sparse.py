"""Sparse pure-PyTorch backend of :func:`surfphase.render.rasterize_surfels`.

Instead of every pixel against every surfel, only the (pixel, surfel) pairs that can
contribute are generated: for each visible surfel and each row of its screen box, the
x-range where ``ρ ≤ min(9, 2 ln(255·o))`` (beyond it α < 1/255) is solved in closed
form (a conic and a disk), and pairs are laid out with ``repeat_interleave`` /
``arange`` arithmetic. Surfels are enumerated in (camera, depth) order, so one stable
int64 sort by pixel index gives (pixel, depth) order. Blending uses segmented prefix
sums (log-transmittance, float64) and ``index_add`` scatters; the exact per-pair tests
(support, near plane, 1/255, termination) are masks. Images are split into bands of
rows holding at most ``max_pairs_per_chunk`` candidate pairs; with several bands each
is checkpointed (recomputed in backward), so memory stays bounded in backward too.

``_render_band`` (about 100 lines of code) is kept whole: it is one band's
differentiable pass (pairs, weights, compositing, accumulation), the unit that is
checkpointed and recomputed in backward, so its intermediate tensors live and are freed
together.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from surfphase.render.projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    CUTOFF,
    T_MIN,
    bounding_boxes,
    project_surfels,
)

# Column layout of the packed per-(camera, surfel) feature table gathered per pair.
_J, _DET, _MX, _MY, _Z, _OPA, _NRM, _COL = 0, 9, 10, 11, 12, 13, 14, 17


def rasterize_sparse(
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
) -> dict[str, Tensor]:
    """Render; returns raw accumulations (see :func:`surfphase.render.rasterize_surfels`).

    Output dict: ``n_pairs`` (int) candidate (pixel, surfel) pairs processed;
    ``accum`` (C, H, W, D + 6) = Σw·colour (D), Σw, Σw·z, Σw·n_cam (3), distortion;
    ``depth_median`` (C, H, W, 1); per surfel ``means2d`` (C, N, 2), ``radii`` and
    ``visible`` (C, N).
    """
    C, N = viewmats.shape[0], means.shape[0]
    D = colors.shape[-1]
    prep = prepare_surfels(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, low_pass
    )
    proj, visible, radii, vis_idx, vbox = (
        prep[k] for k in ("proj", "visible", "radii", "vis_idx", "vbox")
    )
    # Feature-major: per-pair values are gathered column by column (1-D gathers and
    # 1-D index_add backwards are much faster than row gathers plus transposes).
    feats = prep["feats"].t().contiguous()
    with torch.no_grad():
        # Support test per (surfel, row), in float64: ρ ≤ r² with r² = min(9, 2 ln(255·o))
        # (beyond it α < 1/255), slightly widened; the exact per-pair test runs later.
        f64 = feats.detach().index_select(1, vis_idx).to(torch.float64)
        r2 = torch.clamp(2 * torch.log(255.0 * f64[_OPA]), max=CUTOFF * CUTOFF)
        span = _span_coefficients(f64, r2 * (1 + 1e-6) + 1e-6, low_pass)

    bands = _plan_bands(vbox, height, width, max_pairs_per_chunk)
    inv_lp2 = 1.0 / (low_pass * low_pass) if low_pass > 0 else 0.0
    consts = (C, N, width, D, near, far, inv_lp2, low_pass)
    outs, meds, n_pairs = [], [], []
    for y0, y1 in bands:
        if len(bands) > 1 and feats.requires_grad:
            acc, med = checkpoint(
                _render_band,
                feats,
                vis_idx,
                vbox,
                span,
                y0,
                y1,
                consts,
                n_pairs,
                use_reentrant=False,
            )
        else:
            acc, med = _render_band(feats, vis_idx, vbox, span, y0, y1, consts, n_pairs)
        outs.append(acc)
        meds.append(med)
    # Read now: checkpointed bands append again when they are recomputed in backward.
    total_pairs = sum(n_pairs)
    return {
        "n_pairs": total_pairs,
        "accum": torch.cat(outs, dim=1),
        "depth_median": torch.cat(meds, dim=1),
        "means2d": proj["means2d"],
        "radii": radii,
        "visible": visible,
    }


def prepare_surfels(
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
) -> dict:
    """Projection and culling shared by the CPU backends (differentiable where it matters).

    Returns a dict: ``proj`` (:func:`project_surfels`'s dict); ``feats`` (C·N, 17 + D)
    the packed per-(camera, surfel) features, row ``c·N + n``, columns
    ``J (9), det, μx, μy, z, opacity, n_cam (3), colour (D)`` (differentiable);
    ``visible`` (C, N) bool, ``radii`` (C, N) int32; ``vis_idx`` (S,) int64 the visible
    rows of ``feats`` in (camera, centre depth) order, stable on ties; ``vbox`` (S, 4)
    their integer pixel boxes ``(x0, y0, x1, y1)``, inclusive, clipped to the image.
    """
    C, N = viewmats.shape[0], means.shape[0]
    D = colors.shape[-1]
    proj = project_surfels(means, quats, scales, viewmats, Ks)
    z = proj["depth"]
    box, half = bounding_boxes(proj["M"], proj["means2d"].detach(), low_pass, width, height)
    with torch.no_grad():
        visible = (
            (z >= near)
            & (z <= far)
            & (box[..., 0] <= box[..., 2])
            & (box[..., 1] <= box[..., 3])
            & (opacities[None, :] * 1.0 >= ALPHA_MIN)
        )
        radii = torch.where(visible, half.amax(-1).ceil(), 0).to(torch.int32)
        # Every camera's surfels in order of depth, stable on ties; then the visible ones.
        order = torch.argsort(z.detach(), dim=1, stable=True)
        rows = order + N * torch.arange(C, device=z.device)[:, None]
        vis_idx = rows.reshape(-1)[visible.gather(1, order).reshape(-1)]

    feats = torch.cat(
        [
            proj["J"].reshape(C, N, 9),
            proj["det"][..., None],
            proj["means2d"],
            z[..., None],
            opacities[None, :, None].expand(C, N, 1),
            proj["normals_camera"],
            colors if colors.dim() == 3 else colors[None].expand(C, N, D),
        ],
        dim=-1,
    ).reshape(C * N, 17 + D)

    vbox = box.reshape(-1, 4)[vis_idx]
    return {
        "proj": proj,
        "feats": feats,
        "visible": visible,
        "radii": radii,
        "vis_idx": vis_idx,
        "vbox": vbox,
    }


def _plan_bands(vbox: Tensor, height: int, width: int, max_pairs: int) -> list[tuple[int, int]]:
    """Split rows [0, H) into bands of at most ``max_pairs`` candidate pairs (≥ 1 row)."""
    if vbox.shape[0] == 0:
        return [(0, height)]
    w = (vbox[:, 2] - vbox[:, 0] + 1).to(torch.float64)
    diff = torch.zeros(height + 1, dtype=torch.float64, device=vbox.device)
    diff.index_add_(0, vbox[:, 1], w)
    diff.index_add_(0, vbox[:, 3] + 1, -w)
    per_row = torch.cumsum(diff[:-1], 0).cpu().tolist()
    if sum(per_row) <= max_pairs:
        return [(0, height)]
    bands, start, acc = [], 0, 0.0
    for y, n in enumerate(per_row):
        if y > start and acc + n > max_pairs:
            bands.append((start, y))
            start, acc = y, 0.0
        acc += n
    bands.append((start, height))
    return bands


def _segmented_exclusive_cumsum(x: Tensor, seg_start: Tensor) -> Tensor:
    """Exclusive prefix sum of ``x`` (P,) restarting at each segment (float64 inside).

    ``seg_start`` (P,) is the index of the first element of each element's segment.
    """
    x64 = x.to(torch.float64)
    incl = torch.cumsum(x64, 0)
    excl = incl - x64
    # index_select: its backward (index_add_) sums in a fixed order; ``excl[seg_start]``
    # would accumulate through index_put_, which is not bit-for-bit on threaded CPUs.
    return (excl - excl.index_select(0, seg_start)).to(x.dtype)


def _render_band(
    feats: Tensor,
    vis_idx: Tensor,
    vbox: Tensor,
    span: list[Tensor],
    y0: int,
    y1: int,
    consts: tuple,
    n_pairs: list[int],
) -> tuple[Tensor, Tensor]:
    """Composite rows [y0, y1) of every camera → ((C, y1−y0, W, D+6), (C, y1−y0, W, 1)).

    ``feats`` (17 + D, C·N) packed per-(camera, surfel) features; ``vis_idx`` (S,) the
    visible ones in (camera, depth) order, ``vbox`` (S, 4) their boxes, ``span`` nine (S,)
    float64 columns bounding each row's pixels (:func:`_span_coefficients`).
    The number of candidate pairs is appended to ``n_pairs``.
    """
    C, n_surf, W, D, near, far, inv_lp2, low_pass = consts
    use_lp = low_pass > 0
    dev, dt = feats.device, feats.dtype
    rows = y1 - y0
    n_pix = C * rows * W
    accum = torch.zeros(n_pix, D + 6, device=dev, dtype=dt)
    median = torch.zeros(n_pix, device=dev, dtype=dt)
    empty = (accum.reshape(C, rows, W, D + 6), median.reshape(C, rows, W, 1))

    # --- candidate pairs: per (surfel, row) the x-range of its support ----------------
    by0 = vbox[:, 1].clamp(min=y0)
    bh = (vbox[:, 3].clamp(max=y1 - 1) - by0 + 1).clamp(min=0)
    n_rows = int(bh.sum())
    if n_rows == 0:
        return empty
    row_owner = torch.repeat_interleave(
        torch.arange(bh.shape[0], device=dev), bh, output_size=n_rows
    )
    row_offs = torch.cumsum(bh, 0) - bh
    ry = by0.index_select(0, row_owner) + (
        torch.arange(n_rows, device=dev) - row_offs.index_select(0, row_owner)
    )
    lo, hi = _row_spans([c.index_select(0, row_owner) for c in span], ry.to(torch.float64))
    x0 = torch.maximum(
        torch.ceil(lo).nan_to_num(0, 0, 0).clamp(-1, W).long(),
        vbox[:, 0].index_select(0, row_owner),
    )
    x1 = torch.minimum(
        torch.floor(hi).nan_to_num(-1, -1, -1).clamp(-1, W).long(),
        vbox[:, 2].index_select(0, row_owner),
    )
    n_x = (x1 - x0 + 1).clamp(min=0)
    total = int(n_x.sum())
    n_pairs.append(total)
    if total == 0:
        return empty
    pair_row = torch.repeat_interleave(torch.arange(n_rows, device=dev), n_x, output_size=total)
    x_offs = torch.cumsum(n_x, 0) - n_x
    px = x0.index_select(0, pair_row) + (
        torch.arange(total, device=dev) - x_offs.index_select(0, pair_row)
    )
    py = ry.index_select(0, pair_row)
    surf = vis_idx.index_select(0, row_owner.index_select(0, pair_row))
    del pair_row, x_offs, row_owner, lo, hi
    cam = torch.div(surf, n_surf, rounding_mode="floor")
    pix = (cam * rows + (py - y0)) * W + px
    # Pairs were generated in (camera, depth) order, so a stable sort by pixel gives
    # (pixel, depth) order.
    pix, perm = torch.sort(pix, stable=True)
    surf, px, py = (t.index_select(0, perm) for t in (surf, px, py))
    P = pix.shape[0]
    new_seg = torch.ones(P, dtype=torch.bool, device=dev)
    new_seg[1:] = pix[1:] != pix[:-1]
    seg_id = torch.cumsum(new_seg, 0) - 1
    starts = torch.nonzero(new_seg).squeeze(1)
    seg_start = starts.index_select(0, seg_id)

    # --- differentiable compositing ----------------------------------------------------
    f = tuple(col.index_select(0, surf) for col in feats)
    alpha, depth, ok = _pair_alpha_depth(f, px.to(dt), py.to(dt), inv_lp2, use_lp, near)
    ok = ok & (alpha >= ALPHA_MIN)
    alpha = torch.where(ok, alpha, 0)
    depth = torch.where(ok, depth, 1)
    log_t = _segmented_exclusive_cumsum(torch.log1p(-alpha), seg_start)
    trans = torch.exp(log_t)  # transmittance before each pair
    with torch.no_grad():
        # Early termination, monotone within a pixel; skipped pairs have α = 0.
        alive = ok & (trans * (1 - alpha) >= T_MIN)
    w = alpha * trans * alive
    m = (far / (far - near)) * (1 - near / depth)
    wm = w * m
    m1 = _segmented_exclusive_cumsum(wm, seg_start)
    m2 = _segmented_exclusive_cumsum(wm * m, seg_start)
    distortion = (m * m * (1 - trans) + m2 - 2 * m * m1) * w
    vals = torch.stack(
        [
            *(w * fc for fc in f[_COL:]),
            w,
            w * depth,
            *(w * fc for fc in f[_NRM:_COL]),
            distortion,
        ],
        dim=1,
    )
    accum = accum.index_add(0, pix, vals)

    # Median depth: the last blended pair whose incoming transmittance is above 0.5.
    with torch.no_grad():
        last = torch.full((starts.shape[0],), -1, dtype=torch.long, device=dev)
        before_half = alive & (trans > 0.5)
        pos = torch.where(before_half, torch.arange(P, device=dev), -1)
        last.scatter_reduce_(0, seg_id, pos, reduce="amax")
        last = last[last >= 0]
    median = median.index_put((pix.index_select(0, last),), depth.index_select(0, last))
    return accum.reshape(C, rows, W, D + 6), median.reshape(C, rows, W, 1)


def _span_coefficients(f64: Tensor, r2: Tensor, low_pass: float) -> list[Tensor]:
    """Per-surfel polynomials in the row ``y`` that bound its support (float64).

    ``f64`` (17 + D, S) packed features, ``r2`` (S,) support radius². With
    ``q = adj(M)·(x, y, 1) = x·a + b(y)``, the conic ``q0² + q1² − r² q2² ≤ 0`` on row y
    reads ``A x² + 2 B(y) x + Cq(y) ≤ 0``; returns the columns
    ``[A, B0, B1, C0, C1, C2, μx, μy, (r·low_pass)²]`` (each (S,)), with
    ``B = B0 + B1 y`` and ``Cq = C0 + C1 y + C2 y²``.
    """
    J = f64[:9]
    a = (J[0], J[3], J[6])
    b1 = (J[1], J[4], J[7])
    b0 = (J[2], J[5], J[8])
    k = (1.0, 1.0, -r2)
    A = sum(k[i] * a[i] * a[i] for i in range(3))
    B0 = sum(k[i] * a[i] * b0[i] for i in range(3))
    B1 = sum(k[i] * a[i] * b1[i] for i in range(3))
    C0 = sum(k[i] * b0[i] * b0[i] for i in range(3))
    C1 = sum(2 * k[i] * b0[i] * b1[i] for i in range(3))
    C2 = sum(k[i] * b1[i] * b1[i] for i in range(3))
    r2d = r2 * low_pass * low_pass if low_pass > 0 else torch.full_like(r2, -1.0)
    return [A, B0, B1, C0, C1, C2, f64[_MX], f64[_MY], r2d]


def _row_spans(sp: list[Tensor], y: Tensor) -> tuple[Tensor, Tensor]:
    """Float64 x-interval [lo, hi] holding a surfel's support on pixel row ``y``.

    ``sp``: the :func:`_span_coefficients` columns gathered per row (each (R,)); ``y``
    (R,). The 3D part is the conic (unbounded rows give ±inf), the 2D part the disk of
    radius ``r·low_pass``; the interval returned is the hull of both (NaN when empty).
    """
    A, B0, B1, C0, C1, C2, mx, my, r2d = sp
    B = B0 + B1 * y
    Cq = C0 + (C1 + C2 * y) * y
    disc = B * B - A * Cq
    root = torch.sqrt(disc.clamp(min=0))
    bounded = A > 0
    safeA = torch.where(bounded, A, 1.0)
    lo3 = torch.where(bounded, (-B - root) / safeA, -torch.inf)
    hi3 = torch.where(bounded, (-B + root) / safeA, torch.inf)
    none3 = bounded & (disc < 0)
    # Pad for rounding: the exact per-pair test decides at the boundary.
    lo3 = torch.where(none3, torch.inf, lo3 - (1e-6 + 1e-6 * lo3.abs()))
    hi3 = torch.where(none3, -torch.inf, hi3 + (1e-6 + 1e-6 * hi3.abs()))
    dy = my - y
    h2 = r2d - dy * dy
    h = torch.sqrt(h2.clamp(min=0)) + 1e-6
    lo3 = torch.minimum(lo3, torch.where(h2 >= 0, mx - h, torch.inf))
    hi3 = torch.maximum(hi3, torch.where(h2 >= 0, mx + h, -torch.inf))
    empty = lo3 > hi3
    return lo3.masked_fill(empty, torch.nan), hi3.masked_fill(empty, torch.nan)


def _pair_alpha_depth(
    f: tuple[Tensor, ...], x: Tensor, y: Tensor, inv_lp2: float, use_lp: bool, near: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Per pair: alpha, hit depth and the support mask (before the 1/255 test).

    ``f`` ≥ 14 per-pair feature rows (P,) in the packed order, ``x``, ``y`` (P,) pixel coordinates.
    """
    q0 = f[0] * x + f[1] * y + f[2]
    q1 = f[3] * x + f[4] * y + f[5]
    q2 = f[6] * x + f[7] * y + f[8]
    hit = q2 != 0
    q2s = torch.where(hit, q2, torch.ones_like(q2))
    inv = 1.0 / q2s
    u = q0 * inv
    v = q1 * inv
    rho3 = u * u + v * v
    depth3 = f[_DET] * inv
    if use_lp:
        dx = f[_MX] - x
        dy = f[_MY] - y
        rho2 = (dx * dx + dy * dy) * inv_lp2
        use3 = rho3 <= rho2
        rho = torch.where(use3, rho3, rho2)
        depth = torch.where(use3, depth3, f[_Z])
    else:
        rho, depth = rho3, depth3
    ok = hit & (rho <= CUTOFF * CUTOFF) & (depth >= near)
    alpha = torch.clamp(f[_OPA] * torch.exp(-0.5 * rho), max=ALPHA_MAX)
    return alpha, depth, ok
