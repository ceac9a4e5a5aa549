"""View-dependent colour (surfphase.render.shading) and per-camera colours in the renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_render import random_scene

from surfphase.cameras import look_at
from surfphase.fit.model import normal_to_quat
from surfphase.render import camera_tensors, rasterize_surfels
from surfphase.render.reference import rasterize_surfels_reference
from surfphase.render.shading import (
    camera_centres,
    facing_cosines,
    monotone_knots,
    monotone_raw,
    shading_curve,
    view_colors,
)

torch.set_num_threads(2)


def test_camera_centres_are_the_cameras_eyes():
    eyes = [np.array([0.01, 0.02, 0.06]), np.array([-0.05, 0.0, 0.03])]
    cams = [
        look_at(f"c{k}", e, np.zeros(3), fx=500.0, width=32, height=32) for k, e in enumerate(eyes)
    ]
    viewmats, _ = camera_tensors(cams, "cpu", torch.float64)
    np.testing.assert_allclose(camera_centres(viewmats).numpy(), np.stack(eyes), atol=1e-12)


def test_facing_cosines_by_hand():
    # Camera on +z, 0.1 m from the origin, looking at it. Surfels at the origin with
    # normals at 0°, 60°, 90° and 180° from +z: |cos| = 1, 1/2, 0, 1.
    cam = look_at("c", np.array([0.0, 0.0, 0.1]), np.zeros(3), fx=500.0, width=32, height=32)
    viewmats, _ = camera_tensors([cam], "cpu", torch.float64)
    a = math.radians(60)
    normals = torch.tensor(
        [[0, 0, 1.0], [math.sin(a), 0, math.cos(a)], [1.0, 0, 0], [0, 0, -1.0]],
        dtype=torch.float64,
    )
    quats = normal_to_quat(normals)
    means = torch.zeros(4, 3, dtype=torch.float64)
    cos = facing_cosines(means, quats, viewmats)
    np.testing.assert_allclose(cos.numpy(), [[1.0, 0.5, 0.0, 1.0]], atol=1e-12)
    # Off-axis: a +z-facing surfel at (0.1, 0, 0) is seen along (1, 0, -1)/√2.
    cos = facing_cosines(torch.tensor([[0.1, 0, 0.0]], dtype=torch.float64), quats[:1], viewmats)
    assert cos.item() == pytest.approx(1 / math.sqrt(2), abs=1e-12)


def test_shading_curve_is_numpy_interp():
    knots = torch.tensor([[0.0, 1.0], [0.2, 0.5], [-0.1, 0.0], [0.6, 2.0]], dtype=torch.float64)
    x = torch.linspace(0, 1, 37, dtype=torch.float64)
    got = shading_curve(x, knots).numpy()
    grid = np.linspace(0, 1, 4)
    for d in range(2):
        np.testing.assert_allclose(got[:, d], np.interp(x.numpy(), grid, knots[:, d]), atol=1e-12)
    with pytest.raises(ValueError, match="2 knots"):
        shading_curve(x, knots[:1])


def test_view_colors_without_curve_are_the_colours():
    s = random_scene(5, 3, 8, 8, torch.float64)
    out = view_colors(s["colors"], s["means"], s["quats"], None, s["viewmats"])
    assert out.shape == (3, 5, 2) and torch.equal(out[2], s["colors"])


def test_per_camera_colours_render_like_separate_cameras():
    s = random_scene(40, 3, 24, 20, torch.float64, seed=3)
    g = torch.Generator().manual_seed(1)
    per_cam = torch.rand(3, 40, 2, generator=g, dtype=torch.float64)
    together, alphas, _ = rasterize_surfels(**{**s, "colors": per_cam})
    ref = rasterize_surfels_reference(**{**s, "colors": per_cam})
    assert (together - ref["colors"]).abs().max() < 1e-10
    for c in range(3):
        one = {**s, "colors": per_cam[c], "viewmats": s["viewmats"][c : c + 1]}
        one["Ks"] = s["Ks"][c : c + 1]
        rgb, _, _ = rasterize_surfels(**one)
        assert (rgb[0] - together[c]).abs().max() < 1e-12
    assert alphas.max() > 0.5
    with pytest.raises(ValueError, match=r"\(C, N, D\)"):
        rasterize_surfels(**{**s, "colors": per_cam[:2]})


def test_the_curve_gets_gradients_through_the_renderer():
    s = random_scene(40, 2, 24, 20, torch.float64, seed=4)
    knots = torch.zeros(5, 2, dtype=torch.float64, requires_grad=True)
    cols = view_colors(s["colors"], s["means"], s["quats"], knots, s["viewmats"])
    rgb, _, _ = rasterize_surfels(**{**s, "colors": cols})
    rgb.sum().backward()
    assert knots.grad is not None and knots.grad.abs().sum() > 0
    # d(sum of image)/d(all knots of a channel) = Σ blending weights: the alpha sum.
    _, alphas, _ = rasterize_surfels(**s)
    np.testing.assert_allclose(knots.grad.sum(0).numpy(), [alphas.sum().item()] * 2, rtol=1e-9)


def test_monotone_knots_round_trip_and_never_decrease():
    knots = torch.tensor([[0.1], [0.1], [0.25], [0.7]], dtype=torch.float64)
    back = monotone_knots(monotone_raw(knots, min_step=1e-6))
    np.testing.assert_allclose(back.numpy(), knots.numpy(), atol=4e-6)
    g = torch.Generator().manual_seed(0)
    raw = torch.randn(9, 2, generator=g, dtype=torch.float64) * 3
    assert (torch.diff(monotone_knots(raw), dim=0) > 0).all()
