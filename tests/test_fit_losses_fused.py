"""The fused (numba) photometric term against the PyTorch one, scikit-image and itself."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from surfphase.fit import losses
from surfphase.fit.fused_losses import photometric_fused


def _images(shape, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(*shape, generator=g, dtype=dtype)
    y = (x + 0.2 * torch.randn(*shape, generator=g, dtype=dtype)).clamp(0, 1)
    return x.requires_grad_(), y


@pytest.mark.parametrize("shape", [(3, 20, 17, 2), (2, 4, 6, 1), (1, 13, 1, 3)])
def test_fused_matches_torch_values_and_gradients_float64(shape):
    """Every output and the gradient of a weighted sum of all three, to ~1e-12; images
    smaller than the 11-tap window included (zero padding on both sides of a row)."""
    x, y = _images(shape, seed=sum(shape))
    # Pixels where x = y: the subgradient of |x − y| there is 0, as torch's.
    with torch.no_grad():
        x[0, 0, :2] = y[0, 0, :2]
    w = torch.rand(3, shape[0], generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    fused = photometric_fused(x, y, 0.3)
    ref = losses.photometric_terms(x, y, 0.3, backend="torch")
    for a, b in zip(fused, ref, strict=True):
        assert a.dtype == torch.float64 and a.shape == (shape[0],)
        np.testing.assert_allclose(a.detach().numpy(), b.detach().numpy(), rtol=0, atol=1e-12)
    (ga,) = torch.autograd.grad(sum((wi * t).sum() for wi, t in zip(w, fused, strict=True)), x)
    (gb,) = torch.autograd.grad(sum((wi * t).sum() for wi, t in zip(w, ref, strict=True)), x)
    np.testing.assert_allclose(ga.numpy(), gb.numpy(), rtol=0, atol=1e-12)
    assert float(gb.abs().max()) > 1e-4  # the comparison is not of zeros


def test_fused_float32_within_rounding_of_torch():
    """float32 images (the fit's): float64 inside, so within float32 rounding."""
    x, y = _images((2, 24, 20, 1), seed=5, dtype=torch.float32)
    fused = photometric_fused(x, y, 0.2)
    ref = losses.photometric_terms(x, y, 0.2, backend="torch")
    for a, b in zip(fused, ref, strict=True):
        assert a.dtype == torch.float32
        np.testing.assert_allclose(a.detach().numpy(), b.detach().numpy(), rtol=0, atol=2e-6)
    (ga,) = torch.autograd.grad(fused[0].sum(), x)
    (gb,) = torch.autograd.grad(ref[0].sum(), x)
    assert ga.dtype == torch.float32
    np.testing.assert_allclose(ga.numpy(), gb.numpy(), rtol=0, atol=1e-8)


def test_fused_gradcheck():
    x, y = _images((2, 9, 8, 2), seed=3)

    def f(t):
        loss_v, l1_v, dssim_v = photometric_fused(t, y, 0.4)
        return loss_v, l1_v, dssim_v

    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-8)


def test_fused_dssim_matches_scikit_image():
    """With a band of 5 zero pixels around both images, zero padding (ours) and
    scikit-image's reflection see the same window at every pixel, so the mean over the
    whole full SSIM map of ``structural_similarity`` (Gaussian window σ = 1.5, population
    statistics) is the view's ``1 − D-SSIM``; L1 against numpy."""
    rng = np.random.default_rng(2)
    K, H, W, D = 2, 30, 26, 2
    a = np.zeros((K, H, W, D))
    b = np.zeros((K, H, W, D))
    a[:, 5:-5, 5:-5] = rng.random((K, H - 10, W - 10, D))
    b[:, 5:-5, 5:-5] = np.clip(
        a[:, 5:-5, 5:-5] + 0.1 * rng.standard_normal((K, H - 10, W - 10, D)), 0, 1
    )
    _, l1_v, dssim_v = photometric_fused(torch.as_tensor(a), torch.as_tensor(b))
    for k in range(K):
        maps = [
            structural_similarity(
                a[k, ..., d], b[k, ..., d], gaussian_weights=True, sigma=1.5,
                use_sample_covariance=False, data_range=1.0, full=True,
            )[1]
            for d in range(D)
        ]  # fmt: skip
        assert abs(float(dssim_v[k]) - (1 - np.mean(maps))) < 1e-10
        assert abs(float(l1_v[k]) - np.abs(a[k] - b[k]).mean()) < 1e-14
    same = torch.as_tensor(a)
    assert float(photometric_fused(same, same)[2].abs().max()) < 1e-14


def test_fused_same_bits_for_one_and_two_threads():
    x, y = _images((3, 37, 29, 1), seed=7, dtype=torch.float32)
    threads = torch.get_num_threads()
    runs = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            out = photometric_fused(x, y, 0.2)
            (gx,) = torch.autograd.grad(out[0].sum() + out[1][1], x)
            runs.append([*out, gx])
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(*runs, strict=True):
        assert torch.equal(a, b)


def test_auto_backend_and_refusals():
    """``auto`` takes the fused kernels on the CPU and PyTorch's ops when the observed
    image needs a gradient (which the kernels do not compute); bad calls say why."""
    x, y = _images((1, 8, 8, 1), seed=11)
    auto = losses.photometric_terms(x, y)
    assert type(auto[0].grad_fn).__name__.startswith("_Photometric")
    y.requires_grad_()
    assert "Photometric" not in type(losses.photometric_terms(x, y)[0].grad_fn).__name__
    with pytest.raises(ValueError, match="observed image"):
        photometric_fused(x, y)
    with pytest.raises(ValueError, match="one shape"):
        photometric_fused(x, y.detach()[:, :4])
    with pytest.raises(ValueError, match="unknown backend"):
        losses.photometric_terms(x, y, backend="gpu")


def _normal_maps(shape, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(*shape, 3, generator=g, dtype=dtype), dim=-1)
    nd = torch.nn.functional.normalize(torch.randn(*shape, 3, generator=g, dtype=dtype), dim=-1)
    alpha = torch.rand(*shape, 1, generator=g, dtype=dtype)
    return n.requires_grad_(), nd.requires_grad_(), alpha


@pytest.mark.parametrize("with_alpha", [True, False])
def test_fused_normal_consistency_matches_torch(with_alpha):
    n, nd, alpha = _normal_maps((2, 11, 9), seed=4)
    a = alpha if with_alpha else None
    fused = losses.normal_consistency(n, nd, a, backend="fused")
    ref = losses.normal_consistency(n, nd, a, backend="torch")
    assert abs(float(fused.detach()) - float(ref.detach())) < 1e-12
    for ga, gb in zip(
        torch.autograd.grad(fused, (n, nd)), torch.autograd.grad(ref, (n, nd)), strict=True
    ):
        np.testing.assert_allclose(ga.numpy(), gb.numpy(), rtol=0, atol=1e-14)
    f32 = [t.detach().float().requires_grad_() for t in (n, nd)]
    v32 = losses.normal_consistency(*f32, None if a is None else a.float(), backend="fused")
    assert v32.dtype == torch.float32 and abs(float(v32.detach()) - float(ref.detach())) < 1e-6
    assert torch.autograd.gradcheck(
        lambda p, q: losses.normal_consistency(p, q, a, backend="fused"), (n, nd)
    )


def _projection_scene(dtype=torch.float64):
    """Two views of points around the origin over a rendered depth ~0.1 m, with an empty
    band (depth 0), points outside the images and points beyond the threshold."""
    from surfphase.cameras import look_at
    from surfphase.render import camera_tensors

    cams = [
        look_at("a", [0, 0, 0.1], [0, 0, 0], fx=200.0, width=40, height=30),
        look_at("b", [0.1, 0, 0.01], [0, 0, 0], fx=180.0, width=40, height=30),
    ]
    viewmats, Ks = camera_tensors(cams, "cpu", dtype)
    g = torch.Generator().manual_seed(6)
    pts = 0.012 * torch.randn(400, 3, generator=g, dtype=dtype)
    depth = 0.1 + 0.003 * torch.rand(2, 30, 40, 1, generator=g, dtype=dtype)
    depth[:, :6] = 0.0
    return pts.requires_grad_(), depth, viewmats, Ks


def test_fused_projection_loss_matches_torch():
    pts, depth, viewmats, Ks = _projection_scene()
    kept = []
    for thr in (0.1, 0.02):
        fused = losses.projection_loss(pts, depth, viewmats, Ks, 0.02, thr, backend="fused")
        ref = losses.projection_loss(pts, depth, viewmats, Ks, 0.02, thr, backend="torch")
        assert abs(float(fused.detach()) - float(ref.detach())) < 1e-12 and float(ref.detach()) > 0
        (ga,) = torch.autograd.grad(fused, pts)
        (gb,) = torch.autograd.grad(ref, pts)
        np.testing.assert_allclose(ga.numpy(), gb.numpy(), rtol=0, atol=1e-12)
        kept.append(int((gb != 0).any(dim=1).sum()))
        assert int((gb == 0).all(dim=1).sum()) > 20  # points not kept in either view
    assert kept[0] > 20 and 0 < kept[1] < kept[0]
    # Nothing kept: 0, with a zero gradient.
    none = losses.projection_loss(pts, depth * 0, viewmats, Ks, 0.02, 0.1, backend="fused")
    (g0,) = torch.autograd.grad(none, pts)
    assert float(none.detach()) == 0.0 and not g0.any()
    with pytest.raises(ValueError, match="viewmats or Ks"):
        losses.projection_loss(
            pts, depth, viewmats.clone().requires_grad_(), Ks, 0.02, backend="fused"
        )


def test_fused_geometry_losses_same_bits_for_one_and_two_threads():
    n, nd, alpha = _normal_maps((2, 33, 21), seed=8, dtype=torch.float32)
    threads = torch.get_num_threads()
    runs = []
    try:
        for k in (1, 2):
            torch.set_num_threads(k)
            v = losses.normal_consistency(n, nd, alpha, backend="fused")
            runs.append([v, *torch.autograd.grad(v, (n, nd))])
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(*runs, strict=True):
        assert torch.equal(a, b)
