"""Image metrics of a rendered view against the observed one: L1, PSNR and SSIM.

Images are float arrays in ``[0, data_range]`` of shape (H, W) or (H, W, C). SSIM uses
the standard 11×11 Gaussian window, σ = 1.5 pixels (Wang et al. 2004), with
``K1 = 0.01``, ``K2 = 0.03``, population (not sample) covariances, evaluated where the
window lies wholly inside the image and averaged over those positions and the channels;
this equals scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False)``.

Region metrics (:func:`region_metrics`) restrict the same quantities to a boolean pixel
mask (e.g. the projected bubbles): L1 and the PSNR's MSE average over the masked pixels
(and channels); the region SSIM is the mean of the SSIM map over the masked pixels whose
11×11 window lies wholly inside the image (the positions the full-frame SSIM averages),
which equals averaging scikit-image's ``structural_similarity(full=True)`` map over the
same pixels.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import correlate1d

#: SSIM window: 11 taps (radius 5 pixels), Gaussian σ = 1.5 pixels.
SSIM_RADIUS = 5
SSIM_SIGMA = 1.5


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if a.ndim not in (2, 3):
        raise ValueError(f"expected (H, W) or (H, W, C) images, got shape {a.shape}")
    return a, b


def l1(pred: np.ndarray, target: np.ndarray) -> float:
    """Mean absolute difference over all pixels and channels (image units)."""
    a, b = _pair(pred, target)
    return float(np.mean(np.abs(a - b)))


def psnr(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB: ``10·log10(data_range² / MSE)``; ``inf`` if equal."""
    a, b = _pair(pred, target)
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))


def gaussian_window(radius: int = SSIM_RADIUS, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """(2·radius + 1,) normalised 1D Gaussian taps; the 2D window is their outer product."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _local_mean(img: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Gaussian-weighted mean over each fully inside window: (H, W) → (H−2r, W−2r)."""
    r = (w.size - 1) // 2
    out = correlate1d(img, w, axis=0, mode="constant")[r : img.shape[0] - r]
    return correlate1d(out, w, axis=1, mode="constant")[:, r : img.shape[1] - r]


def ssim_map(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> np.ndarray:
    """Per-position SSIM of two (H, W) images: (H − 10, W − 10) for the 11×11 window."""
    a, b = _pair(pred, target)
    if a.ndim != 2:
        raise ValueError(f"ssim_map takes one channel (H, W), got shape {a.shape}")
    w = gaussian_window()
    if min(a.shape) < w.size:
        raise ValueError(f"images of shape {a.shape} are smaller than the {w.size}-pixel window")
    mu_a, mu_b = _local_mean(a, w), _local_mean(b, w)
    var_a = _local_mean(a * a, w) - mu_a**2
    var_b = _local_mean(b * b, w) - mu_b**2
    cov = _local_mean(a * b, w) - mu_a * mu_b
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    return num / den


def ssim(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> float:
    """Mean SSIM (dimensionless, ≤ 1) of (H, W) or (H, W, C) images; channels averaged."""
    a, b = _pair(pred, target)
    if a.ndim == 2:
        return float(ssim_map(a, b, data_range).mean())
    return float(
        np.mean([ssim_map(a[..., c], b[..., c], data_range).mean() for c in range(a.shape[2])])
    )


def image_metrics(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> dict:
    """``{"l1", "psnr", "ssim"}`` of one rendered image against its target."""
    return {
        "l1": l1(pred, target),
        "psnr": psnr(pred, target, data_range),
        "ssim": ssim(pred, target, data_range),
    }


def _region(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) bool mask checked against an (H, W[, C]) image."""
    m = np.asarray(mask, dtype=bool)
    if m.shape != a.shape[:2]:
        raise ValueError(f"mask of shape {m.shape} does not match images of shape {a.shape}")
    if not m.any():
        raise ValueError("the region mask is empty")
    return m


def masked_l1(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    """Mean absolute difference over the pixels where ``mask`` (H, W) is true, all
    channels (image units)."""
    a, b = _pair(pred, target)
    m = _region(a, mask)
    return float(np.mean(np.abs(a[m] - b[m])))


def masked_psnr(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray, data_range: float = 1.0
) -> float:
    """PSNR in dB with the MSE taken over the masked pixels (all channels); ``inf`` if
    they are equal."""
    a, b = _pair(pred, target)
    m = _region(a, mask)
    mse = float(np.mean((a[m] - b[m]) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))


def masked_ssim(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray, data_range: float = 1.0
) -> float:
    """Mean of the SSIM map over the masked pixels whose window lies inside the image;
    channels averaged; NaN if the mask has no such pixel (it hugs the border)."""
    a, b = _pair(pred, target)
    m = _region(a, mask)
    r = SSIM_RADIUS
    inner = m[r : m.shape[0] - r, r : m.shape[1] - r]
    if not inner.any():
        return float("nan")
    chans = [(a, b)] if a.ndim == 2 else [(a[..., c], b[..., c]) for c in range(a.shape[2])]
    return float(np.mean([ssim_map(x, y, data_range)[inner].mean() for x, y in chans]))


def region_metrics(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray, data_range: float = 1.0
) -> dict:
    """``{"l1", "psnr", "ssim", "pixels"}`` of one image restricted to ``mask`` (H, W)."""
    return {
        "l1": masked_l1(pred, target, mask),
        "psnr": masked_psnr(pred, target, mask, data_range),
        "ssim": masked_ssim(pred, target, mask, data_range),
        "pixels": int(np.count_nonzero(mask)),
    }
