"""The stage-1 fit of one session: sequential per-frame optimisation of SDF surfels with
bubble-guided tracking, checkpointed after every frame (docs/method.md §5).

Frame 0 starts from surfels on the visual hull of the masks
(:func:`surfphase.fit.seeding.initial_model`); every frame is then fitted by the frame
loop of :mod:`surfphase.fit.loop` on the input views (prepare: advect → register →
reseed → spawn; fit; finish: bind, record, checkpoint), and the outputs are written by
:mod:`surfphase.fit.outputs`. Stage 2 (:mod:`surfphase.fit.stage2`) runs the same loop
with refined views beside the inputs.

Units: positions metres (lab frame), time seconds, velocity m/s. The SDF value ``f`` and
the sharpness ``γ`` are optimised in units of the scene extent ``L`` (m,
:func:`surfphase.fit.init.scene_extent`: the radius of the sphere holding every bubble
triangulated from the first frame's masks); see :mod:`surfphase.fit.model`.

Only the bubbles are reconstructed. The rest of each input view (backlight, heated
plate) is a per-view background image composited behind the surfels
(:mod:`surfphase.fit.backgrounds`): ``I = C + (1 − α)·B_c``.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from functools import partial
from pathlib import Path

from surfphase.device import resolve_device
from surfphase.fit.loop import FitInputs, run_frames
from surfphase.fit.params import DEFAULTS  # every hyperparameter, with its default
from surfphase.fit.seeding import initial_model
from surfphase.fit.session import SessionData
from surfphase.settings import check_keys


def merge_params(params: Mapping | None) -> dict:
    """``DEFAULTS`` updated with ``params``; unknown keys are an error."""
    check_keys(DEFAULTS, params, "fit", see="surfphase.fit.stage.DEFAULTS")
    out = copy.deepcopy(DEFAULTS)
    out.update(params or {})
    if not out["surfel_colors"] and not out["shading"]:
        raise ValueError("fit: surfel_colors false needs shading true (nothing else colours)")
    return out


def checkpoint_folder(out_dir: Path, checkpoint_dir: str | os.PathLike | None) -> Path:
    """Where a fit writing ``out_dir`` keeps its checkpoints (default ``<out_dir>.ckpt``)."""
    if checkpoint_dir:
        return Path(checkpoint_dir)
    return out_dir.parent / (out_dir.name + ".ckpt")


def run_fit(
    ingest_dir: str | os.PathLike,
    masks_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    params: Mapping | None = None,
    device: str = "auto",
    checkpoint_dir: str | os.PathLike | None = None,
) -> dict:
    """Fit one session; write ``out_dir`` (see :mod:`surfphase.fit.outputs`).

    Args:
        ingest_dir: ``<cam>.npy`` frame stacks, ``cameras.json``, ``meta.json``.
        masks_dir: ``<cam>_labels.npy`` instance masks.
        out_dir: output folder.
        params: overrides of :data:`DEFAULTS`.
        device: ``auto``, ``cpu`` or ``cuda``.
        checkpoint_dir: where per-frame checkpoints go (default ``<out_dir>.ckpt``);
            an existing checkpoint of the same inputs and parameters is resumed.

    Returns:
        The summary dict (also written to ``out_dir/summary.json``).
    """
    p = merge_params(params)
    out_dir = Path(out_dir)
    data = SessionData(ingest_dir, masks_dir)
    fit = FitInputs(data, p, start=partial(initial_model, data, p))
    return run_frames(fit, out_dir, checkpoint_folder(out_dir, checkpoint_dir),
                      resolve_device(device))  # fmt: skip
