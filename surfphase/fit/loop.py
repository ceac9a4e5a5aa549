"""The checkpointed frame loop that both fits run (docs/method.md §5, §9).

:func:`run_frames` fits the frames of one session in order, fed a :class:`FitInputs`:
the session, the settings, the views (the input views, or inputs plus refined views
with their weights and sampler: :class:`~surfphase.fit.viewset.ViewSet`) and the
surfels a fresh run starts from. Per frame ``t``:

1. prepare (:func:`prepare_frame`) — ``t`` > 0: the previous frame's surfels, advected
   and registered to the new frame (:mod:`surfphase.fit.guidance`), merged bubbles
   dropped, new surfels for bubbles that appear or were dropped
   (:func:`surfphase.fit.seeding.spawn_bubbles`);
2. fit (:func:`optimise_frame`, :func:`surfphase.fit.optimise.fit_frame`) — Adam on the
   frame's views; densify and prune at frame 0 only
   (:func:`surfphase.fit.densify.frame_strategy`);
3. finish (:func:`finish_frame`) — bind every surfel to a bubble through the masks,
   record the frame (:class:`~surfphase.fit.record.FrameRecord`) and checkpoint it
   (:mod:`surfphase.fit.checkpoint`), so a killed job resumes at the last finished frame
   with a bit-identical result.

Determinism: one seeded ``torch.Generator`` drives every random choice; each frame starts
a fresh Adam, so a checkpoint holds the surfels, the generator state and the per-frame
records, and a resumed run reproduces an uninterrupted one bit for bit (CPU, same
thread count).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from surfphase.fit import binding, checkpoint, losses
from surfphase.fit.backgrounds import input_backgrounds
from surfphase.fit.bounds import depth_bounds
from surfphase.fit.densify import frame_strategy
from surfphase.fit.guidance import advect_and_register, reseed_merges
from surfphase.fit.model import SurfelModel
from surfphase.fit.optimise import fit_frame, render_views
from surfphase.fit.record import FrameRecord, SurfelIds
from surfphase.fit.seeding import spawn_bubbles
from surfphase.fit.session import SessionData
from surfphase.fit.viewset import RefinedViews, ViewSet
from surfphase.progress import Progress


@dataclass
class FitInputs:
    """What one run of the frame loop fits.

    Attributes:
        data: the session.
        p: the fit settings (:func:`surfphase.fit.stage.merge_params`).
        start: ``generator → SurfelModel``, the surfels of frame 0 of a fresh run (it may
            draw from the run's generator).
        refined: refined views beside the input views (stage 2), or None.
        key_extra: what else a checkpoint must match (stage 2: a hash of its inputs).
    """

    data: SessionData
    p: dict
    start: Callable[[torch.Generator], SurfelModel]
    refined: RefinedViews | None = None
    key_extra: str = ""

    def n_frames(self) -> int:
        """Frames to fit: the session's, the first ``frames`` ones, and no more than the
        refined views have."""
        data, p = self.data, self.p
        n = data.n_frames if p["frames"] is None else min(int(p["frames"]), data.n_frames)
        if n < 1:
            raise ValueError(f"session {data.session}: no frames to fit")
        if self.refined is not None:
            n = min(n, int(self.refined.n_frames))
        return n

    def key(self, n_frames: int) -> str:
        """The run key a checkpoint must match (:func:`surfphase.fit.checkpoint.run_key`)."""
        key = checkpoint.run_key(self.data, {**self.p, "frames": n_frames})
        if self.key_extra:
            key = hashlib.sha256((key + self.key_extra).encode()).hexdigest()
        return key


@dataclass
class Run:
    """The state of a run of the loop between frames."""

    fit: FitInputs
    ckpt: Path
    key: str
    device: torch.device
    n_frames: int
    start: int  # first frame to fit (a resumed run: the first unfinished one)
    model: SurfelModel
    generator: torch.Generator
    background: np.ndarray  # (C, H, W, D) input-view backgrounds
    views: ViewSet
    ids: SurfelIds
    records: list[FrameRecord] = field(default_factory=list)


def open_run(fit: FitInputs, ckpt: Path, device: torch.device) -> Run:
    """Resume the checkpoint in ``ckpt`` of the same run, or start afresh."""
    dtype = torch.float32
    data, p = fit.data, fit.p
    n_frames = fit.n_frames()
    key = fit.key(n_frames)
    state, saved = checkpoint.load_checkpoint(ckpt, key)
    gen = torch.Generator().manual_seed(int(p["seed"]))
    records = [FrameRecord.from_dict(r) for r in saved]
    if state is None:
        checkpoint.start_fresh(ckpt)
        model = fit.start(gen)
        background = input_backgrounds(data, n_frames, p)
        start, ids = 0, SurfelIds(np.zeros(0, dtype=np.int64), 0)
    else:
        model = SurfelModel(state["params"], extent=state["extent"], use_sdf=p["use_sdf"])
        gen.set_state(state["generator"])
        background = state["background"]
        start = state["next_frame"]
        ids = SurfelIds(
            records[-1].ids if records else np.zeros(0, dtype=np.int64),
            int(state.get("next_id", model.n)),
        )
    model.params = {k: v.detach().to(device).requires_grad_(True) for k, v in model.params.items()}
    views = ViewSet(data.cameras, background, fit.refined, device, dtype)
    return Run(
        fit=fit, ckpt=ckpt, key=key, device=device, n_frames=n_frames, start=start,
        model=model, generator=gen, background=background, views=views, ids=ids,
        records=records,
    )  # fmt: skip


@dataclass
class Prepared:
    """What preparing a frame did to the surfels before its fit."""

    spawned: list[int] = field(default_factory=list)  # bubbles that got new surfels
    registered: dict[int, np.ndarray] = field(default_factory=dict)  # rigid shifts, m
    reseeded: dict[int, np.ndarray] = field(default_factory=dict)  # merged: their m/s


def prepare_frame(run: Run, t: int) -> Prepared:
    """Carry the surfels of frame ``t − 1`` over to frame ``t`` (nothing at ``t`` = 0):
    advect and register them (bubble guidance on), drop the bubbles a merge formed at
    ``t``, and seed the bubbles no surfel covers."""
    if t == 0:
        return Prepared()
    data, p, model = run.fit.data, run.fit.p, run.model
    out, vb = Prepared(), {}
    if p["guidance"]:
        vb, out.registered = advect_and_register(
            model, run.records, data, t, p, run.views.viewmats, run.views.Ks,
            run.views.backgrounds,
        )  # fmt: skip
    model.params = {k: v.detach().cpu() for k, v in model.params.items()}
    if p["guidance"] and p["reseed_merges"]:
        out.reseeded, keep = reseed_merges(model, data, t, vb, p)
        run.ids.keep(keep)
    n_before = model.n
    grid = (int(p["reseed_grid"]), int(p["reseed_max_surfels"]))
    out.spawned = spawn_bubbles(model, data, t, p, run.generator, {b: grid for b in out.reseeded})
    run.ids.extend(model.n - n_before)
    model.params = {
        k: v.detach().to(run.device).requires_grad_(True) for k, v in model.params.items()
    }
    return out


def optimise_frame(
    run: Run, t: int, observed: torch.Tensor, prep: Prepared
) -> tuple[list[dict], int]:
    """Optimise the surfels on frame ``t`` (``observed`` (C, H, W, D) its input images)
    → the logged curve rows and the number of steps."""
    data, p = run.fit.data, run.fit.p
    labels = data.labels(t)
    if t == 0:
        iters, geo_from = int(p["iters_first"]), int(p["geo_from"] * int(p["iters_first"]))
    else:
        iters, geo_from = int(p["iters_reseed"] if prep.reseeded else p["iters_next"]), 0
    centres = data.anchor_centres(t) if p["anchor_centres"] else None
    bounds = depth_bounds(data.cameras, labels, p["depth_bound"], centres)
    fg = torch.as_tensor(np.stack(labels) >= 0, dtype=torch.float32, device=run.device)
    rows = fit_frame(
        run.model, run.views.frame(t, observed), p, iters, frame_strategy(p, t, iters), t,
        run.generator, geo_from=geo_from, bounds=bounds, foreground=fg,
    )  # fmt: skip
    return rows, iters


def finish_frame(run: Run, t: int, observed: torch.Tensor, **fields) -> FrameRecord:
    """Bind the fitted surfels of frame ``t`` to the bubbles, record the frame
    (``fields``: the record's other fields) and checkpoint it."""
    data, model = run.fit.data, run.model
    with torch.no_grad():
        rgb, _, _ = render_views(
            model, run.views.viewmats, run.views.Ks, data.width, data.height,
            run.views.backgrounds,
        )  # fmt: skip
    psnr = [losses.psnr(rgb[c], observed[c]) for c in range(observed.shape[0])]
    model_cpu = SurfelModel(
        {k: v.detach().cpu() for k, v in model.params.items()},
        extent=model.extent,
        use_sdf=model.use_sdf,
    )
    bubble = binding.bind_surfels_to_bubbles(
        model_cpu.means.detach().double().numpy(), data.cameras, data.labels(t)
    )
    if t == 0:  # densification has settled the first frame's surfels
        run.ids.renumber(model.n)
    seconds = time.perf_counter() - fields.pop("started")
    rec = FrameRecord.of_model(
        model_cpu, bubble, ids=run.ids.ids.astype(np.int64), frame=t, psnr=psnr,
        seconds=seconds, **fields,
    )  # fmt: skip
    run.records.append(rec)
    state = {
        "key": run.key,
        "next_frame": t + 1,
        "next_id": run.ids.next_id,
        "params": model_cpu.state(),
        "extent": model.extent,
        "generator": run.generator.get_state(),
        "background": run.background,
    }
    checkpoint.save_frame(run.ckpt, t, rec.to_dict(), state)
    return rec


def run_frames(fit: FitInputs, out_dir: Path, ckpt: Path, device: torch.device) -> dict:
    """Fit every frame of ``fit`` (resuming ``ckpt``), then write ``out_dir``
    (:func:`surfphase.fit.outputs.write_outputs`) → the summary dict."""
    from surfphase.fit import outputs

    run = open_run(fit, ckpt, device)
    data = fit.data
    # One line per frame with elapsed time and ETA (a resumed run counts what is left).
    progress = Progress(run.n_frames - run.start, f"session {data.session}: frame",
                        offset=run.start)  # fmt: skip
    for t in range(run.start, run.n_frames):
        t0 = time.perf_counter()
        prep = prepare_frame(run, t)
        observed = torch.as_tensor(data.images(t), device=device)
        t_opt = time.perf_counter()
        rows, iters = optimise_frame(run, t, observed, prep)
        seconds_optimise = time.perf_counter() - t_opt
        rec = finish_frame(
            run, t, observed, started=t0, curves=rows, iters=iters, spawned=prep.spawned,
            registered=prep.registered, reseeded=prep.reseeded,
            seconds_optimise=seconds_optimise,
        )  # fmt: skip
        progress.step(
            f"{iters} steps, "
            f"input-view PSNR {', '.join(f'{v:.1f}' for v in rec.psnr)} dB, "
            f"{rec.seconds:.1f} s"
        )
    records = [r.to_dict() for r in run.records]
    return outputs.write_outputs(
        out_dir, records, data, fit.p, run.background, extent=run.model.extent, device=device
    )
