"""The fused (numba) rasterizer against the float64 brute-force reference and the sparse
PyTorch backend: outputs, gradients, gradcheck, edge cases and bit-for-bit determinism."""

from __future__ import annotations

import pytest
import torch
from test_render import OUTPUTS, _tiny_scene, random_scene

from surfphase.render import rasterize_surfels
from surfphase.render.reference import rasterize_surfels_reference
from surfphase.render.scenes import sphere_scene

NAMES = ("means", "quats", "scales", "opacities", "colors")


def _errors(scene: dict, backend: str, **kw) -> float:
    colors, alphas, meta = rasterize_surfels(**scene, backend=backend, **kw)
    ref = rasterize_surfels_reference(**scene, **kw)
    errs = [(colors - ref["colors"]).abs().max(), (alphas - ref["alphas"]).abs().max()]
    errs += [(meta[k] - ref[k]).abs().max() for k in OUTPUTS]
    return max(float(e) for e in errs)


def _check_scene(dtype: torch.dtype) -> dict:
    """The scene of ``surfphase bench render --check``."""
    scene = sphere_scene(60, 2, 48, seed=1, dtype=dtype)
    scene["width"], scene["height"] = 48, 40
    return scene


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 5e-5)])
def test_matches_brute_force_on_the_check_scene(dtype, tol):
    scene = _check_scene(dtype)
    fused, sparse = _errors(scene, "fused"), _errors(scene, "torch")
    assert fused < tol, fused
    # As accurate as the sparse backend (float64 inside the kernels: usually more).
    assert fused <= max(sparse, tol / 10), (fused, sparse)


def _render_and_grads(scene: dict, backend: str, **kw):
    """All outputs and the gradients of a random weighted sum of them."""
    leaves = {k: scene[k].detach().clone().requires_grad_(True) for k in NAMES}
    colors, alphas, meta = rasterize_surfels(**{**scene, **leaves}, backend=backend, **kw)
    outs = [colors, alphas] + [meta[k] for k in OUTPUTS]
    g = torch.Generator().manual_seed(0)
    loss = sum((o * torch.rand(o.shape, generator=g, dtype=o.dtype)).sum() for o in outs)
    loss.backward()
    grads = [leaves[k].grad for k in NAMES] + [meta["means2d"].grad]
    return outs, grads, meta


def _assert_backends_agree(scene: dict, atol: float = 1e-10, **kw) -> None:
    outs_f, grads_f, meta_f = _render_and_grads(scene, "fused", **kw)
    outs_s, grads_s, meta_s = _render_and_grads(scene, "torch", **kw)
    assert meta_f["n_pairs"] == meta_s["n_pairs"]
    assert torch.equal(meta_f["radii"], meta_s["radii"])
    for a, b in zip(outs_f, outs_s, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=atol)
    for a, b in zip(grads_f, grads_s, strict=True):
        scale = max(1.0, float(b.abs().max()))
        torch.testing.assert_close(a, b, rtol=0, atol=atol * scale)


@pytest.mark.parametrize("seed", [0, 1])
def test_outputs_and_gradients_match_sparse(seed):
    _assert_backends_agree(random_scene(50, 2, 26, 21, torch.float64, seed))


def test_matches_sparse_without_low_pass_and_on_spheres():
    _assert_backends_agree(random_scene(40, 2, 26, 21, torch.float64, seed=3), low_pass=0.0)
    scene = sphere_scene(150, 2, 32, seed=4, dtype=torch.float64)
    scene.update(near=0.03, far=0.1)
    _assert_backends_agree(scene)


def test_edge_cases_match_sparse():
    """Opaque stacks (early termination) and a surfel whose 3σ disk reaches the camera
    plane (unbounded footprint)."""
    opaque = random_scene(60, 1, 20, 20, torch.float64, seed=5)
    opaque["opacities"][:] = 1.0
    opaque["scales"] *= 3
    _, alphas, _ = rasterize_surfels(**opaque, backend="fused")
    assert 1 - alphas.max() < 1.01e-4  # terminated just before T < 1e-4
    _assert_backends_agree(opaque)
    near = random_scene(30, 2, 26, 21, torch.float64, seed=4)
    near["means"][0] = torch.tensor([0.0, 0.0, -0.9], dtype=torch.float64)
    near["scales"][0] = torch.tensor([0.5, 0.3], dtype=torch.float64)
    near["quats"][0] = torch.tensor([0.8, 0.5, 0.1, 0.0], dtype=torch.float64)
    _assert_backends_agree(near)


def test_per_camera_colours_and_backgrounds():
    scene = random_scene(40, 2, 24, 20, torch.float64, seed=6)
    g = torch.Generator().manual_seed(1)
    scene["colors"] = torch.rand(2, 40, 3, generator=g, dtype=torch.float64)
    scene["backgrounds"] = torch.rand(2, 3, generator=g, dtype=torch.float64)
    _assert_backends_agree(scene)
    assert _errors(scene, "fused") < 1e-12


def test_float32_matches_sparse():
    scene = random_scene(50, 2, 26, 21, torch.float32, seed=2)
    outs_f, grads_f, _ = _render_and_grads(scene, "fused")
    outs_s, grads_s, _ = _render_and_grads(scene, "torch")
    assert all(o.dtype == torch.float32 for o in outs_f + grads_f)
    for a, b in zip(outs_f, outs_s, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-4)
    for a, b in zip(grads_f, grads_s, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-3 * float(b.abs().max()))


def test_gradcheck():
    scene = _tiny_scene()
    inputs = tuple(scene[k].clone().requires_grad_(True) for k in NAMES)
    rest = {k: v for k, v in scene.items() if k not in NAMES}

    def fn(*args):
        colors, alphas, meta = rasterize_surfels(
            **dict(zip(NAMES, args, strict=True)), **rest, backend="fused"
        )
        return (colors, alphas, *(meta[k] for k in OUTPUTS))

    assert fn(*inputs)[1].max() > 0.5  # several surfels blended per pixel
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_empty_and_fully_culled_scenes():
    empty = random_scene(0, 2, 10, 8, torch.float32)
    colors, alphas, meta = rasterize_surfels(**empty, backend="fused")
    assert alphas.abs().max() == 0 and meta["n_pairs"] == 0
    torch.testing.assert_close(colors, empty["backgrounds"].expand(2, 8, 10, 2))
    culled = random_scene(3, 1, 12, 10, torch.float64)
    culled["means"][:, 2] = -5.0  # all behind the camera
    outs, grads, meta = _render_and_grads(culled, "fused")
    assert outs[1].abs().max() == 0 and meta["n_pairs"] == 0
    assert all(g.abs().max() == 0 for g in grads[:-1])


def test_bit_for_bit_deterministic():
    scene = sphere_scene(400, 2, 40, seed=5, dtype=torch.float32)
    first = _render_and_grads(scene, "fused")
    second = _render_and_grads(scene, "fused")
    for a, b in zip(first[0] + first[1], second[0] + second[1], strict=True):
        assert torch.equal(a, b)


def test_default_backend_is_fused_on_cpu():
    scene = random_scene(20, 1, 16, 12, torch.float64, seed=8)
    default = rasterize_surfels(**scene)
    fused = rasterize_surfels(**scene, backend="fused")
    for a, b in zip(default[:2], fused[:2], strict=True):
        assert torch.equal(a, b)


def test_depth_normals_kernel_matches_pytorch():
    """The numba depth normals (CPU, Ks without grad) against the PyTorch rule (taken
    when Ks needs a gradient), values and gradients, with a hole of zero depth."""
    from surfphase.render import depth_normals

    g = torch.Generator().manual_seed(0)
    depth = 1 + torch.rand(2, 9, 11, 1, generator=g, dtype=torch.float64)
    depth[0, 2:4, 3:6] = 0
    K = torch.tensor([[50.0, 0.3, 5.0], [0.0, 52.0, 4.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    K = K.repeat(2, 1, 1)
    weights = torch.rand(2, 9, 11, 3, generator=g, dtype=torch.float64)
    outs = []
    for Ks in (K, K.clone().requires_grad_(True)):
        d = depth.clone().requires_grad_(True)
        n = depth_normals(d, Ks)
        (n * weights).sum().backward()
        outs.append((n, d.grad))
    torch.testing.assert_close(outs[0][0], outs[1][0], rtol=0, atol=1e-14)
    torch.testing.assert_close(outs[0][1], outs[1][1], rtol=1e-12, atol=1e-12)
    d = (1 + torch.rand(1, 5, 6, 1, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: depth_normals(x, K[:1]), (d,))


def test_same_bits_for_any_thread_count():
    """Bands are self-contained and every sum has a fixed order, so the thread count
    changes no bit of the outputs or gradients."""
    scene = sphere_scene(400, 2, 40, seed=6, dtype=torch.float32)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _render_and_grads(scene, "fused")
        torch.set_num_threads(2)
        two = _render_and_grads(scene, "fused")
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one[0] + one[1], two[0] + two[1], strict=True):
        assert torch.equal(a, b)


def test_camera_gradients_take_the_sparse_backend():
    """The fused backend computes no gradient to viewmats / Ks: it refuses them, and
    ``auto`` renders such calls with the sparse backend."""
    scene = random_scene(20, 2, 16, 12, torch.float64, seed=9)
    scene["viewmats"] = scene["viewmats"].clone().requires_grad_(True)
    with pytest.raises(ValueError, match="viewmats or Ks"):
        rasterize_surfels(**scene, backend="fused")
    colors, _, _ = rasterize_surfels(**scene)
    colors.sum().backward()
    assert scene["viewmats"].grad is not None and scene["viewmats"].grad.abs().max() > 0
