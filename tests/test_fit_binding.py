"""Bubble binding, centroids, velocities and advection, checked by hand."""

from __future__ import annotations

import numpy as np
import pytest

from surfphase.cameras import look_at
from surfphase.fit import binding


def _cams():
    a = look_at("a", [0, 0, 0.1], [0, 0, 0], fx=100.0, width=21, height=21)
    b = look_at("b", [0.1, 0, 0], [0, 0, 0], fx=100.0, width=21, height=21)
    return [a, b]


def test_view_order_most_masks_first():
    one = np.full((5, 5), -1)
    one[0, 0] = 3
    two = np.full((5, 5), -1)
    two[0, 0], two[4, 4] = 1, 2
    assert binding.view_order([one, two]) == [1, 0]
    assert binding.view_order([two, two]) == [0, 1]


def test_bind_uses_view_order_and_skips_bound_surfels():
    cams = _cams()
    # Surfel A at the origin: pixel (10, 10) in both views. Surfel B at x = +0.01 m:
    # view a sees it at column 20; view b looks along −x, so B is on its optical axis.
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.05, 0.0]])
    lab_a = np.full((21, 21), -1)
    lab_a[10, 10] = 1  # A → bubble 1 in view a
    lab_a[10, 20] = 2  # B → bubble 2 in view a
    lab_b = np.full((21, 21), -1)
    lab_b[10, 10] = 5  # A and B (same pixel) → bubble 5 in view b
    lab_b[0, 0], lab_b[0, 1] = 6, 7  # view b has more distinct masks → visited first
    out = binding.bind_surfels_to_bubbles(pts, cams, [lab_a, lab_b])
    assert out.tolist() == [5, 5, -1]
    # Without the extra mask in b, view a goes first (tie on count: more pixels).
    lab_b[0, 0] = lab_b[0, 1] = -1
    out = binding.bind_surfels_to_bubbles(pts, cams, [lab_a, lab_b])
    assert out.tolist() == [1, 2, -1]


def test_centroids_and_velocities_by_hand():
    means = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 1.0, 0], [5.0, 5, 5]])
    bubble = np.array([1, 1, 2, -1])
    opa = np.array([1.0, 0.5, 0.2, 1.0])
    scales = np.array([[1.0, 1.0], [2.0, 2.0], [1.0, 3.0], [1.0, 1.0]])
    w = binding.surfel_weights(opa, scales)
    np.testing.assert_allclose(w, [1.0, 2.0, 0.6, 1.0])
    c = binding.bubble_centroids(means, bubble, w)
    assert set(c) == {1, 2}
    np.testing.assert_allclose(c[1], [4.0 / 3.0, 0, 0])
    np.testing.assert_allclose(c[2], [0, 1.0, 0])
    moved = means + np.array([[0.1, 0, 0], [0.1, 0, 0], [0, 0, 0.3], [9, 9, 9]])
    v = binding.bubble_velocities(means, moved, bubble, w, dt=0.5)
    np.testing.assert_allclose(v[1], [0.2, 0, 0])
    np.testing.assert_allclose(v[2], [0, 0, 0.6])
    with pytest.raises(ValueError):
        binding.bubble_velocities(means, moved, bubble, w, dt=0.0)


def test_advect_bubble_velocity_nucleation_per_surfel_and_unbound_static():
    means = np.zeros((4, 3))
    bubble = np.array([1, 0, -1, 7])
    vb = {1: np.array([0.07, 0.3, 0.0])}
    vs = np.array([[9.0, 9, 9], [0.03, 0.03, 0], [1.0, 1, 1], [0.0, 2.0, 0]])
    out = binding.advect(means, bubble, vb, vs, dt=0.01)
    np.testing.assert_allclose(out[0], [0.0007, 0.003, 0])  # bubble velocity
    np.testing.assert_allclose(out[1], [0.0003, 0.0003, 0])  # nucleation: per surfel
    np.testing.assert_allclose(out[2], [0, 0, 0])  # unbound: stays
    np.testing.assert_allclose(out[3], [0, 0.02, 0])  # no bubble velocity: per surfel


def test_track_continues_through_id_change_but_not_merges_births_or_spawns():
    w = np.ones(8)
    # Frame A: bubble 1 = surfels 0-2, bubble 2 = 3-5, nucleation region 0 = 6, 7.
    a = np.array([1, 1, 1, 2, 2, 2, 0, 0])
    # Same bubbles, new ids (the masks renumbered bubble 2 as 4), one stray surfel.
    b = np.array([1, 1, -1, 4, 4, 4, 0, 0])
    assert binding.track_continues(a, b, w, w, 1) is None  # only 2/3 of it stays
    assert binding.track_continues(a, b, w, w, 1, min_share=0.5) == 1
    assert binding.track_continues(a, b, w, w, 2) == 4
    assert binding.track_continues(b, a, w, w, 4) == 2  # backwards in time
    assert binding.track_continues(a, b, w, w, 0) == 0
    assert binding.track_continues(a, b, w, w, 9) is None  # no such bubble
    # Bubbles 1 and 2 merge into 5: half of 5 comes from each, so both tracks end.
    merged = np.array([5, 5, 5, 5, 5, 5, 0, 0])
    assert binding.track_continues(a, merged, w, w, 1) is None
    assert binding.track_continues(merged, a, w, w, 5) is None
    # Unequal parents (3:1 in weight) still end both tracks; a 9:1 "merge" is bubble 1
    # picking up a few stray surfels, so its track goes on.
    wm = np.array([3.0, 3, 3, 1, 1, 1, 1, 1])
    assert binding.track_continues(a, merged, w, wm, 1) is None
    wm = np.array([9.0, 9, 9, 1, 1, 1, 1, 1])
    assert binding.track_continues(a, merged, w, wm, 1) == 5
    # A bubble detaching from the nucleation region starts a new track.
    detach = np.array([1, 1, 1, 2, 2, 2, 3, 3])
    assert binding.track_continues(detach, a, w, w, 3) is None
    # Surfels spawned at the later frame (absent before: id −1, weight 0 there).
    spawned_ids = np.array([-1, -1, -1, 2, 2, 2, 0, 0])
    w_absent = np.array([0.0, 0, 0, 1, 1, 1, 1, 1])
    assert binding.track_continues(a, spawned_ids, w, w_absent, 1) is None
    assert binding.track_continues(spawned_ids, a, w_absent, w, 2) == 2
