"""The shading curve in the fit (``fit: shading``) on a backlit toy scene.

The toy images are ray-cast in numpy (tests/test_fit_toy.py) with a shadowgraph look:
a sphere is dark where the ray meets it obliquely and bright where it faces the camera,
so the same point of the sphere looks different from the two input cameras. A third
camera halfway between them is held out.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_fit_stage import SMALL
from test_fit_toy import BACKGROUND, make_toy_session, raycast, toy_cameras, toy_spheres

from surfphase.fit.outputs import load_surfels, render_surfels
from surfphase.fit.stage import merge_params, run_fit

# Bubbles opaque inside their masks (w_mask), or the fit lets the backlight through the
# core instead of learning it; a curve rate that converges within one frame.
PARAMS = {**SMALL, "frames": 1, "iters_first": 120, "w_mask": 5.0, "lr_shade": 0.05}
SIZE = 96
#: Four input cameras, so that the geometry is pinned down and the look is what differs.
AZIMUTHS = (0.0, 35.0, 90.0, 125.0)


@pytest.fixture(scope="module")
def backlit(tmp_path_factory):
    root = tmp_path_factory.mktemp("backlit")
    return make_toy_session(root, frames=1, size=SIZE, look="backlit", azimuths=AZIMUTHS)


def heldout_error(fit_dir) -> float:
    """Mean |rendered − ray-cast| inside the spheres of the held-out middle camera."""
    mid = toy_cameras(SIZE, azimuths=(17.5,))[0]
    truth, labels = raycast(mid, toy_spheres(0, 1000.0), look="backlit")
    s = load_surfels(fit_dir / "surfels.npz")
    bg = np.full((1, SIZE, SIZE, 1), BACKGROUND, np.float32)
    img = render_surfels(s, 0, [mid], "cpu", bg)[0, ..., 0]
    return float(np.abs(img - truth)[labels >= 0].mean())


def test_the_curve_learns_the_core_and_the_middle_view_improves(backlit, tmp_path):
    torch.set_num_threads(2)
    ingest, masks = backlit
    run_fit(ingest, masks, tmp_path / "plain", PARAMS, device="cpu")
    shaded = {**PARAMS, "shading": True, "surfel_colors": False}
    run_fit(ingest, masks, tmp_path / "shaded", shaded, device="cpu")
    s = load_surfels(tmp_path / "shaded" / "surfels.npz")
    knots = s["shade"][0, :, 0]
    assert "shade" not in load_surfels(tmp_path / "plain" / "surfels.npz")
    # Never decreasing; the rim (|n·d| = 0) and the core (1) near the truth: 0.07 and 0.58.
    assert np.all(np.diff(knots) >= 0), knots
    assert abs(knots[0] - 0.072) < 0.05 and abs(knots[-1] - 0.584) < 0.12, knots
    assert np.all(s["colors"][s["alive"]] == 0)
    plain, with_curve = heldout_error(tmp_path / "plain"), heldout_error(tmp_path / "shaded")
    assert with_curve < 0.85 * plain, (with_curve, plain)


def test_surfel_colors_off_needs_the_curve():
    with pytest.raises(ValueError, match="needs shading"):
        merge_params({"surfel_colors": False})
