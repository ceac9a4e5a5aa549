"""Visual-hull seeds of a bubble partly hidden behind another in one view."""

from __future__ import annotations

import numpy as np
import pytest

from surfphase.cameras import look_at
from surfphase.fit.init import visual_hull_surfels

# Occluder A in front (camera "front" looks along −z from z = 30 mm), bubble B behind it
# and higher, so A hides B's lower part in "front"; the side camera (35° about y) sees
# them apart. Metres.
A = (np.array([0.0, -0.0004, 0.006]), 0.0012)
B = (np.array([0.0, 0.0008, 0.0]), 0.0010)


def sphere_labels(cam, spheres: dict[int, tuple[np.ndarray, float]]) -> np.ndarray:
    """(H, W) label of the nearest sphere each pixel's ray hits (−1: none), exact."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    d = cam.pixel_rays(np.stack([u.ravel(), v.ravel()], 1), distorted=False)
    o = cam.center
    best = np.full(d.shape[0], np.inf)
    lab = np.full(d.shape[0], -1, dtype=np.int64)
    for b, (c, r) in spheres.items():
        oc = o - c
        bq = d @ oc
        disc = bq**2 - (oc @ oc - r * r)
        t = -bq - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc > 0) & (t > 0) & (t < best)
        best[hit], lab[hit] = t[hit], b
    return lab.reshape(cam.height, cam.width)


@pytest.fixture(scope="module")
def scene():
    cams = [
        look_at("front", [0.0, 0.0, 0.03], [0, 0, 0], fx=400.0, width=96, height=96),
        look_at(
            "side",
            [0.03 * np.sin(np.radians(35)), 0.0, 0.03 * np.cos(np.radians(35))],
            [0, 0, 0],
            fx=400.0,
            width=96,
            height=96,
        ),
    ]
    labels = [sphere_labels(c, {1: A, 2: B}) for c in cams]
    images = [np.where(lab >= 0, 0.2, 0.9)[..., None] for lab in labels]
    return cams, labels, images


def test_scene_hides_part_of_b_in_one_view_only(scene):
    cams, labels, _ = scene
    alone = [sphere_labels(c, {2: B}) for c in cams]
    hidden = [
        ((a == 2) & (lab != 2)).mean() / (a == 2).mean()
        for a, lab in zip(alone, labels, strict=True)
    ]
    assert hidden[0] > 0.5 and hidden[1] == 0.0  # 55 % of B is hidden in "front"


def test_occlusion_keeps_the_hidden_part(scene):
    cams, labels, images = scene
    lowest = B[0][1] - B[1]  # the true bottom of B, y
    plain = visual_hull_surfels(cams, labels, images, bubble=2, grid=48)
    occl = visual_hull_surfels(cams, labels, images, bubble=2, grid=48, occlusion=True)
    # Without occlusion the part of B hidden in "front" is carved away: the hull stops
    # far above B's bottom. With it the hull reaches B's bottom (to a voxel and a pixel).
    assert plain.points[:, 1].min() > lowest + 0.4 * B[1]
    assert abs(occl.points[:, 1].min() - lowest) < 2 * occl.spacing + 0.0001
    # The new hull holds the old one: occlusion only stops carving.
    lo, hi = occl.points.min(0), occl.points.max(0)
    assert np.all(plain.points >= lo - occl.spacing) and np.all(plain.points <= hi + occl.spacing)


def test_occlusion_changes_nothing_for_a_bubble_in_plain_view(scene):
    cams, labels, images = scene
    plain = visual_hull_surfels(cams, labels, images, bubble=1, grid=32)
    occl = visual_hull_surfels(cams, labels, images, bubble=1, grid=32, occlusion=True)
    np.testing.assert_array_equal(plain.points, occl.points)


def test_occlusion_only_where_the_mask_is_smaller(scene):
    cams, labels, images = scene
    areas = [(lab == 2).sum() for lab in labels]
    assert 0.3 < areas[0] / areas[1] < 0.75  # B's mask in "front" is 45 % of its side mask
    plain = visual_hull_surfels(cams, labels, images, bubble=2, grid=48)
    # A view counts as hiding part of B only below the ratio: at 0.3 neither view does,
    # so the hull is the plain one; at the default (0.75) "front" does.
    strict = visual_hull_surfels(
        cams, labels, images, bubble=2, grid=48, occlusion=True, occlusion_ratio=0.3
    )
    np.testing.assert_array_equal(plain.points, strict.points)
    every = visual_hull_surfels(
        cams, labels, images, bubble=2, grid=48, occlusion=True, occlusion_ratio=np.inf
    )
    default = visual_hull_surfels(cams, labels, images, bubble=2, grid=48, occlusion=True)
    np.testing.assert_array_equal(every.points, default.points)
    assert len(default.points) > len(plain.points)
