"""Region metrics: masked L1/PSNR/SSIM against scikit-image and hand computation; the
bubbles' region (projected spheres) against the analytic silhouette of a sphere and
against projected surface points."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from skimage.metrics import structural_similarity

from surfphase.cameras import look_at
from surfphase.eval import image_metrics, regions


def _pair(shape, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    b = np.clip(a + 0.1 * rng.standard_normal(shape), 0, 1)
    return a, b


def _disk(shape, cx, cy, r):
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


@pytest.mark.parametrize("channels", [None, 3])
def test_masked_ssim_matches_skimage_map(channels):
    shape = (40, 48) if channels is None else (40, 48, channels)
    a, b = _pair(shape, seed=2)
    # A disk in the middle plus one that runs over the left border: the border pixels
    # (window not inside the image) are left out, as in the full-frame SSIM.
    mask = _disk(shape, 25, 18, 8) | _disk(shape, 2, 30, 6)
    _, full = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
        channel_axis=2 if channels else None, full=True,
    )  # fmt: skip
    inner = np.zeros_like(mask)
    inner[5:-5, 5:-5] = True
    sel = mask & inner
    ref = full[sel].mean()  # over pixels (and channels, when present)
    assert image_metrics.masked_ssim(b, a, mask) == pytest.approx(ref, abs=1e-10)
    # The whole frame as the region gives the full-frame SSIM.
    everything = np.ones(shape[:2], bool)
    assert image_metrics.masked_ssim(b, a, everything) == pytest.approx(
        image_metrics.ssim(b, a), abs=1e-12
    )
    # A region inside the 5-pixel border only has no SSIM.
    edge = np.zeros(shape[:2], bool)
    edge[:3, :] = True
    assert np.isnan(image_metrics.masked_ssim(b, a, edge))


def test_masked_psnr_and_l1_by_hand():
    target = np.full((10, 12), 0.5)
    pred = target.copy()
    mask = np.zeros((10, 12), bool)
    mask[2:4, 3:7] = True  # 8 pixels
    pred[2, 3:7] += 0.2  # 4 of them off by 0.2, the other 4 exact
    pred[8, 8] = 1.0  # outside the region: ignored
    # MSE = 4·0.04 / 8 = 0.02 → PSNR = 10·log10(1 / 0.02) = 16.9897 dB; L1 = 0.1.
    assert image_metrics.masked_psnr(pred, target, mask) == pytest.approx(
        10 * np.log10(50.0), abs=1e-12
    )
    assert image_metrics.masked_l1(pred, target, mask) == pytest.approx(0.1, abs=1e-12)
    m = image_metrics.region_metrics(pred, target, mask)
    assert m["pixels"] == 8 and m["psnr"] == pytest.approx(16.9897, abs=1e-4)
    # data_range scales the peak: 2 → +6.02 dB
    assert image_metrics.masked_psnr(pred, target, mask, 2.0) == pytest.approx(
        10 * np.log10(200.0), abs=1e-12
    )
    same = np.zeros((10, 12), bool)
    same[6:8, 0:2] = True
    assert image_metrics.masked_psnr(pred, target, same) == np.inf
    with pytest.raises(ValueError, match="empty"):
        image_metrics.masked_l1(pred, target, np.zeros((10, 12), bool))
    with pytest.raises(ValueError, match="does not match"):
        image_metrics.masked_psnr(pred, target, np.ones((10, 11), bool))


def test_sphere_silhouette_on_axis_is_the_analytic_disk():
    f, size = 400.0, 160
    cam = look_at("c", [0.0, 0.0, 0.05], [0.0, 0.0, 0.0], f, size, size)
    R, d = 2e-3, 0.05
    mask = regions.sphere_silhouettes(cam, [[0.0, 0.0, 0.0]], [R])
    # Silhouette of a sphere on the optical axis: a disk of radius f·R/√(d² − R²).
    r_px = f * R / np.sqrt(d * d - R * R)
    cx, cy = cam.K[0, 2], cam.K[1, 2]
    ref = _disk((size, size), cx, cy, r_px)
    assert abs(int(mask.sum()) - int(ref.sum())) <= 4
    assert np.count_nonzero(mask ^ ref) <= 0.02 * ref.sum()
    # a sphere behind the camera is not seen; a camera inside a sphere sees only it
    assert not regions.sphere_silhouettes(cam, [[0, 0, 0.1]], [R]).any()
    assert regions.sphere_silhouettes(cam, [[0, 0, 0.05]], [R]).all()


def test_bubble_region_holds_the_projected_spheres():
    cam = look_at("c", [0.02, 0.01, 0.045], [0.0, 0.005, 0.0], 300.0, 128, 96)
    truth = pd.DataFrame(
        {"frame": [3, 3, 4], "x": [-2e-3, 3e-3, 0.0], "y": [4e-3, 8e-3, 5e-3],
         "z": [0.0, 1e-3, 0.0], "r_eq": [0.6e-3, 1.0e-3, 0.8e-3]}
    )  # fmt: skip
    masks = regions.region_masks(cam, truth, [3, 4, 5], scale=1.5)
    assert sorted(masks) == [3, 4]  # frame 5 has no bubble
    rng = np.random.default_rng(0)
    for f, mask in masks.items():
        rows = truth[truth.frame == f]
        for _, b in rows.iterrows():
            # points on the sphere of radius 1.2·r_eq project inside; points whose rays miss
            # every region sphere (1.5·r_eq) by 25 % project outside
            dirs = rng.normal(size=(400, 3))
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            c = b[["x", "y", "z"]].to_numpy(float)
            uv = np.round(cam.project(c + 1.2 * b.r_eq * dirs)).astype(int)
            assert mask[uv[:, 1], uv[:, 0]].all()
        centres = rows[["x", "y", "z"]].to_numpy(float)
        dirs = rng.normal(size=(2000, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        b0 = rows.iloc[0]
        pts = b0[["x", "y", "z"]].to_numpy(float) + 2.5 * b0.r_eq * dirs
        # keep the points whose rays miss every region sphere by a margin
        ray = pts - cam.center
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        rel = centres - cam.center  # (B, 3)
        along = np.einsum("nk,bk->nb", ray, rel)
        miss = np.sqrt((rel**2).sum(-1)[None] - along**2) > 1.5 * rows.r_eq.to_numpy() * 1.25
        uv = np.round(cam.project(pts[miss.all(axis=1)])).astype(int)
        assert len(uv) > 100 and not mask[uv[:, 1], uv[:, 0]].any()
    with pytest.raises(ValueError, match="scale"):
        regions.bubble_region(cam, truth, scale=0.0)
