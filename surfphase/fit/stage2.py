"""The stage-2 fit of one session (docs/method.md §9): the stage-1 loop again, restarted from
the stage-1 surfels of the first frame, with the refined orbit views as extra supervision.

Inputs: the session's ingest and mask folders (as stage 1), the stage-1 fit
(``surfels.npz``, :mod:`surfphase.fit.outputs`), the rendered orbit views
(``views/cameras.json`` and ``views/<v>_alpha.npy``, the stage-1 alpha) and the refined
orbit videos (``refine/<v>.npy``, (T, H, W) uint16 grey frames, value·65535), read through
:mod:`surfphase.folders.views`.

Per frame the loss is ``λ_app Σ_c w_c (L1 + D-SSIM)_c + λ_geo (geometry)``: input views
``w = weight_inputs`` (1.0), refined views ``weight_near`` (0.5) for orbit views 1–3 and
9–11 and ``weight_far`` (0.25) for ``far_views`` (4–8). The geometry losses, binding to
bubbles (through the input views' masks), bubble guidance, spawning and per-frame
checkpoints are stage 1's: both run the frame loop of :mod:`surfphase.fit.loop`, stage 2
with the refined views in its :class:`~surfphase.fit.viewset.ViewSet`.

Rendering every refined view at every step costs about 6× stage 1, so each step renders
the input views and ``views_per_step`` refined views drawn without replacement
(weights scaled by ``n_views / views_per_step``, so the loss is unbiased); the draw is
seeded per frame (``seed``, frame index), so a resumed run draws the same views.

The refinement changes what a view shows behind the bubbles too (plate, backlight):
each refined view gets its own background image, the per-pixel temporal median of its
refined frames where the stage-1 alpha is below ``bg_alpha_max``
(:func:`refined_background`), so the surfels are not pushed to explain it.

A refined view with weight 0 is not loaded or rendered: the fit is then the same as
without it.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from surfphase.cameras import Camera
from surfphase.device import resolve_device
from surfphase.fit.backgrounds import background_median, fill_nearest
from surfphase.fit.loop import FitInputs, run_frames
from surfphase.fit.model import SurfelModel
from surfphase.fit.outputs import load_surfels
from surfphase.fit.params import DEFAULTS as FIT_DEFAULTS
from surfphase.fit.params import FIT_OVERRIDES  # stage-1 settings stage 2 changes
from surfphase.fit.params import STAGE2_DEFAULTS as DEFAULTS  # config fit2:
from surfphase.fit.session import SessionData
from surfphase.fit.stage import checkpoint_folder, merge_params
from surfphase.folders.views import read_refined, read_views
from surfphase.io import atomic_write_json
from surfphase.render.shading import monotone_raw
from surfphase.settings import check_keys


def split_params(params: Mapping | None, fit_params: Mapping | None = None) -> tuple[dict, dict]:
    """(stage-2 settings, fit settings) from ``fit2:`` (``params``) and ``fit:``
    (``fit_params``). Precedence, lowest first: stage-1 defaults, ``fit:``,
    :data:`FIT_OVERRIDES`, fit keys in ``fit2:``. Unknown keys are an error."""
    see = "surfphase.fit.stage2.DEFAULTS and surfphase.fit.stage.DEFAULTS"
    check_keys({**FIT_DEFAULTS, **DEFAULTS}, params, "fit2", see=see)
    s2 = copy.deepcopy(DEFAULTS)
    fit = {**dict(fit_params or {}), **FIT_OVERRIDES}
    for k, v in (params or {}).items():
        if k in DEFAULTS:
            s2[k] = v
        else:
            fit[k] = v
    if float(s2["weight_inputs"]) <= 0:
        raise ValueError("fit2: weight_inputs must be positive")
    for k in ("weight_near", "weight_far", "bg_alpha_max"):
        if float(s2[k]) < 0:
            raise ValueError(f"fit2: {k} must be ≥ 0")
    if int(s2["views_per_step"]) < 0:
        raise ValueError("fit2: views_per_step must be ≥ 0")
    return s2, merge_params(fit)


def view_number(name: str) -> int:
    """The orbit number k of a view named like ``orbit07`` (trailing digits)."""
    m = re.search(r"(\d+)$", name)
    if not m:
        raise ValueError(f"orbit view {name!r}: no view number at the end of its name")
    return int(m.group(1))


def view_weights(names: Sequence[str], s2: Mapping) -> np.ndarray:
    """(V,) photometric weight of each named orbit view (near or far, see DEFAULTS)."""
    far = {int(k) for k in s2["far_views"]}
    return np.array(
        [s2["weight_far"] if view_number(n) in far else s2["weight_near"] for n in names],
        dtype=np.float64,
    )


def refined_background(
    frames: np.ndarray, alpha: np.ndarray, alpha_max: float = 0.02, fallback=None
) -> np.ndarray:
    """Background image of one refined view: per pixel, the median over time of the
    frames where the stage-1 alpha is ≤ ``alpha_max``.

    Args:
        frames: (T, H, W) refined frames in [0, 1].
        alpha: (T, H, W) stage-1 rendered alpha of the same view.
        alpha_max: largest alpha that counts as background.
        fallback: (H, W) image or scalar used when no pixel is ever background
            (default: the median of all frames, per pixel).

    Returns:
        (H, W) float32. A pixel covered by the stage-1 bubbles in every frame takes the
        value of the nearest pixel that is background at some frame.
    """
    frames = np.asarray(frames, dtype=np.float32)
    alpha = np.asarray(alpha, dtype=np.float32)
    if frames.shape != alpha.shape or frames.ndim != 3:
        raise ValueError(f"refined_background: frames {frames.shape} and alpha {alpha.shape}")
    med = background_median(np.where(alpha <= alpha_max, frames, np.nan))
    missing = np.isnan(med)
    if missing.all():
        if fallback is None:
            return np.median(frames, axis=0).astype(np.float32)
        return np.broadcast_to(np.asarray(fallback, np.float32), med.shape).copy()
    if missing.any():
        med = fill_nearest(med, missing)
    return med.astype(np.float32)


@dataclass
class ExtraViews:
    """Refined orbit views as extra supervision of the fit (see the module docstring).

    Attributes:
        names: the V views kept (weight > 0).
        cameras: their undistorted cameras (input-view size).
        frames: (V, T, H, W) float32 refined frames in [0, 1].
        backgrounds: (V, H, W, D) float32 background images.
        weights: (V,) photometric weights.
        weight_inputs: photometric weight of each input view.
        views_per_step: refined views per step (0 or ≥ V: all).
        seed: seed of the per-frame view draws.
        digest: hash of all of the above (checkpoint key).
    """

    names: list[str]
    cameras: list[Camera]
    frames: np.ndarray
    backgrounds: np.ndarray
    weights: np.ndarray
    weight_inputs: float = 1.0
    views_per_step: int = 0
    seed: int = 0
    digest: str = field(default="", repr=False)

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[1])

    def images(self, t: int) -> np.ndarray:
        """(V, H, W, D) refined images of frame ``t``."""
        D = self.backgrounds.shape[-1]
        return np.repeat(self.frames[:, t, :, :, None], D, axis=-1)

    def schedule(self, t: int, n_inputs: int) -> Callable[[int], tuple[torch.Tensor, torch.Tensor]]:
        """Step ``it`` → (view indices into inputs + these views, their weights) for
        frame ``t``: every input view, then the refined views drawn for that step."""
        V = len(self.names)
        k = V if self.views_per_step <= 0 else min(int(self.views_per_step), V)
        w_ref = torch.as_tensor(self.weights, dtype=torch.float64) * (V / max(k, 1))
        w_in = torch.full((n_inputs,), float(self.weight_inputs), dtype=torch.float64)
        inputs = torch.arange(n_inputs)
        gen = torch.Generator().manual_seed(int(self.seed) * 1_000_003 + int(t))

        def pick(it: int) -> tuple[torch.Tensor, torch.Tensor]:
            sel = torch.arange(V) if k == V else torch.randperm(V, generator=gen)[:k].sort()[0]
            idx = torch.cat([inputs, n_inputs + sel])
            return idx, torch.cat([w_in, w_ref[sel]]).float()

        return pick


def load_extra_views(
    views_dir: str | os.PathLike,
    refine_dir: str | os.PathLike,
    s2: Mapping,
    size: tuple[int, int],
    channels: int = 1,
    seed: int = 0,
) -> ExtraViews:
    """Read the refined views named in ``views_dir/cameras.json`` (weight > 0 only).

    Args:
        views_dir: the views folder (:func:`surfphase.folders.views.read_views`):
            ``cameras.json``, ``<v>_alpha.npy`` (T, H, W) and optionally
            ``background.npy`` (H, W) of the rendered orbit views.
        refine_dir: the refine folder: ``<v>.npy`` (T, H, W) uint16 refined frames
            (:func:`surfphase.folders.views.read_refined`).
        s2: stage-2 settings (:data:`DEFAULTS`).
        size: (H, W) of the input views; every orbit view must have it.
        channels: D of the input images (grey refined frames are repeated).
        seed: seed of the per-frame view draws.
    """
    views = read_views(views_dir)
    cams = views.cameras
    names = list(cams)
    w = view_weights(names, s2)
    keep = [i for i in range(len(names)) if w[i] > 0]
    fallback = views.background()
    frames, bgs, h = [], [], hashlib.sha256()
    for i in keep:
        name, cam = names[i], cams[names[i]]
        if (cam.height, cam.width) != tuple(size):
            raise ValueError(
                f"{views.path / 'cameras.json'}: view {name} is {cam.width}×{cam.height}, "
                f"the input views {size[1]}×{size[0]} (session {views.session})"
            )
        fr = read_refined(refine_dir, name)
        al = views.alpha(name)
        if fr.shape[1:] != tuple(size) or al.shape[1:] != tuple(size):
            raise ValueError(
                f"{Path(refine_dir) / (name + '.npy')}: refined frames {fr.shape} / alpha "
                f"{al.shape} do not match the {size[1]}×{size[0]} views "
                f"(session {views.session})"
            )
        T = min(fr.shape[0], al.shape[0])
        fr = fr[:T]
        bg = refined_background(fr, al[:T].astype(np.float32), float(s2["bg_alpha_max"]), fallback)
        frames.append(fr)
        bgs.append(bg)
        h.update(name.encode())
        h.update(json.dumps(cam.to_dict(), sort_keys=True).encode())
        h.update(np.ascontiguousarray(fr).tobytes())
        h.update(np.ascontiguousarray(bg).tobytes())
    V = len(keep)
    T = min((f.shape[0] for f in frames), default=10**9)
    H, W = size
    stack = np.stack([f[:T] for f in frames]) if V else np.zeros((0, 0, H, W), np.float32)
    bg_arr = np.repeat(np.stack(bgs)[..., None], channels, axis=-1) if V else None
    if bg_arr is None:
        bg_arr = np.zeros((0, H, W, channels), np.float32)
    h.update(json.dumps({k: s2[k] for k in sorted(s2)}, sort_keys=True).encode())
    h.update(str(seed).encode())
    return ExtraViews(
        names=[names[i] for i in keep],
        cameras=[cams[names[i]].undistorted() for i in keep],
        frames=stack,
        backgrounds=bg_arr.astype(np.float32),
        weights=w[keep],
        weight_inputs=float(s2["weight_inputs"]),
        views_per_step=int(s2["views_per_step"]),
        seed=int(seed),
        digest=h.hexdigest(),
    )


def initial_model_from_stage1(
    surfels: Mapping[str, np.ndarray], use_sdf: bool, shade_knots: int | None = None
) -> SurfelModel:
    """The surfels of frame 0 of a stage-1 ``surfels.npz`` as a :class:`SurfelModel`.

    The file stores ``f`` in metres and ``γ`` per metre; the model works in units of the
    scene extent ``L`` (``f/L``, ``γ·L``). Without SDF the free opacity becomes its logit.
    A stage-1 shading curve (``shade``) is carried over; without one, ``shade_knots``
    (an int) starts a curve of zeros, None none.
    """
    a = np.asarray(surfels["alive"][0], dtype=bool)
    L = float(surfels["extent"])
    t = lambda k: torch.as_tensor(np.asarray(surfels[k][0])[a], dtype=torch.float32)  # noqa: E731
    params = {k: t(k) for k in ("means", "log_scales", "quats", "colors")}
    if use_sdf:
        sdf = np.asarray(surfels["sdf"][0])[a]
        gamma = float(surfels["gamma"][0])
        if not (np.isfinite(sdf).all() and math.isfinite(gamma)):
            raise ValueError("stage-1 surfels have no SDF values (a 'no SDF' fit): set use_sdf")
        params["sdf"] = torch.as_tensor(sdf / L, dtype=torch.float32)
        params["log_gamma"] = torch.tensor(math.log(gamma * L), dtype=torch.float32)
    else:
        o = np.clip(np.asarray(surfels["opacity"][0])[a], 1e-6, 1 - 1e-6)
        params["opacity_logit"] = torch.as_tensor(np.log(o / (1 - o)), dtype=torch.float32)
    if "shade" in surfels:
        knots = torch.as_tensor(np.asarray(surfels["shade"][0]), dtype=torch.float32)
        params["shade"] = monotone_raw(knots)
    elif shade_knots is not None:
        params["shade"] = monotone_raw(torch.zeros((int(shade_knots), params["colors"].shape[1])))
    return SurfelModel(params, extent=L, use_sdf=use_sdf)


def run_fit_stage2(
    ingest_dir: str | os.PathLike,
    masks_dir: str | os.PathLike,
    stage1_dir: str | os.PathLike,
    views_dir: str | os.PathLike,
    refine_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    params: Mapping | None = None,
    fit_params: Mapping | None = None,
    device: str = "auto",
    checkpoint_dir: str | os.PathLike | None = None,
) -> dict:
    """Stage-2 fit of one session; writes ``out_dir`` in the stage-1 formats
    (:mod:`surfphase.fit.outputs`) plus ``stage2.json`` (views, weights, settings).

    Args:
        ingest_dir, masks_dir: as :func:`surfphase.fit.stage.run_fit`.
        stage1_dir: the stage-1 fit folder (``surfels.npz``).
        views_dir: the rendered orbit views (``cameras.json``, ``<v>_alpha.npy``).
        refine_dir: the refined orbit views (``<v>.npy``).
        out_dir: output folder.
        params: stage-2 settings (config ``fit2:``; :data:`DEFAULTS` and fit keys).
        fit_params: the stage-1 settings (config ``fit:``).
        device: ``auto``, ``cpu`` or ``cuda``.
        checkpoint_dir: per-frame checkpoints (default ``<out_dir>.ckpt``).

    Returns:
        The summary dict of :func:`surfphase.fit.outputs.write_outputs`.
    """
    s2, fit = split_params(params, fit_params)
    stage1 = Path(stage1_dir) / "surfels.npz"
    surfels = load_surfels(stage1)
    data = SessionData(ingest_dir, masks_dir)
    knots = int(fit["shade_knots"]) if fit["shading"] else None
    model = initial_model_from_stage1(surfels, bool(fit["use_sdf"]), knots)
    D = int(np.asarray(surfels["colors"]).shape[-1])
    extra = load_extra_views(
        views_dir, refine_dir, s2, (data.height, data.width), D, seed=int(fit["seed"])
    )
    h = hashlib.sha256(extra.digest.encode())
    for k, v in sorted(model.state().items()):
        h.update(k.encode())
        h.update(v.numpy().tobytes())
    inputs = FitInputs(
        data,
        fit,
        start=lambda _gen: SurfelModel(model.state(), model.extent, fit["use_sdf"]),
        refined=extra if extra.names else None,
        key_extra=h.hexdigest(),
    )
    out = Path(out_dir)
    summary = run_frames(inputs, out, checkpoint_folder(out, checkpoint_dir),
                         resolve_device(device))  # fmt: skip
    atomic_write_json(
        Path(out_dir) / "stage2.json",
        {
            "stage1": str(stage1),
            "views": extra.names,
            "weights": {n: float(w) for n, w in zip(extra.names, extra.weights, strict=True)},
            "weight_inputs": extra.weight_inputs,
            "views_per_step": extra.views_per_step,
            "settings": s2,
            "fit_overrides": {k: fit[k] for k in FIT_OVERRIDES},
        },
    )
    return summary
