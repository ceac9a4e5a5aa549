"""Compositing over a background, ``C + (1 − α)·B``: one function, the formula's bits."""

from __future__ import annotations

import numpy as np
import torch

from surfphase.render import over_background, rasterize_surfels
from surfphase.render.scenes import sphere_scene


def _inputs(rng: np.random.Generator, dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    alpha = rng.uniform(0, 1, (2, 5, 7, 1)).astype(dtype)
    colors = (alpha * rng.uniform(0, 1, (2, 5, 7, 3))).astype(dtype)
    background = rng.uniform(0, 1, (2, 5, 7, 3)).astype(dtype)
    return colors, alpha, background


def test_numpy_matches_the_formula_bit_for_bit():
    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        c, a, b = _inputs(rng, dtype)
        out = over_background(c, a, b)
        assert out.dtype == dtype and out.shape == c.shape
        np.testing.assert_array_equal(out, c + (1.0 - a) * b)
        assert np.array_equal(out, c + (1 - a) * b)


def test_grey_images_over_one_background_broadcast():
    rng = np.random.default_rng(1)
    grey = rng.uniform(0, 0.5, (3, 4, 6)).astype(np.float32)
    a = rng.uniform(0, 1, (3, 4, 6)).astype(np.float32)
    bg = rng.uniform(0, 1, (4, 6)).astype(np.float32)
    out = over_background(grey, a, bg)
    assert out.shape == (3, 4, 6)
    np.testing.assert_array_equal(out, grey + (1 - a) * bg[None])


def test_torch_matches_numpy_and_passes_gradients():
    rng = np.random.default_rng(2)
    c, a, b = _inputs(rng, np.float32)
    ct, at, bt = (torch.tensor(x, requires_grad=True) for x in (c, a, b))
    out = over_background(ct, at, bt)
    assert torch.equal(out, ct + (1.0 - at) * bt)
    np.testing.assert_array_equal(out.detach().numpy(), c + (1 - a) * b)
    out.sum().backward()
    np.testing.assert_array_equal(ct.grad.numpy(), np.ones_like(c))
    np.testing.assert_allclose(at.grad.numpy(), -b.sum(-1, keepdims=True), rtol=1e-6)
    np.testing.assert_array_equal(bt.grad.numpy(), np.broadcast_to(1 - a, b.shape))


def test_rasterizer_backgrounds_are_the_composite_of_the_bare_render():
    scene = sphere_scene(60, 2, 24, seed=5)
    bg = scene.pop("backgrounds")
    with torch.no_grad():
        bare, alpha, _ = rasterize_surfels(**scene)
        over, alpha2, _ = rasterize_surfels(**scene, backgrounds=bg)
    assert torch.equal(alpha, alpha2)
    assert torch.equal(over, bare + (1 - alpha) * bg.expand(2, 1)[:, None, None, :])
