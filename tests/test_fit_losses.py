"""Losses and the SDF→opacity map of the stage-1 fit, against independent references."""

from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import structural_similarity

from surfphase.cameras import look_at
from surfphase.fit import losses
from surfphase.fit.model import (
    HALF_OPACITY_GF,
    SurfelModel,
    normal_to_quat,
    sdf_to_opacity,
    surfel_normals,
)
from surfphase.render import camera_tensors


def test_sdf_to_opacity_matches_formula_and_half_point():
    f = torch.linspace(-3, 3, 61, dtype=torch.float64)
    gamma = 2.5
    ref = 4 * np.exp(-gamma * f.numpy()) / (1 + np.exp(-gamma * f.numpy())) ** 2
    np.testing.assert_allclose(sdf_to_opacity(f, gamma).numpy(), ref, rtol=1e-12)
    assert float(sdf_to_opacity(torch.tensor(0.0), gamma)) == 1.0
    half = torch.tensor(HALF_OPACITY_GF / gamma, dtype=torch.float64)
    assert abs(float(sdf_to_opacity(half, gamma)) - 0.5) < 1e-12
    # Large |γf| must not overflow to NaN.
    assert torch.isfinite(sdf_to_opacity(torch.tensor([1e4, -1e4]), 10.0)).all()


def test_ssim_matches_scikit_image_away_from_border():
    rng = np.random.default_rng(0)
    a = rng.random((40, 36))
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    _, ref = structural_similarity(
        a,
        b,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        full=True,
    )
    ours = losses.ssim_map(
        torch.as_tensor(a)[None, :, :, None], torch.as_tensor(b)[None, :, :, None]
    )[0, :, :, 0].numpy()
    np.testing.assert_allclose(ours[5:-5, 5:-5], ref[5:-5, 5:-5], atol=1e-10)
    same = torch.as_tensor(a)[None, :, :, None]
    assert abs(float(losses.ssim(same, same)) - 1.0) < 1e-12


def test_photometric_loss_is_sum_over_views_of_l1_dssim_mix():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 16, 16, 1, generator=g, dtype=torch.float64)
    y = torch.rand(2, 16, 16, 1, generator=g, dtype=torch.float64)
    loss_v, l1_v, _ = losses.photometric_terms(x, y, 0.2)
    loss, l1v = loss_v.sum(), l1_v.mean()
    ref = sum(
        0.8 * (x[c] - y[c]).abs().mean() + 0.2 * (1 - losses.ssim(x[c : c + 1], y[c : c + 1]))
        for c in range(2)
    )
    assert abs(float(loss) - float(ref)) < 1e-12
    assert abs(float(l1v) - float((x - y).abs().mean())) < 1e-12


def test_photometric_loss_is_the_sum_of_the_terms_bit_for_bit():
    """The PyTorch backend (the reference of the fused one, tests/test_fit_losses_fused.py)."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(3, 20, 18, 2, generator=g).requires_grad_()
    y = torch.rand(3, 20, 18, 2, generator=g)
    loss = losses.photometric_terms(x, y, 0.3, backend="torch")[0].sum()
    (gx,) = torch.autograd.grad(loss, x)
    # The formula written out, as the loss of the views summed.
    l1_v = (x - y).abs().flatten(1).mean(dim=1)
    dssim_v = 1.0 - losses.ssim_map(x, y).flatten(1).mean(dim=1)
    ref = ((1 - 0.3) * l1_v + 0.3 * dssim_v).sum()
    (gref,) = torch.autograd.grad(ref, x)
    assert torch.equal(loss, ref) and torch.equal(gx, gref)
    loss_v, l1_t, ds_t = losses.photometric_terms(x, y, 0.3, backend="torch")
    assert (
        torch.equal(loss_v.sum(), loss) and torch.equal(l1_t, l1_v) and torch.equal(ds_t, dssim_v)
    )


def test_normal_consistency_zero_when_aligned_one_when_orthogonal():
    n = torch.zeros(1, 4, 4, 3)
    n[..., 2] = 1
    assert float(losses.normal_consistency(n, n)) == 0.0
    m = torch.zeros(1, 4, 4, 3)
    m[..., 0] = 1
    assert float(losses.normal_consistency(n, m)) == 1.0
    alpha = torch.zeros(1, 4, 4, 1)
    assert float(losses.normal_consistency(n, n, alpha)) == 1.0  # empty pixels: ñ = 0


def test_gamma_hinge_target_and_gradient():
    f = torch.tensor([0.1, -0.2, 0.4, -0.05, 0.3])
    target = HALF_OPACITY_GF / 0.2
    assert abs(float(losses.gamma_target(f)) - target) < 1e-5
    g = torch.tensor(2.0, requires_grad=True)
    loss = losses.gamma_hinge(g, f)
    loss.backward()
    assert abs(float(loss.detach()) - (target - 2.0)) < 1e-5 and float(g.grad) == -1.0
    assert float(losses.gamma_hinge(torch.tensor(target + 1), f)) == 0.0


def test_normal_quaternion_round_trip():
    g = torch.Generator().manual_seed(1)
    n = torch.randn(50, 3, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    n[0] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    np.testing.assert_allclose(surfel_normals(normal_to_quat(n)).numpy(), n.numpy(), atol=1e-12)


def test_projection_loss_uses_zero_level_points_and_threshold():
    cam = look_at("c", [0, 0, 0.06], [0, 0, 0], fx=100.0, width=32, height=32)
    view, K = camera_tensors([cam], "cpu", torch.float64)
    # Rendered depth: a fronto-parallel plane at camera depth 0.06 m (world z = 0).
    depth = torch.full((1, 32, 32, 1), 0.06, dtype=torch.float64)
    L = 0.01
    # Surfels 1 mm in front of the plane (world +z is towards the camera), facing it,
    # with f = +1 mm: μ − f·n lands on the plane → zero loss.
    mu = torch.tensor([[0.0, 0.0, 0.001], [0.001, 0.0005, 0.001]], dtype=torch.float64)
    normals = torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64)
    model = SurfelModel.from_points(
        mu, normals, torch.ones(2, 1, dtype=torch.float64), 1e-4, extent=L, init_sdf=0.1
    )
    with torch.no_grad():
        model.params["sdf"].fill_(0.001 / L)
    pts = model.zero_level_points()
    assert float(losses.projection_loss(pts, depth, view, K, L, 0.1).detach()) < 1e-12
    # With f = 0 the error is 1 mm = 0.1 L: kept at threshold 0.15, ignored at 0.05.
    err = losses.projection_loss(mu, depth, view, K, L, 0.15)
    assert abs(float(err) - 0.1) < 1e-9
    assert float(losses.projection_loss(mu, depth, view, K, L, 0.05)) == 0.0
    # Gradient flows to f through μ − f·n.
    with torch.no_grad():
        model.params["sdf"].fill_(0.0005 / L)
    losses.projection_loss(model.zero_level_points(), depth, view, K, L, 0.15).backward()
    assert model.params["sdf"].grad is not None and (model.params["sdf"].grad != 0).all()


def test_psnr_reference():
    a = torch.zeros(1, 4, 4, 1)
    b = torch.full((1, 4, 4, 1), 0.1)
    assert abs(losses.psnr(a, b) - 20.0) < 1e-6
    assert math.isfinite(losses.psnr(a, a))
