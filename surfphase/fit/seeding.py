"""Where the fit's surfels come from: the visual hull of the masks.

* :func:`initial_model` — frame 0 of a stage-1 fit: surfels on the visual hull of every
  bubble (:func:`surfphase.fit.init.visual_hull_surfels`), in units of the scene extent
  ``L`` (:func:`surfphase.fit.init.scene_extent`);
* :func:`spawn_bubbles` — a later frame: new surfels for the bubbles its masks show
  but no surfel covers (a bubble that appears, or one a merge re-seeded).

Units: positions metres (lab frame).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from surfphase.fit import binding, init
from surfphase.fit.densify import append_surfels
from surfphase.fit.model import HALF_OPACITY_GF, SurfelModel, per_surfel
from surfphase.fit.session import SessionData
from surfphase.render.shading import monotone_raw


def initial_model(
    data: SessionData, p: dict, gen: torch.Generator, dtype: torch.dtype = torch.float32
) -> SurfelModel:
    """The surfels of a fresh stage-1 fit: at most ``n_init`` of the visual-hull surfels
    of frame 0's masks (drawn with ``gen``), with the shading curve when ``shading``."""
    labels = data.labels(0)
    images = data.images(0)
    spheres = init.bubble_spheres(data.cameras, labels)
    if not spheres:
        raise ValueError(f"session {data.session}: no bubble mask at frame 0 is seen in 2 views")
    extent = init.scene_extent(spheres)
    hull = init.visual_hull_surfels(
        data.cameras, labels, list(images), spheres=spheres, grid=p["hull_grid"]
    )
    if hull.points.shape[0] == 0:
        raise ValueError(f"session {data.session}: the visual hull of frame 0 is empty")
    n = hull.points.shape[0]
    if n > p["n_init"]:
        idx = torch.randperm(n, generator=gen)[: p["n_init"]].sort().values.numpy()
    else:
        idx = np.arange(n)
    t = lambda a: torch.as_tensor(a[idx], dtype=dtype)  # noqa: E731
    model = SurfelModel.from_points(
        t(hull.points),
        t(hull.normals),
        t(hull.colors),
        hull.spacing * p["init_scale"],
        extent=extent,
        init_sdf=p["init_sdf"],
        use_sdf=p["use_sdf"],
    )
    if p["shading"]:
        params = model.state()
        D = model.colors.shape[1]
        knots = torch.zeros((int(p["shade_knots"]), D), dtype=dtype)
        if not p["surfel_colors"]:
            knots += params["colors"].mean(0)
            params["colors"] = torch.zeros_like(params["colors"])
        params["shade"] = monotone_raw(knots)
        model = SurfelModel(params, extent=extent, use_sdf=p["use_sdf"])
    return model


def spawn_bubbles(
    model: SurfelModel,
    data: SessionData,
    t: int,
    p: dict,
    gen: torch.Generator,
    sizes: Mapping[int, tuple[int, int]] | None = None,
) -> list[int]:
    """Add surfels for bubbles that the masks of frame ``t`` show but no surfel covers.

    ``sizes``: ``{bubble: (hull grid, most surfels)}`` overriding ``spawn_grid`` and
    ``spawn_max_surfels`` (bubbles re-seeded at a merge).
    """
    sizes = sizes or {}
    labels = data.labels(t)
    spheres = init.bubble_spheres(data.cameras, labels)
    bound = binding.bind_surfels_to_bubbles(
        model.means.detach().double().numpy(), data.cameras, labels
    )
    images = None
    added = []
    for b in sorted(spheres):
        if int((bound == b).sum()) >= p["spawn_min_surfels"]:
            continue
        if images is None:
            images = list(data.images(t))
        grid, most = sizes.get(b, (p["spawn_grid"], p["spawn_max_surfels"]))
        hull = init.visual_hull_surfels(
            data.cameras,
            labels,
            images,
            bubble=b,
            spheres=spheres,
            grid=grid,
            occlusion=bool(p["hull_occlusion"]),
            occlusion_ratio=float(p["hull_occlusion_ratio"]),
        )
        n = hull.points.shape[0]
        if n == 0:
            continue
        idx = np.arange(n)
        if n > most:
            idx = torch.randperm(n, generator=gen)[:most].sort().values.numpy()
        dt = model.means.dtype
        new = SurfelModel.from_points(
            torch.as_tensor(hull.points[idx], dtype=dt),
            torch.as_tensor(hull.normals[idx], dtype=dt),
            torch.as_tensor(hull.colors[idx], dtype=dt) * (1.0 if p["surfel_colors"] else 0.0),
            hull.spacing * p["init_scale"],
            extent=model.extent,
            init_sdf=p["init_sdf"],
            use_sdf=model.use_sdf,
        )
        vals = new.state()
        if model.use_sdf:
            # New surfels start at opacity 1/2 under the current γ.
            vals["sdf"] = torch.full_like(
                vals["sdf"], HALF_OPACITY_GF / float(model.gamma.detach())
            )
        append_surfels(model, None, {k: v for k, v in vals.items() if per_surfel(k)})
        added.append(b)
    return added
