"""The ``evaluate`` stage of one session: metrics JSON, baseline and velocity tables.

Inputs (folders of earlier stages):

* ``INGEST`` — ``cameras.json`` (undistorted cameras), ``meta.json`` (``session``,
  ``fps``, ``frame_indices``), ``<cam>.npy`` frame stacks;
* ``MASKS`` — ``<cam>_labels.npy`` (int32 T × H × W, −1 background, ids shared across
  views and time, 0 the nucleation region);
* ``FIT`` — ``bubbles.csv`` (``frame, time_s, bubble, x, y, z, vx, vy, vz``; m, m/s, lab
  frame) and, for held-out views, ``surfels.npz`` (:mod:`surfphase.fit.outputs`); the
  final fit, and optionally the stage-1 fit and ablation fits in the same format;
* ``GT`` (synthetic sessions only) — ``cameras.json``, ``bubbles.csv`` (with ``r_eq``
  for the region metrics),
  ``views/<cam>/<frame:06d>.png`` (held-out views as recorded), optionally
  ``views_clean/<cam>/<frame:06d>.png`` (the same without sensor noise) and
  ``views_background/<cam>.png`` (each held-out camera's reference frame without
  bubbles), ``meshes/<frame:06d>.ply``;
* ``MESHES`` (optional, from the mesh stage) — ``<frame:06d>.ply``, metres.

Outputs in ``OUT`` (each written whole or not at all):

* ``metrics.json`` — ``session``; ``heldout`` (per held-out camera and ``mean``: ``l1``,
  ``psnr`` dB, ``ssim``, ``frames`` over the full frame, and ``region``: the same inside
  the true bubbles' region, :mod:`.regions`, with ``pixels`` its mean size; the
  protocol is in ``settings.heldout``: with ``views_clean`` and ``views_background`` the
  reconstructed bubbles are rendered over the held-out camera's reference frame and
  compared with the noiseless views, and ``heldout_whole`` then holds the figures of
  the whole image predicted — the input views' mean background behind the bubbles,
  compared with the recorded views);
  ``velocity`` (``method`` and ``baseline``: ``mean_abs_error_mps``,
  ``relative_error``, ``mean_speed_gt_mps``, ``matched``); ``chamfer_mm`` (with method
  meshes); ``reference2d`` (always: the 2D reference's relative x/y errors of ``method``
  and ``baseline``; with ground truth also ``truth``, the true velocities of the
  baseline-matched bubbles against the reference, which scores the reference itself);
  ``stage1`` (with a stage-1 fit) and ``ablations`` ``{name: …}`` (with ablation fits):
  each ``fit`` (its folder), ``velocity`` (errors as the method's), ``heldout`` and
  ``heldout_whole`` (as above) and ``reference2d`` (its errors against the 2D reference);
  ``sizes`` (:func:`surfphase.eval.sizes.size_metrics`: the meshes' bubble-frames with a
  volume, their mean and median equivalent diameter, mean volume, and with ground truth
  the equivalent diameter's relative error against the matched true bubbles');
  non-finite numbers are ``null``;
* ``bubbles.csv`` — the fit's ``bubbles.csv`` with each bubble-frame's ``volume_m3``,
  ``d_eq_m`` and ``closed`` from the meshes (``MESHES/bubble_sizes.csv``; NaN where it
  has none): positions, velocities and sizes in one table;
* ``baseline_bubbles.csv`` — the two-view centroid baseline (:mod:`.baseline`);
* ``velocity_table.csv`` — one row per compared bubble-frame, column ``source``
  (``method``/``baseline``, and ``stage1`` / the ablation names with ground truth):
  with ground truth the matches of
  :func:`surfphase.eval.velocity.match_bubbles`, without it the rows of
  :func:`surfphase.eval.reference2d.compare_to_reference`.

Bubble 0 (the nucleation region at the plate) is not a bubble of the ground truth and is
left out of the velocity comparisons unless ``include_nucleation``. The baseline is
compared on the frames present in the fit's ``bubbles.csv`` only, so that method and
baseline errors average over the same frames.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.cameras import Camera, load_cameras
from surfphase.eval import baseline as bl
from surfphase.eval import geometry, image_metrics, reference2d, regions, sizes, velocity
from surfphase.io import atomic_write_json, atomic_write_text, stack_frame_indices

METRIC_KEYS = ("l1", "psnr", "ssim")


# -- inputs ------------------------------------------------------------------------------
def read_session(ingest_dir: Path, masks_dir: Path) -> dict:
    """Session name, fps, frame indices, and the undistorted cameras with label stacks."""
    cam_path, meta_path = ingest_dir / "cameras.json", ingest_dir / "meta.json"
    for p in (cam_path, meta_path):
        if not p.exists():
            raise FileNotFoundError(f"{p}: not found in the ingest folder")
    try:
        meta = json.loads(meta_path.read_text())
    except ValueError as e:
        raise ValueError(f"{meta_path}: not valid JSON ({e})") from e
    session = str(meta.get("session", ingest_dir.name))
    fps = float(meta.get("fps") or 0)
    if not fps > 0:
        raise ValueError(f"{meta_path}: session {session}: fps must be positive")
    cameras, labels = [], []
    for name, cam in load_cameras(cam_path).items():
        if not (ingest_dir / f"{name}.npy").exists():
            continue
        lab_path = masks_dir / f"{name}_labels.npy"
        if not lab_path.exists():
            raise FileNotFoundError(f"{lab_path}: session {session}: no masks for {name}")
        lab = np.load(lab_path, mmap_mode="r")
        if lab.ndim != 3 or lab.shape[1:] != (cam.height, cam.width):
            raise ValueError(
                f"{lab_path}: session {session}: labels of shape {lab.shape} do not match "
                f"the {cam.width}×{cam.height} camera {name}"
            )
        cameras.append(cam.undistorted())
        labels.append(lab)
    if len(cameras) < 2:
        raise ValueError(f"{ingest_dir}: session {session}: need ≥ 2 cameras with frames and masks")
    T = min(lab.shape[0] for lab in labels)
    frames = stack_frame_indices(meta, T, meta_path)
    return {
        "session": session,
        "fps": fps,
        "frames": frames,
        "cameras": cameras,
        "labels": [lab[:T] for lab in labels],
    }


def read_table(path: Path, columns: Sequence[str], what: str) -> pd.DataFrame:
    """A CSV with at least ``columns``; errors name the file and ``what`` it is for."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what}: not found")
    try:
        df = pd.read_csv(path)
    except (ValueError, pd.errors.ParserError) as e:
        raise ValueError(f"{path}: {what}: not a readable CSV ({e})") from e
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: {what}: missing columns {missing}")
    return df


def read_view(path: Path) -> np.ndarray:
    """An 8- or 16-bit PNG → (H, W) or (H, W, 3) RGB float64 in [0, 1]."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float64) / scale
    if img.ndim == 3:
        img = img[..., :3][..., ::-1]
    return img


# -- held-out views ----------------------------------------------------------------------
def heldout_metrics(
    surfels: dict[str, np.ndarray],
    cameras: Sequence[Camera],
    views_dir: Path,
    device: str = "cpu",
    truth: pd.DataFrame | None = None,
    region_scale: float = regions.REGION_SCALE,
    backdrops_dir: Path | None = None,
) -> dict:
    """L1, PSNR (dB) and SSIM of the surfels rendered into held-out cameras, over the
    full frame and, with ``truth``, inside the bubbles' region.

    Every frame of ``surfels`` (``frame`` = session frame index) that has
    ``views_dir/<cam>/<frame:06d>.png`` is rendered and compared; the per-camera values
    are means over frames, ``mean`` the mean over cameras. The fit reconstructs only the
    bubbles: behind them a held-out view sees its camera's reference frame
    ``backdrops_dir/<cam>.png`` when there is one, else the mean of the input views'
    background images when they have its size, else the fit's constant background colour.

    With ``truth`` (the true bubbles: ``frame, x, y, z, r_eq``, metres), each camera also
    gets ``region``: the same metrics restricted to :func:`surfphase.eval.regions.
    bubble_region` (projected spheres of ``region_scale · r_eq``), averaged over the
    frames where the region is not empty (``frames``), with ``pixels`` its mean size.
    """
    from surfphase.fit.outputs import render_surfels

    out: dict = {}
    bg_images = surfels.get("bg_images")
    frames = [int(f) for f in np.asarray(surfels["frame"]).tolist()]
    for cam in cameras:
        folder = views_dir / cam.name
        masks = regions.region_masks(cam, truth, frames, region_scale) if truth is not None else {}
        vals, region_vals = [], []
        bg = None  # behind the bubbles, the same in every frame
        backdrop = backdrops_dir / f"{cam.name}.png" if backdrops_dir is not None else None
        if backdrop is not None and backdrop.exists():
            ref = read_view(backdrop)
            if ref.shape[:2] != (cam.height, cam.width):
                raise ValueError(
                    f"{backdrop}: image is {ref.shape[1]}×{ref.shape[0]}, camera "
                    f"{cam.name} is {cam.width}×{cam.height}"
                )
            bg = ref.reshape(1, cam.height, cam.width, -1).astype(np.float32)
        elif bg_images is not None and bg_images.shape[1:3] == (cam.height, cam.width):
            bg = bg_images.mean(axis=0, keepdims=True)
        for t, f in enumerate(frames):
            path = folder / f"{f:06d}.png"
            if not path.exists():
                continue
            target = read_view(path)
            if target.shape[:2] != (cam.height, cam.width):
                raise ValueError(
                    f"{path}: image is {target.shape[1]}×{target.shape[0]}, camera {cam.name} "
                    f"is {cam.width}×{cam.height}"
                )
            rgb = render_surfels(surfels, t, [cam], device, bg)[0].astype(np.float64)
            if target.ndim == 2:
                if rgb.shape[-1] != 1:
                    raise ValueError(
                        f"{path}: grey image, but the surfels have {rgb.shape[-1]} channels"
                    )
                rgb = rgb[..., 0]
            vals.append(image_metrics.image_metrics(rgb, target))
            mask = masks.get(f)
            if mask is not None and mask.any():
                region_vals.append(image_metrics.region_metrics(rgb, target, mask))
        if vals:
            out[cam.name] = _mean_metrics(vals)
            if truth is not None:
                out[cam.name]["region"] = _mean_metrics(region_vals)
    if out:
        cams = list(out)
        out["mean"] = {**_mean_over(out[c] for c in cams), "cameras": len(cams)}
        if truth is not None:
            with_region = [c for c in cams if out[c]["region"]["frames"]]
            out["mean"]["region"] = {
                **_mean_over(out[c]["region"] for c in with_region),
                "cameras": len(with_region),
            }
    return out


def _mean_metrics(vals: Sequence[dict]) -> dict:
    """Per-frame metric dicts → their means over frames, ``frames``, and ``pixels``."""
    out = {k: _nanmean([v[k] for v in vals]) for k in METRIC_KEYS}
    out["frames"] = len(vals)
    if vals and "pixels" in vals[0]:
        out["pixels"] = float(np.mean([v["pixels"] for v in vals]))
    return out


def _mean_over(items) -> dict:
    items = list(items)
    return {k: _nanmean([i[k] for i in items]) for k in METRIC_KEYS}


def _nanmean(values: Sequence[float]) -> float:
    """Mean of the finite-or-infinite values, NaNs left out; NaN if there are none."""
    v = np.asarray(values, dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def chamfer_per_frame(
    meshes_dir: Path,
    gt_meshes_dir: Path,
    frames: Sequence[int],
    n_points: int = 20000,
    seed: int = 0,
    cameras: Sequence[Camera] | None = None,
) -> dict:
    """Chamfer (mm) of ``meshes_dir/<frame:06d>.ply`` against the true mesh of each frame
    that has both; ``mean_mm``/``mean_sq_mm2`` averaged over frames, and ``per_frame``.

    With the input ``cameras`` (true ones), the comparison is restricted to the volume
    they all see (:func:`surfphase.eval.geometry.in_all_views`); ``whole_truth_mean_mm``
    is then the mean over frames without that restriction, for reference. Frames with
    nothing to compare in that volume are left out of the means (``frames`` counts the
    rest)."""
    per = {}
    for f in frames:
        name = f"{int(f):06d}.ply"
        a, b = meshes_dir / name, gt_meshes_dir / name
        if a.exists() and b.exists():
            per[int(f)] = geometry.mesh_chamfer(a, b, n_points, seed, cameras)
    if not per:
        return {}
    out = {
        "mean_mm": _nanmean([v["mean_mm"] for v in per.values()]),
        "mean_sq_mm2": _nanmean([v["mean_sq_mm2"] for v in per.values()]),
        "frames": int(sum(np.isfinite(v["mean_mm"]) for v in per.values())),
        "points_per_mesh": n_points,
    }
    if cameras is not None:
        out["volume"] = "seen by every input camera (" + ", ".join(c.name for c in cameras) + ")"
        out["whole_truth_mean_mm"] = float(
            np.mean([v["whole_truth_mean_mm"] for v in per.values()])
        )
    out["per_frame"] = {str(k): v for k, v in per.items()}
    return out


def _finite(obj):
    """JSON-safe copy: non-finite floats become None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float | np.floating) and not math.isfinite(float(obj)):
        return None
    return obj


def _truth_region_table(gt_dir: Path, name: str) -> pd.DataFrame | None:
    """The true bubbles with ``r_eq`` for region metrics, or None if it has no radius."""
    cols = ["frame", "x", "y", "z"]
    truth = read_table(gt_dir / "bubbles.csv", cols, f"session {name}")
    return truth if "r_eq" in truth.columns else None


# -- the stage ---------------------------------------------------------------------------
def run_evaluate(
    ingest_dir: str | os.PathLike,
    masks_dir: str | os.PathLike,
    fit_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    gt_dir: str | os.PathLike | None = None,
    meshes_dir: str | os.PathLike | None = None,
    session: str | None = None,
    device: str = "cpu",
    max_match_dist: float = velocity.MAX_MATCH_DIST,
    include_nucleation: bool = False,
    reference_camera: str | None = None,
    fit_stage1_dir: str | os.PathLike | None = None,
    ablations: Mapping[str, str | os.PathLike] | None = None,
    region_scale: float = regions.REGION_SCALE,
    compare_meshes: Mapping[str, str | os.PathLike] | None = None,
) -> dict:
    """Evaluate one session (see the module docstring); returns the metrics dict.

    Args:
        ingest_dir, masks_dir, fit_dir: outputs of the ingest, mask and fit stages
            (``fit_dir``: the final fit, stage 2 when refinement is on).
        out_dir: where ``metrics.json``, ``baseline_bubbles.csv`` and
            ``velocity_table.csv`` go.
        gt_dir: ground-truth folder (synthetic sessions), or None for real data.
        meshes_dir: the method's meshes (``<frame:06d>.ply``), for the Chamfer distance.
        session: session name (default: ``meta.json``'s).
        device: torch device for rendering held-out views.
        max_match_dist: gating distance of the bubble matching, metres.
        include_nucleation: compare bubble 0 (nucleation region) too.
        reference_camera: view of the 2D reference (default: the first input camera).
        fit_stage1_dir: the stage-1 fit (no refinement), scored like the final fit into
            ``metrics["stage1"]``.
        ablations: ``{name: fit folder}`` of ablation fits (e.g. ``no_sdf``), scored
            into ``metrics["ablations"][name]``.
        region_scale: bubble region = projected spheres of ``region_scale · r_eq``.
        compare_meshes: ``{name: meshes folder}`` of ``stage1`` or an ablation: with
            ground truth, their Chamfer distance goes into that fit's entry.
    """
    from surfphase.device import resolve_device

    ingest_dir, masks_dir, fit_dir, out_dir = map(Path, (ingest_dir, masks_dir, fit_dir, out_dir))
    data = read_session(ingest_dir, masks_dir)
    name = session or data["session"]
    fit_cols = ["frame", "bubble", "x", "y", "z", "vx", "vy", "vz"]
    ablations = {str(k): Path(v) for k, v in (ablations or {}).items()}
    compare_meshes = {str(k): Path(v) for k, v in (compare_meshes or {}).items()}
    for label, d in ablations.items():
        if not label or label in ("method", "baseline", "stage1"):
            raise ValueError(f"{d}: session {name}: ablation name {label!r} is not allowed")
    # Every fit's table first, so that a missing one fails before any long computation.
    method = read_table(fit_dir / "bubbles.csv", fit_cols, f"session {name}")
    others: dict[str, tuple[Path, pd.DataFrame]] = {}
    if fit_stage1_dir is not None:
        d = Path(fit_stage1_dir)
        others["stage1"] = (d, read_table(d / "bubbles.csv", fit_cols, f"session {name} stage 1"))
    for label, d in ablations.items():
        others[label] = (d, read_table(d / "bubbles.csv", fit_cols, f"session {name} {label}"))
    for label, d in compare_meshes.items():
        if label not in others:
            raise ValueError(
                f"{d}: session {name}: meshes of {label!r}, which is not a fit scored here "
                "(stage1 needs the stage-1 fit, an ablation its fit)"
            )
    base = bl.baseline_bubbles(data["cameras"], data["labels"], data["frames"], data["fps"])
    keep = (lambda df: df) if include_nucleation else (lambda df: df[df["bubble"] >= 1])
    metrics: dict = {
        "session": name,
        "frames": int(len(data["frames"])),
        "fps": data["fps"],
        "cameras": [c.name for c in data["cameras"]],
        "settings": {
            "max_match_dist_m": float(max_match_dist),
            "include_nucleation": bool(include_nucleation),
        },
    }
    # The baseline is compared on the frames the method reconstructed, so both errors in a
    # table average over the same frames (baseline_bubbles.csv keeps every frame).
    base_cmp = base[base["frame"].isin(method["frame"].unique())]
    metrics["settings"]["frames_compared"] = int(base_cmp["frame"].nunique())
    tables = []
    method_matches = None
    truth_by_mask_id = None
    truth = region_truth = None
    held: list[Camera] = []
    dev = str(resolve_device(device))
    if gt_dir is not None:
        gt_dir = Path(gt_dir)
        truth = read_table(gt_dir / "bubbles.csv", fit_cols, f"session {name}")
        region_truth = _truth_region_table(gt_dir, name)
        metrics["settings"]["region"] = (
            f"projected spheres of {region_scale:g}·r_eq around the true bubbles"
            if region_truth is not None
            else "none: the ground truth's bubbles.csv has no r_eq column"
        )
        metrics["velocity"] = {}
        for label, pred in (("method", method), ("baseline", base_cmp)):
            m = velocity.match_bubbles(keep(pred), truth, max_match_dist)
            metrics["velocity"][label] = velocity.velocity_errors(m)
            if label == "method":
                method_matches = m.copy()
            if label == "baseline":
                # The truth under the masks' bubble ids (through the baseline's matches),
                # to score the 2D reference itself.
                truth_by_mask_id = m[["frame", "bubble", "gt_vx", "gt_vy", "gt_vz"]].rename(
                    columns={"gt_vx": "vx", "gt_vy": "vy", "gt_vz": "vz"}
                )
            m.insert(0, "source", label)
            tables.append(m)
        gt_cams = load_cameras(gt_dir / "cameras.json")
        views_dir = gt_dir / "views"
        if views_dir.is_dir():
            held = [c for n, c in gt_cams.items() if (views_dir / n).is_dir()]
        if held:
            metrics["settings"]["heldout"] = heldout_protocol(gt_dir)
        metrics.update(_fit_heldout(fit_dir, held, gt_dir, dev, region_truth, region_scale))
        inputs = [gt_cams[c.name] for c in data["cameras"] if c.name in gt_cams]
        seen_by = inputs if len(inputs) == len(data["cameras"]) else None
        if meshes_dir is not None:
            metrics["chamfer_mm"] = chamfer_per_frame(
                Path(meshes_dir), gt_dir / "meshes", data["frames"].tolist(), cameras=seen_by
            )
    cams = {c.name: (c, lab) for c, lab in zip(data["cameras"], data["labels"], strict=True)}
    ref_name = reference_camera or data["cameras"][0].name
    if ref_name not in cams:
        raise ValueError(
            f"{ingest_dir}: session {name}: no camera {ref_name!r} for the 2D reference"
        )
    ref_cam, ref_lab = cams[ref_name]
    ref = reference2d.reference_velocities(ref_cam, ref_lab, data["frames"], data["fps"], base)
    metrics["reference2d"] = {"camera": ref_name}
    for label, pred in (("method", method), ("baseline", base_cmp)):
        res, rows = reference2d.compare_to_reference(keep(pred), ref, ref_cam)
        metrics["reference2d"][label] = res
        if gt_dir is None:
            rows.insert(0, "source", label)
            tables.append(rows)
    if truth_by_mask_id is not None:
        metrics["reference2d"]["truth"] = reference2d.compare_to_reference(
            truth_by_mask_id, ref, ref_cam
        )[0]
    # Stage 1 and the ablations: the same velocity, held-out and 2D-reference scores.
    for label, (d, pred) in others.items():
        res: dict = {"fit": str(d)}
        if truth is not None:
            m = velocity.match_bubbles(keep(pred), truth, max_match_dist)
            res["velocity"] = velocity.velocity_errors(m)
            m.insert(0, "source", label)
            tables.append(m)
            res.update(_fit_heldout(d, held, gt_dir, dev, region_truth, region_scale))
            if label in compare_meshes:
                res["chamfer_mm"] = chamfer_per_frame(
                    compare_meshes[label],
                    gt_dir / "meshes",
                    data["frames"].tolist(),
                    cameras=seen_by,
                )
        res["reference2d"] = reference2d.compare_to_reference(keep(pred), ref, ref_cam)[0]
        if label == "stage1":
            metrics["stage1"] = res
        else:
            metrics.setdefault("ablations", {})[label] = res
    # Per-bubble sizes from the meshes, beside the fit's positions and velocities.
    size_csv = Path(meshes_dir) / "bubble_sizes.csv" if meshes_dir is not None else None
    sizes_in = pd.read_csv(size_csv) if size_csv is not None and size_csv.is_file() else None
    with_sizes = sizes.bubble_sizes_table(method, sizes_in)
    truth_r = None
    if gt_dir is not None:
        gt_table = pd.read_csv(Path(gt_dir) / "bubbles.csv")
        truth_r = gt_table[["frame", "bubble", "r_eq"]] if "r_eq" in gt_table else None
    metrics["sizes"] = sizes.size_metrics(with_sizes, method_matches, truth_r)
    metrics = _finite(metrics)
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "bubbles.csv", with_sizes.to_csv(index=False, float_format="%.9g"))
    atomic_write_text(out_dir / "baseline_bubbles.csv", base.to_csv(index=False))
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    atomic_write_text(out_dir / "velocity_table.csv", table.to_csv(index=False))
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def _fit_heldout(
    fit_dir: Path,
    held: Sequence[Camera],
    gt_dir: Path,
    device: str,
    region_truth: pd.DataFrame | None,
    region_scale: float,
) -> dict:
    """``{"heldout": …}`` (:func:`heldout_metrics` of ``fit_dir/surfels.npz`` under
    :func:`heldout_protocol`) and, when that protocol is not the recorded views over the
    input backgrounds, ``"heldout_whole"`` (the recorded views, the whole image
    predicted); ``{}`` without surfels or held-out cameras."""
    surfels_path = fit_dir / "surfels.npz"
    if not held or not surfels_path.exists():
        return {}
    from surfphase.fit.outputs import load_surfels

    surfels = load_surfels(surfels_path)
    views, backdrops = _heldout_sources(gt_dir)
    out = {
        "heldout": heldout_metrics(
            surfels, held, views, device, region_truth, region_scale, backdrops
        )
    }
    if (views, backdrops) != (gt_dir / "views", None):
        out["heldout_whole"] = heldout_metrics(
            surfels, held, gt_dir / "views", device, region_truth, region_scale
        )
    return out


def _heldout_sources(gt_dir: Path) -> tuple[Path, Path | None]:
    """(views compared with, backdrops folder or None) of the held-out protocol."""
    clean, backdrops = gt_dir / "views_clean", gt_dir / "views_background"
    if clean.is_dir() and backdrops.is_dir():
        return clean, backdrops
    return gt_dir / "views", None


def heldout_protocol(gt_dir: Path) -> str:
    """One line saying what the held-out figures of ``gt_dir`` compare."""
    views, backdrops = _heldout_sources(Path(gt_dir))
    if backdrops is not None:
        return (
            "heldout: the reconstructed bubbles over each held-out camera's reference frame "
            "(views_background), against the noiseless views (views_clean); heldout_whole: "
            "the whole image predicted (the input views' mean background behind the "
            "bubbles), against the recorded views"
        )
    return (
        "heldout: the reconstructed bubbles over the input views' mean background, against "
        "the recorded views"
    )


def campaign_table(metrics: Sequence[dict]) -> pd.DataFrame:
    """One row per session: the metrics JSONs flattened (``velocity.method.relative_error``
    …), session first, then velocity (method beside baseline, stage 1 and the ablations),
    held-out means (full frame, then the bubbles' region), Chamfer and the 2D reference;
    per-frame Chamfer values are left out, and so are the per-camera held-out values of
    stage 1 and the ablations (their means stay)."""
    flat = []
    for m in metrics:
        m = dict(m)
        if isinstance(m.get("chamfer_mm"), dict):
            m["chamfer_mm"] = {k: v for k, v in m["chamfer_mm"].items() if k != "per_frame"}
        m.pop("cameras", None)
        if isinstance(m.get("stage1"), dict):
            m["stage1"] = _means_only(m["stage1"])
        if isinstance(m.get("ablations"), dict):
            m["ablations"] = {k: _means_only(v) for k, v in m["ablations"].items()}
        flat.append(m)
    df = pd.json_normalize(flat, sep=".")
    # Column groups in order, as regular expressions matched at the start of a name.
    order = [
        r"session$", r"velocity\.", r"stage1\.velocity\.", r"ablations\.[^.]+\.velocity\.",
        r"heldout\.mean\.(?!region)", r"stage1\.heldout\.mean\.(?!region)",
        r"ablations\.[^.]+\.heldout\.mean\.(?!region)", r"heldout\.mean\.region\.",
        r"stage1\.heldout\.mean\.region\.", r"ablations\.[^.]+\.heldout\.mean\.region\.",
        r"heldout_whole\.mean\.", r"stage1\.heldout_whole\.mean\.",
        r"ablations\.[^.]+\.heldout_whole\.mean\.",
        r"chamfer_mm\.", r"stage1\.chamfer_mm\.", r"ablations\.[^.]+\.chamfer_mm\.",
        r"reference2d\.", r"stage1\.reference2d\.",
        r"ablations\.[^.]+\.reference2d\.", r"heldout\.", r"heldout_whole\.",
    ]  # fmt: skip
    cols: list[str] = []
    for group in order:
        pat = re.compile(group)
        cols += [c for c in df.columns if pat.match(c) and c not in cols]
    cols += [c for c in df.columns if c not in cols]
    return df[cols]


def _means_only(fit_metrics: dict) -> dict:
    """A stage-1 / ablation entry without its per-camera held-out values."""
    out = dict(fit_metrics)
    for key in ("heldout", "heldout_whole"):
        if isinstance(out.get(key), dict):
            out[key] = {k: v for k, v in out[key].items() if k == "mean"}
    if isinstance(out.get("chamfer_mm"), dict):
        out["chamfer_mm"] = {k: v for k, v in out["chamfer_mm"].items() if k != "per_frame"}
    return out
