"""The background images the fit composites its surfels over: ``I = C + (1 − α)·B_c``.

Only the bubbles are reconstructed. The rest of each input view (backlight, heated
plate) is a per-view background image: by default the per-pixel temporal median of the
pixels the masks call background (``fit: background``, see
:data:`surfphase.fit.params.DEFAULTS`).
"""

from __future__ import annotations

import warnings

import numpy as np

from surfphase.fit.session import SessionData


def background_median(x: np.ndarray) -> np.ndarray:
    """Per-pixel median over time of (K, H, W[, D]) frames whose non-background entries
    are NaN: (H, W[, D]), NaN where a pixel is never background."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: the caller fills
        return np.nanmedian(x, axis=0)


def fill_nearest(image: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """``image`` (H, W[, D]) with each ``missing`` pixel ((H, W) bool, not all of them)
    taking the value of the nearest pixel that is not (Euclidean distance)."""
    from scipy import ndimage

    _, (ri, ci) = ndimage.distance_transform_edt(missing, return_indices=True)
    return image[ri, ci]


def estimate_backgrounds(data: SessionData, n_frames: int, max_frames: int = 64) -> np.ndarray:
    """Per-view background images (C, H, W, D) in [0, 1]: the per-pixel median over time of
    the pixels the masks call background (backlight, plate, static dirt); pixels that are
    never background take the nearest background pixel's value."""
    idx = np.unique(np.linspace(0, n_frames - 1, min(n_frames, max_frames)).round().astype(int))
    imgs = np.stack([data.images(t) for t in idx])  # (K, C, H, W, D)
    labs = np.stack([np.stack(data.labels(t)) for t in idx])  # (K, C, H, W)
    out = np.empty(imgs.shape[1:], dtype=np.float32)
    for c in range(imgs.shape[1]):
        med = background_median(np.where((labs[:, c] < 0)[..., None], imgs[:, c], np.nan))
        missing = np.isnan(med[..., 0])
        if missing.all():
            med = np.broadcast_to(np.median(imgs[:, c], axis=(0, 1, 2)), med.shape).copy()
        elif missing.any():
            med = fill_nearest(med, missing)
        out[c] = med
    return out


def input_backgrounds(data: SessionData, n_frames: int, p: dict) -> np.ndarray:
    """(C, H, W, D) float32 background images of the input views over the first
    ``n_frames`` frames (see ``background`` in DEFAULTS)."""
    bg = p["background"]
    C, H, W = len(data.cameras), data.height, data.width
    D = data.images(0).shape[-1]
    if isinstance(bg, str):
        if bg not in ("images", "constant"):
            raise ValueError(
                f"fit: background must be 'images', 'constant' or a number, not {bg!r}"
            )
        imgs = estimate_backgrounds(data, n_frames)
        if bg == "constant":
            imgs = np.broadcast_to(np.median(imgs, axis=(0, 1, 2)), imgs.shape).copy()
        return imgs.astype(np.float32)
    return np.full((C, H, W, D), float(bg), dtype=np.float32)
