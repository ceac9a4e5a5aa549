"""Tests of the sparse surfel rasterizer against a brute-force reference and closed forms."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest
import torch

from surfphase.cameras import look_at
from surfphase.render import camera_tensors
from surfphase.render import rasterize_surfels as _rasterize_surfels
from surfphase.render.reference import rasterize_surfels_reference
from surfphase.render.scenes import sphere_scene

torch.set_num_threads(2)

# These tests pin the sparse PyTorch backend (the reference implementation that
# tests/test_render_fused.py compares the default, fused CPU backend against).
rasterize_surfels = partial(_rasterize_surfels, backend="torch")

OUTPUTS = (
    "depth_expected",
    "depth_median",
    "normals_camera",
    "normals_world",
    "normals_from_depth",
    "distortion",
)


def random_scene(
    n: int, n_cams: int, width: int, height: int, dtype: torch.dtype, seed: int = 0
) -> dict:
    """Randomly oriented surfels about 2 m in front of slightly rotated cameras."""
    g = torch.Generator().manual_seed(seed)
    kw = {"dtype": torch.float64}
    means = (torch.rand(n, 3, generator=g, **kw) - 0.5) * torch.tensor([0.6, 0.5, 0.4], **kw)
    views = torch.eye(4, **kw).repeat(n_cams, 1, 1)
    for c in range(n_cams):
        a = 0.35 * c
        views[c, :3, :3] = torch.tensor(
            [[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]], **kw
        )
        views[c, :3, 3] = torch.tensor([0.02, -0.01, 2.0], **kw)
    K = torch.tensor(
        [
            [1.2 * width, 0.3, (width - 1) / 2 + 0.7],
            [0, 1.25 * height, (height - 1) / 2 - 0.4],
            [0, 0, 1],
        ],
        **kw,
    )
    scene = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, **kw),
        "scales": torch.rand(n, 2, generator=g, **kw) * 0.08 + 0.004,
        "opacities": torch.rand(n, generator=g, **kw) * 0.9 + 0.05,
        "colors": torch.rand(n, 2, generator=g, **kw),
        "viewmats": views,
        "Ks": K.repeat(n_cams, 1, 1),
        "backgrounds": torch.tensor([0.2, 0.7], **kw),
    }
    scene = {k: v.to(dtype) for k, v in scene.items()}
    scene.update(width=width, height=height, near=1.0, far=4.0)
    return scene


def max_errors(scene: dict, **kw) -> dict[str, float]:
    colors, alphas, meta = rasterize_surfels(**scene, **kw)
    ref = rasterize_surfels_reference(**scene, **{k: v for k, v in kw.items() if k == "low_pass"})
    errs = {
        "colors": (colors - ref["colors"]).abs().max().item(),
        "alphas": (alphas - ref["alphas"]).abs().max().item(),
    }
    errs.update({k: (meta[k] - ref[k]).abs().max().item() for k in OUTPUTS})
    # The scene must exercise every output, or agreement says little.
    assert ref["alphas"].max() > 0.9 and ref["distortion"].max() > 1e-4
    assert (ref["depth_median"] > 0).float().mean() > 0.05
    return errs


@pytest.mark.parametrize("seed", [0, 1])
def test_matches_brute_force_float64(seed):
    scene = random_scene(50, 2, 26, 21, torch.float64, seed)
    errs = max_errors(scene)
    assert max(errs.values()) < 1e-8, errs


def test_matches_brute_force_float64_spheres_chunked():
    scene = sphere_scene(80, 2, 40, seed=3, dtype=torch.float64)
    scene.update(near=0.03, far=0.1)
    errs = max_errors(scene, max_pairs_per_chunk=500)
    assert max(errs.values()) < 1e-8, errs


def test_matches_brute_force_edge_cases():
    """Opaque stacks (early termination), no low-pass filter, and a surfel so close and
    large that its 3σ disk reaches the camera plane (unbounded screen footprint)."""
    opaque = random_scene(60, 1, 20, 20, torch.float64, seed=5)
    opaque["opacities"][:] = 1.0
    opaque["scales"] *= 3
    colors, alphas, _ = rasterize_surfels(**opaque)
    ref = rasterize_surfels_reference(**opaque)
    assert 1 - alphas.max() < 1.01e-4  # stopped just before T < 1e-4
    torch.testing.assert_close(colors, ref["colors"], rtol=0, atol=1e-8)
    torch.testing.assert_close(alphas, ref["alphas"], rtol=0, atol=1e-8)

    errs = max_errors(random_scene(40, 2, 26, 21, torch.float64, seed=3), low_pass=0.0)
    assert max(errs.values()) < 1e-8, errs

    near = random_scene(30, 2, 26, 21, torch.float64, seed=4)
    near["means"][0] = torch.tensor([0.0, 0.0, -0.9], dtype=torch.float64)
    near["scales"][0] = torch.tensor([0.5, 0.3], dtype=torch.float64)
    near["quats"][0] = torch.tensor([0.8, 0.5, 0.1, 0.0], dtype=torch.float64)
    errs = max_errors(near)
    assert max(errs.values()) < 1e-8, errs


def test_empty_scene_renders_background():
    scene = random_scene(0, 2, 10, 8, torch.float32)
    colors, alphas, meta = rasterize_surfels(**scene)
    assert alphas.abs().max() == 0 and meta["radii"].shape == (2, 0)
    torch.testing.assert_close(colors, scene["backgrounds"].expand(2, 8, 10, 2))


def test_matches_brute_force_float32():
    scene = random_scene(50, 2, 26, 21, torch.float32, seed=2)
    errs = max_errors(scene)
    assert max(errs.values()) < 1e-4, errs


def test_single_facing_surfel_is_the_analytic_gaussian():
    """A surfel facing the camera renders o·exp(−½ min(r²/σ², r²/σ_lp²)) with its cut-offs."""
    W, H, f, z, s, o = 41, 37, 300.0, 2.0, 0.0213, 0.8
    cam = look_at("c", [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], fx=f, width=W, height=H, cx=19.3, cy=18.6)
    view, K = camera_tensors([cam], dtype=torch.float64)
    p = torch.tensor([[0.01, -0.005, z]], dtype=torch.float64)
    # Identity rotation: the disk lies in the world xy-plane, parallel to the image
    # (this camera's R is diag(−1, −1, 1)).
    colors, alphas, meta = rasterize_surfels(
        p,
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64),
        torch.tensor([[s, s]], dtype=torch.float64),
        torch.tensor([o], dtype=torch.float64),
        torch.tensor([[0.5]], dtype=torch.float64),
        view,
        K,
        W,
        H,
    )
    uv = cam.project(p.numpy(), distort=False)[0]
    sigma = f * s / z  # pixels
    ys, xs = np.mgrid[0:H, 0:W]
    r2 = (xs - uv[0]) ** 2 + (ys - uv[1]) ** 2
    rho = np.minimum(r2 / sigma**2, r2 / 0.5)
    alpha = np.minimum(o * np.exp(-0.5 * rho), 0.99)
    alpha[(rho > 9) | (alpha < 1 / 255)] = 0
    np.testing.assert_allclose(alphas[0, ..., 0].numpy(), alpha, atol=1e-12)
    np.testing.assert_allclose(colors[0, ..., 0].numpy(), 0.5 * alpha, atol=1e-12)
    inside = alpha > 0
    depth = meta["depth_expected"][0, ..., 0].numpy()
    np.testing.assert_allclose(depth[inside], z, rtol=1e-12)
    np.testing.assert_allclose(meta["depth_median"][0, ..., 0].numpy()[inside], z, rtol=1e-12)
    n = meta["normals_camera"][0].numpy()
    np.testing.assert_allclose(n[..., 2], -alpha, atol=1e-12)  # faces the camera
    np.testing.assert_allclose(n[..., :2], 0, atol=1e-12)
    assert meta["radii"][0, 0] == math.ceil(3 * sigma)
    assert bool(meta["visible"][0, 0])
    np.testing.assert_allclose(meta["means2d"][0, 0].detach().numpy(), uv, atol=1e-10)
    # One surfel: no distortion; a flat plane: depth normals face the camera.
    assert meta["distortion"].abs().max() == 0
    fd = meta["normals_from_depth"][0].numpy()
    core = r2 < (2 * sigma) ** 2
    core[0, :] = core[-1, :] = core[:, 0] = core[:, -1] = False
    np.testing.assert_allclose(fd[core], np.tile([0.0, 0.0, -1.0], (core.sum(), 1)), atol=1e-9)


def _tiny_scene() -> dict:
    scene = random_scene(5, 2, 9, 8, torch.float64, seed=5)
    scene["scales"] = scene["scales"] + 0.05
    return scene


@pytest.mark.parametrize("chunk", [4_000_000, 150])  # 150: three checkpointed bands
def test_gradcheck(chunk):
    scene = _tiny_scene()
    names = ["means", "quats", "scales", "opacities", "colors"]
    inputs = tuple(scene[k].clone().requires_grad_(True) for k in names)
    rest = {k: v for k, v in scene.items() if k not in names}

    def fn(*args):
        colors, alphas, meta = rasterize_surfels(
            **dict(zip(names, args, strict=True)), **rest, max_pairs_per_chunk=chunk
        )
        return (colors, alphas, *(meta[k] for k in OUTPUTS))

    # The scene must blend several surfels per pixel for the check to mean something.
    assert fn(*inputs)[1].max() > 0.5
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_chunked_gradients_equal_unchunked():
    scene = sphere_scene(150, 2, 32, seed=4, dtype=torch.float64)
    grads = []
    for chunk in (10**9, 300):
        leaf = scene["means"].clone().requires_grad_(True)
        colors, _, meta = rasterize_surfels(**{**scene, "means": leaf}, max_pairs_per_chunk=chunk)
        (colors.sum() + meta["depth_expected"].sum()).backward()
        grads.append((leaf.grad, meta["means2d"].grad))
    torch.testing.assert_close(grads[0][0], grads[1][0], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(grads[0][1], grads[1][1], rtol=1e-10, atol=1e-12)


def test_means2d_grad_is_the_screen_space_gradient():
    """means2d.grad = d loss / d (centre's pixel position) at fixed depth and axes."""
    scene = random_scene(20, 1, 30, 24, torch.float64, seed=7)
    target = torch.rand(
        1, 24, 30, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    i = int(torch.argmax(rasterize_surfels(**scene)[2]["radii"][0]))

    def loss(means):
        colors, _, meta = rasterize_surfels(**{**scene, "means": means})
        return ((colors - target) ** 2).sum(), meta

    means = scene["means"].clone().requires_grad_(True)
    value, meta = loss(means)
    value.backward()
    g2d = meta["means2d"].grad[0, i]
    # Move surfel i parallel to the image plane so its centre moves by ±h px along x.
    R = scene["viewmats"][0, :3, :3]
    z = (R @ scene["means"][i] + scene["viewmats"][0, :3, 3])[2]
    fx = scene["Ks"][0, 0, 0]
    h = 1e-5
    step = R.T @ torch.tensor([h * z / fx, 0.0, 0.0], dtype=torch.float64)
    plus, minus = scene["means"].clone(), scene["means"].clone()
    plus[i] += step
    minus[i] -= step
    fd = (loss(plus)[0] - loss(minus)[0]) / (2 * h)
    assert abs(g2d[0].item()) > 1e-3
    assert g2d[0].item() == pytest.approx(fd.item(), rel=1e-5, abs=1e-8)


def test_camera_tensors_project_like_camera():
    cams = [
        look_at("a", [0.01, 0.02, 0.3], [0, 0, 0], fx=500, width=64, height=48, fy=510),
        look_at("b", [0.2, -0.05, 0.2], [0, 0.01, 0], fx=400, width=64, height=48),
    ]
    view, K = camera_tensors(cams, dtype=torch.float64)
    X = np.array([[0.01, -0.02, 0.03], [0.0, 0.01, -0.02]])
    for c, cam in enumerate(cams):
        xc = X @ view[c, :3, :3].numpy().T + view[c, :3, 3].numpy()
        uv = (xc / xc[:, 2:]) @ K[c].numpy().T
        np.testing.assert_allclose(uv[:, :2], cam.project(X, distort=False), atol=1e-9)
    assert view.shape == (2, 4, 4) and K.shape == (2, 3, 3) and view.dtype == torch.float64


def test_bad_input_is_a_value_error():
    scene = random_scene(3, 1, 8, 8, torch.float32)
    with pytest.raises(ValueError, match="backend"):
        _rasterize_surfels(**scene, backend="cuda-magic")
    with pytest.raises(ValueError, match="quats"):
        rasterize_surfels(**{**scene, "quats": scene["quats"][:, :3]})
    with pytest.raises(ValueError, match="near"):
        rasterize_surfels(**{**scene, "near": 5.0, "far": 1.0})


def test_culled_surfels_have_zero_radius():
    scene = random_scene(4, 1, 16, 16, torch.float64)
    scene["means"][0, 2] = -5.0  # behind the camera
    scene["means"][1, 0] = 50.0  # far outside the image
    _, alphas, meta = rasterize_surfels(**scene)
    assert meta["radii"][0, :2].tolist() == [0, 0]
    assert meta["visible"][0].tolist()[:2] == [False, False]
    ref = rasterize_surfels_reference(**scene)
    torch.testing.assert_close(alphas, ref["alphas"], rtol=0, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    scene = sphere_scene(300, 2, 48, seed=2, dtype=torch.float64)
    cpu = rasterize_surfels(**scene)
    gpu_scene = {k: v.cuda() if torch.is_tensor(v) else v for k, v in scene.items()}
    gpu = rasterize_surfels(**gpu_scene)
    torch.testing.assert_close(gpu[0].cpu(), cpu[0], rtol=0, atol=1e-10)
    for k in OUTPUTS:
        torch.testing.assert_close(gpu[2][k].cpu(), cpu[2][k], rtol=0, atol=1e-8)
