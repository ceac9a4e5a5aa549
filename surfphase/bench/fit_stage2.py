"""``surfphase bench fit2``: the cost of a stage-2 step against a stage-1 step.

On a session with a stage-1 fit, rendered orbit views and refined views (the folders of
``surfphase fit2``), runs the optimisation steps of one later frame (frame 1, no
densification, as every frame after the first) from the stage-1 surfels of frame 0:
stage 1 (input views only) and stage 2 with ``views_per_step`` refined views per step
for each requested value (0: all of them). The variants take turns, ``repeats`` times,
so that a shared machine's load falls on all of them alike; the medians are reported.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch


def run_benchmark(
    ingest_dir: str | os.PathLike,
    masks_dir: str | os.PathLike,
    stage1_dir: str | os.PathLike,
    views_dir: str | os.PathLike,
    refine_dir: str | os.PathLike,
    views_per_step: Sequence[int] = (0, 4, 2),
    iters: int = 10,
    repeats: int = 3,
    threads: int = 2,
) -> dict:
    """Seconds per optimisation step (medians over ``repeats``) of stage 1 and of stage 2
    for each ``views_per_step``; CPU, ``threads`` torch threads."""
    from surfphase.fit.backgrounds import input_backgrounds
    from surfphase.fit.densify import NoDensify
    from surfphase.fit.optimise import fit_frame
    from surfphase.fit.outputs import load_surfels
    from surfphase.fit.session import SessionData
    from surfphase.fit.stage2 import initial_model_from_stage1, load_extra_views, split_params
    from surfphase.fit.viewset import FrameViews
    from surfphase.render import camera_tensors

    torch.set_num_threads(int(threads))
    data = SessionData(ingest_dir, masks_dir)
    surfels = load_surfels(Path(stage1_dir) / "surfels.npz")
    s2, p = split_params({})
    bg = torch.as_tensor(input_backgrounds(data, data.n_frames, p))
    vm, Ks = camera_tensors(data.cameras, "cpu", torch.float32)
    nc = len(data.cameras)
    t = min(1, data.n_frames - 1)
    obs = torch.as_tensor(data.images(t))
    variants: dict[str, dict] = {"stage1": {}}
    for k in views_per_step:
        ev = load_extra_views(views_dir, refine_dir, {**s2, "views_per_step": int(k)},
                              (data.height, data.width), int(obs.shape[-1]))  # fmt: skip
        evm, eK = camera_tensors(ev.cameras, "cpu", torch.float32)
        variants[f"stage2_views_per_step_{int(k)}"] = {
            "vm": torch.cat([vm, evm]),
            "Ks": torch.cat([Ks, eK]),
            "bg": torch.cat([bg, torch.as_tensor(ev.backgrounds)]),
            "obs": torch.cat([obs, torch.as_tensor(ev.images(t))]),
            "ev": ev,
            "rendered": nc + (len(ev.names) if int(k) <= 0 else min(int(k), len(ev.names))),
        }
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(int(repeats)):
        for name, v in variants.items():
            knots = int(p["shade_knots"]) if p["shading"] else None
            model = initial_model_from_stage1(surfels, bool(p["use_sdf"]), knots)
            gen = torch.Generator().manual_seed(0)
            t0 = time.perf_counter()
            if not v:
                views = FrameViews(obs, vm, Ks, bg, nc, None)
            else:
                views = FrameViews(v["obs"], v["vm"], v["Ks"], v["bg"], nc,
                                   v["ev"].schedule(t, nc))  # fmt: skip
            fit_frame(model, views, p, iters, NoDensify(), t, gen)
            times[name].append((time.perf_counter() - t0) / iters)
    base = float(np.median(times["stage1"]))
    out = {
        "session": data.session,
        "size": [data.width, data.height],
        "surfels": int(surfels["alive"][0].sum()),
        "iters": int(iters),
        "repeats": int(repeats),
        "threads": int(threads),
        "variants": {},
    }
    for name, ts in times.items():
        med = float(np.median(ts))
        out["variants"][name] = {
            "views_rendered": nc if name == "stage1" else variants[name]["rendered"],
            "seconds_per_iter": med,
            "seconds_per_iter_all": ts,
            "relative_to_stage1": med / base,
        }
    return out
