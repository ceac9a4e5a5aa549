"""Held-out views of one session: the fit rendered into cameras it was not fitted to,
scored against their images (L1, PSNR, SSIM; full frame and the bubbles' region).

The ground-truth folder of a synthetic session holds ``views/<cam>/<frame:06d>.png``
(held-out views as recorded), optionally ``views_clean/`` (the same without sensor noise)
and ``views_background/<cam>.png`` (each held-out camera's reference frame without
bubbles); :func:`heldout_protocol` says which of them a figure compares.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.cameras import Camera
from surfphase.eval import image_metrics, regions
from surfphase.folders.fit import SURFELS, read_fit_surfels

METRIC_KEYS = ("l1", "psnr", "ssim")


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
    out = {k: nanmean([v[k] for v in vals]) for k in METRIC_KEYS}
    out["frames"] = len(vals)
    if vals and "pixels" in vals[0]:
        out["pixels"] = float(np.mean([v["pixels"] for v in vals]))
    return out


def _mean_over(items) -> dict:
    items = list(items)
    return {k: nanmean([i[k] for i in items]) for k in METRIC_KEYS}


def nanmean(values: Sequence[float]) -> float:
    """Mean of the finite-or-infinite values, NaNs left out; NaN if there are none."""
    v = np.asarray(values, dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def fit_heldout(
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
    if not held or not (fit_dir / SURFELS).exists():
        return {}
    surfels = read_fit_surfels(fit_dir)
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
