"""Rigid per-bubble registration of advected surfels against a rendered target."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from surfphase.cameras import look_at
from surfphase.fit.model import SurfelModel
from surfphase.fit.register import register_bubbles
from surfphase.render import camera_tensors, rasterize_surfels


def _blob(centre, n, radius, gen):
    """n surfels on a sphere (m), facing outwards."""
    d = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    return torch.as_tensor(centre, dtype=torch.float64) + radius * d, d


def test_register_recovers_each_bubbles_offset():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    cams = [
        look_at("a", [0, 0.0, 0.03], [0, 0, 0], fx=60.0, width=32, height=32),
        look_at("b", [0.017, 0.0, 0.025], [0, 0, 0], fx=60.0, width=32, height=32),
    ]
    viewmats, Ks = camera_tensors(cams, "cpu", torch.float32)
    p1, n1 = _blob([-0.0015, 0.0, 0.0], 150, 0.001, gen)
    p2, n2 = _blob([0.0015, 0.001, 0.0], 150, 0.0008, gen)
    p0, n0 = _blob([0.0, -0.002, 0.0], 40, 0.0004, gen)  # nucleation region: stays
    pts = torch.cat([p1, p2, p0]).float()
    nrm = torch.cat([n1, n2, n0]).float()
    colors = torch.cat([torch.full((150, 1), 0.2), torch.full((150, 1), 0.5)])
    colors = torch.cat([colors, torch.full((40, 1), 0.3)])
    bubble = np.array([1] * 150 + [2] * 150 + [0] * 40)
    model = SurfelModel.from_points(pts, nrm, colors, 2.5e-4, extent=0.004, init_sdf=0.05)
    bg = torch.full((2, 32, 32, 1), 0.9)
    with torch.no_grad():
        rgb, alpha, _ = rasterize_surfels(
            model.means, model.quats, model.scales, model.opacities(), model.colors,
            viewmats, Ks, 32, 32,
        )  # fmt: skip
        observed = rgb + (1 - alpha) * bg
    # Advection errors: bubble 1 off by ~95 µm, bubble 2 by ~80 µm (a pixel is 500 µm
    # here: 0.15-0.2 px), the nucleation region by 50 µm (left alone).
    off = {1: np.array([8e-5, -4e-5, 3e-5]), 2: np.array([-3e-5, 6e-5, -4e-5])}
    start = pts.clone()
    for b, o in off.items():
        start[torch.as_tensor(bubble == b)] += torch.as_tensor(o, dtype=torch.float32)
    start[torch.as_tensor(bubble == 0)] += torch.tensor([5e-5, 0.0, 0.0])
    with torch.no_grad():
        model.params["means"].data.copy_(start)
    shifts = register_bubbles(
        model, bubble, observed, viewmats, Ks, bg, steps=60, lr=2e-5, lr_decay=0.1
    )
    assert set(shifts) == {1, 2}
    for b, o in off.items():
        # The recovered translation undoes the offset to within 12 µm (0.025 px).
        np.testing.assert_allclose(shifts[b], -o, atol=1.2e-5)
        moved = model.means.detach()[torch.as_tensor(bubble == b)].double()
        np.testing.assert_allclose(
            (moved - start[torch.as_tensor(bubble == b)].double()).mean(0).numpy(),
            shifts[b],
            atol=1e-9,
        )
    # Surfels of the nucleation region are not translated.
    np.testing.assert_array_equal(
        model.means.detach()[torch.as_tensor(bubble == 0)], start[torch.as_tensor(bubble == 0)]
    )


def test_register_without_steps_or_bubbles_changes_nothing():
    pts = torch.zeros((3, 3))
    nrm = torch.tensor([[0.0, 0, 1]] * 3)
    model = SurfelModel.from_points(pts, nrm, torch.zeros((3, 1)), 1e-4, 0.01, 0.05)
    cams = [look_at("a", [0, 0, 0.03], [0, 0, 0], fx=60.0, width=8, height=8)]
    viewmats, Ks = camera_tensors(cams, "cpu", torch.float32)
    obs = torch.zeros((1, 8, 8, 1))
    assert register_bubbles(model, np.array([1, 2, 3]), obs, viewmats, Ks, obs, 0, 1e-5) == {}
    assert register_bubbles(model, np.array([-1, 0, 0]), obs, viewmats, Ks, obs, 5, 1e-5) == {}
    with pytest.raises(ValueError, match="bubble ids"):
        register_bubbles(model, np.array([1, 2]), obs, viewmats, Ks, obs, 5, 1e-5)


def test_register_is_bit_for_bit_with_many_surfels():
    """15,000 surfels (3 bubbles): above the size where a threaded index_put_ backward
    sums in a run-dependent order. Two runs from the same start must agree exactly."""
    gen = torch.Generator().manual_seed(1)
    cams = [
        look_at("a", [0, 0.0, 0.03], [0, 0, 0], fx=40.0, width=12, height=12),
        look_at("b", [0.017, 0.0, 0.025], [0, 0, 0], fx=40.0, width=12, height=12),
    ]
    viewmats, Ks = camera_tensors(cams, "cpu", torch.float32)
    parts = [_blob([0.0015 * (k - 1), 0.0, 0.0], 5000, 0.0008, gen) for k in range(3)]
    pts = torch.cat([p for p, _ in parts]).float()
    nrm = torch.cat([n for _, n in parts]).float()
    bubble = np.repeat([1, 2, 3], 5000)
    rng = np.random.default_rng(0)
    bubble = bubble[rng.permutation(bubble.size)]  # ids interleaved, as after densification
    observed = torch.rand(2, 12, 12, 1, generator=gen)
    runs = []
    for _ in range(2):
        model = SurfelModel.from_points(
            pts, nrm, torch.full((15000, 1), 0.3), 1e-4, extent=0.004, init_sdf=0.05
        )
        shifts = register_bubbles(
            model, bubble, observed, viewmats, Ks, torch.full_like(observed, 0.9), 2, 2e-5
        )
        runs.append((shifts, model.means.detach().clone()))
    for shifts, means in runs[1:]:
        assert torch.equal(means, runs[0][1])
        for b in shifts:
            np.testing.assert_array_equal(shifts[b], runs[0][0][b])
