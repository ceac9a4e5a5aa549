"""Photometric refinement of the bubble advection (docs/method.md §5.4, guidance).

The advection moves each bubble's surfels rigidly by the bubble's velocity predicted
from the two previous centroids. The prediction is off whenever a bubble accelerates, has
no history yet (the configured start velocity) or was just spawned; the per-frame
optimisation then has to drag hundreds of surfels one small Adam step at a time, and the
centroids it reaches in a few dozen steps lag behind the bubbles, which biases every
finite-difference velocity towards the prediction. :func:`register_bubbles` first solves
for one rigid translation per bubble (3 unknowns, constrained by every pixel of the
bubble in every input view) that best explains the new frame, so the per-surfel
optimisation starts from surfels already on the bubble and only refines its shape.

Units: positions and translations in metres (lab frame); images in [0, 1].
"""

from __future__ import annotations

import numpy as np
import torch

from surfphase.fit.model import SurfelModel


def _alpha(means, quats, scales, opacities, colors, viewmats, Ks, W, H) -> torch.Tensor:
    """(C, H, W, 1) accumulated opacity of the given surfels (the rasterizer's)."""
    from surfphase.render import rasterize_surfels

    return rasterize_surfels(means, quats, scales, opacities, colors, viewmats, Ks, W, H)[1]


def register_bubbles(
    model: SurfelModel,
    bubble: np.ndarray,
    observed: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    background: torch.Tensor,
    steps: int,
    lr: float,
    lr_decay: float = 0.1,
    skip_ids: tuple[int, ...] = (0,),
    foreground: torch.Tensor | None = None,
    w_silhouette: float = 0.0,
    silhouettes: dict[int, torch.Tensor] | None = None,
) -> dict[int, np.ndarray]:
    """Translate each bubble's surfels rigidly to fit ``observed``; update ``model`` in place.

    Minimises the summed per-view L1 error between the render (over ``background``) and
    ``observed`` over one translation per bubble with Adam (``steps`` steps, rate
    ``lr`` metres per step decaying exponentially to ``lr·lr_decay``); nothing else of
    the model changes.

    Args:
        model: the surfels (means (N, 3) m); its ``means`` are shifted in place.
        bubble: (N,) bubble id of each surfel; ``-1`` (unbound) and ``skip_ids`` (the
            nucleation region, which moves per surfel) are not translated.
        observed: (C, H, W, D) input images in [0, 1].
        viewmats: (C, 4, 4) world-to-camera; Ks: (C, 3, 3) intrinsics, pixels.
        background: (C, H, W, D) images behind the surfels.
        steps: Adam steps (0: nothing happens).
        lr: initial step size, metres.
        lr_decay: final step size as a fraction of ``lr``.
        skip_ids: bubble ids left where they are.
        foreground: (C, H, W) masks of the new frame in {0, 1} (bubbles and nucleation
            region); with ``w_silhouette`` > 0 the loss adds ``w_silhouette`` times the
            per-view mean |α − foreground|, which a shape change (a coalescing bubble)
            misleads less than the ring's shading.
        w_silhouette: weight of that silhouette term.
        silhouettes: ``{bubble: (C, H, W) its own mask in {0, 1}}``: for these bubbles
            the loss adds ``w_silhouette`` times the per-view mean |α_b − mask_b|, α_b
            rendered from that bubble's surfels alone.

    Returns:
        ``{bubble: (3,) translation applied, metres}`` for every translated bubble.
    """
    from surfphase.render import over_background, rasterize_surfels

    bubble = np.asarray(bubble).reshape(-1)
    if bubble.shape[0] != model.n:
        raise ValueError(f"register_bubbles: {bubble.shape[0]} bubble ids for {model.n} surfels")
    ids = [int(b) for b in np.unique(bubble) if b >= 0 and int(b) not in skip_ids]
    if steps <= 0 or not ids:
        return {}
    dev, dt = model.means.device, model.means.dtype
    # Row k of the translation table belongs to ids[k]; the last row (zeros) to the rest.
    row = np.full(bubble.shape[0], len(ids), dtype=np.int64)
    for k, b in enumerate(ids):
        row[bubble == b] = k
    row_t = torch.as_tensor(row, device=dev)
    shift = torch.zeros((len(ids), 3), dtype=dt, device=dev, requires_grad=True)
    zero = torch.zeros((1, 3), dtype=dt, device=dev)
    opt = torch.optim.Adam([shift], lr=lr, eps=1e-15)
    C, H, W, _ = observed.shape
    with torch.no_grad():
        base = model.means.detach().clone()
        quats, scales = model.quats.detach(), model.scales.detach()
        opac = model.opacities().detach()
        colors = model.view_colors(viewmats).detach()
    for it in range(steps):
        for g in opt.param_groups:
            g["lr"] = lr * lr_decay ** (it / max(steps - 1, 1))
        # index_select, not ``[row_t]``: the backward of advanced indexing with repeated
        # indices accumulates through index_put_, whose threaded CPU kernel sums in a
        # different order on every run once there are ~10k surfels (not bit-for-bit).
        means = base + torch.cat([shift, zero]).index_select(0, row_t)
        rgb, alpha, _ = rasterize_surfels(means, quats, scales, opac, colors, viewmats, Ks, W, H)
        img = over_background(rgb, alpha, background)
        loss = (img - observed).abs().flatten(1).mean(dim=1).sum()
        if foreground is not None and w_silhouette > 0:
            sil = (alpha[..., 0] - foreground).abs().flatten(1).mean(dim=1).sum()
            loss = loss + w_silhouette * sil
        for b, mask in (silhouettes or {}).items():
            if b not in ids or w_silhouette <= 0:
                continue
            sel = row_t == ids.index(b)
            a_b = _alpha(means[sel], quats[sel], scales[sel], opac[sel], colors[..., sel, :],
                         viewmats, Ks, W, H)  # fmt: skip
            loss = loss + w_silhouette * (a_b[..., 0] - mask).abs().flatten(1).mean(dim=1).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        final = shift.detach()
        model.params["means"].data.copy_(base + torch.cat([final, zero])[row_t])
    out = final.cpu().double().numpy()
    return {b: out[k] for k, b in enumerate(ids)}
