"""The optimisation of one frame: Adam on the surfels against the frame's views.

Per step: render the step's views over their backgrounds, then minimise
``λ_app Σ_k w_k (L1 + D-SSIM)_k + w_mask·mean|α − masks| + λ_geo (w_n L_normal + w_γ L_γ
+ w_p L_proj)`` (the geometry losses from ``geo_from`` steps on, on the input views);
the densification strategy may add and remove surfels; after each Adam step the
rotations are renormalised and the centres put back above the plate (``floor_y``) and
within the depth bound. Units: metres; the SDF value and γ in units of the scene extent
``L`` (:mod:`surfphase.fit.model`).
"""

from __future__ import annotations

import torch

from surfphase.fit import losses
from surfphase.fit.bounds import DepthBounds
from surfphase.fit.densify import Strategy
from surfphase.fit.model import SurfelModel
from surfphase.fit.viewset import FrameViews, StepViews


def make_optimizer(model: SurfelModel, p: dict) -> torch.optim.Adam:
    """One Adam over named groups; the position rate is ``lr_means·L`` metres per step."""
    lrs = {
        "means": p["lr_means"] * model.extent,
        "log_scales": p["lr_log_scales"],
        "quats": p["lr_quats"],
        "colors": p["lr_colors"] if p["surfel_colors"] or model.shade is None else 0.0,
        "sdf": p["lr_sdf"],
        "log_gamma": p["lr_log_gamma"],
        "opacity_logit": p["lr_opacity"],
        "shade": p["lr_shade"],
    }
    groups = [{"params": [v], "lr": lrs[k], "name": k} for k, v in model.params.items()]
    return torch.optim.Adam(groups, lr=0.0, eps=p["adam_eps"])


def render_views(model: SurfelModel, viewmats, Ks, width, height, backgrounds: torch.Tensor):
    """Render the model into (C, 4, 4) ``viewmats`` / (C, 3, 3) ``Ks`` over per-view
    background images (C, H, W, D) → ``(rgb, alpha, meta)`` of the rasterizer."""
    from surfphase.render import over_background, rasterize_surfels

    rgb, alpha, meta = rasterize_surfels(
        model.means,
        model.quats,
        model.scales,
        model.opacities(),
        model.view_colors(viewmats),
        viewmats,
        Ks,
        width,
        height,
    )
    return over_background(rgb, alpha, backgrounds), alpha, meta


def geometry_losses(
    model: SurfelModel, step: StepViews, meta: dict, alpha: torch.Tensor, p: dict
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(L_normal, L_γ/γ_m, L_proj)`` on the step's input views (``alpha`` theirs)."""
    geo = {k: step.inputs(meta[k]) for k in ("normals_camera", "normals_from_depth")}
    ln = losses.normal_consistency(geo["normals_camera"], geo["normals_from_depth"], alpha)
    pts = model.zero_level_points()
    lp = losses.projection_loss(
        pts,
        step.inputs(meta["depth_expected"]),
        step.inputs(step.viewmats),
        step.inputs(step.Ks),
        model.extent,
        p["proj_threshold"],
    )
    lg = torch.zeros(())
    if model.use_sdf:
        sdf = model.params["sdf"]
        lg = losses.gamma_hinge(model.gamma, sdf) / losses.gamma_target(sdf)
    return ln, lg, lp


@torch.no_grad()
def constrain(model: SurfelModel, p: dict, bounds: DepthBounds | None) -> None:
    """After a step: unit rotations, centres above ``floor_y`` and within ``bounds``."""
    model.params["quats"].data /= (
        model.params["quats"].data.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    )
    if p["floor_y"] is not None:
        model.params["means"].data[:, 1].clamp_(min=float(p["floor_y"]))
    if bounds is not None:
        bounds.apply(model.params["means"].data)


def fit_frame(
    model: SurfelModel,
    views: FrameViews,
    p: dict,
    iters: int,
    strategy: Strategy,
    frame: int,
    generator: torch.Generator,
    geo_from: int = 0,
    bounds: DepthBounds | None = None,
    foreground: torch.Tensor | None = None,
) -> list[dict]:
    """Optimise ``model`` on one frame's ``views`` (:class:`~surfphase.fit.viewset.
    FrameViews`) for ``iters`` Adam steps. Returns the logged curve rows (every
    ``log_every`` steps and the last).

    The geometry losses start at step ``geo_from``; ``strategy`` (its random draws from
    ``generator``) may densify and prune; ``bounds`` (see
    :func:`~surfphase.fit.bounds.depth_bounds`) limits the surfels' depth extent after
    every step. With ``foreground`` ((C_in, H, W) floats, 1 inside any bubble's mask of
    an input view) and ``w_mask`` > 0, ``w_mask · mean|α − foreground|`` over the input
    views is added: a bubble is opaque inside its mask.
    """
    H, W = views.observed.shape[1:3]
    opt = make_optimizer(model, p)
    state = strategy.initialize_state(model.n, model.means.device)
    rows = []
    base_lr = p["lr_means"] * model.extent
    for it in range(iters):
        frac = it / max(iters - 1, 1)
        for g in opt.param_groups:
            if g["name"] == "means":
                g["lr"] = base_lr * p["lr_means_decay"] ** frac
        step = views.step(it)
        rgb, alpha, meta = render_views(model, step.viewmats, step.Ks, W, H, step.backgrounds)
        strategy.before_backward(meta)
        app, l1v, dssim = step.photometric(rgb, p["lambda_dssim"])
        rgb, alpha = step.inputs(rgb), step.inputs(alpha)
        loss = p["lambda_app"] * app
        if foreground is not None and p["w_mask"] > 0:
            loss = loss + p["w_mask"] * (alpha[..., 0] - foreground).abs().mean()
        ln = lg = lp = torch.zeros(())
        if it >= geo_from:
            ln, lg, lp = geometry_losses(model, step, meta, alpha, p)
            loss = loss + p["lambda_geo"] * (
                p["w_normal"] * ln + p["w_gamma"] * lg + p["w_proj"] * lp
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        meta["width"], meta["height"] = W, H
        if strategy.after_backward(model, opt, state, it, meta, generator=generator):
            # Gradients belong to replaced tensors after a refinement: skip that step.
            opt.zero_grad(set_to_none=True)
            continue
        opt.step()
        constrain(model, p, bounds)
        if it % p["log_every"] == 0 or it == iters - 1:
            terms = {"loss": loss, "l1": l1v, "dssim": dssim, "normal": ln, "gamma": lg, "proj": lp}
            rows.append(
                {"frame": frame, "iter": it}
                | {k: float(v.detach()) for k, v in terms.items()}
                | {"psnr": losses.psnr(rgb, step.inputs(step.observed)), "n_surfels": model.n}
            )
    return rows
