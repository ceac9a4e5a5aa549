"""Dating a detachment from the rise of the silhouette bottom (surfphase.masks.detach)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar
from test_masks_associate import _ids, _segment
from test_masks_scene import rig, write_ingest

from surfphase.masks.associate import ASSOCIATE_DEFAULTS, associate
from surfphase.masks.detach import fit_frames, left_plate_at


def _hinge_sse(t0: float, t: np.ndarray, h: np.ndarray) -> float:
    """Residual of ``h0 + v·max(0, t − t0)`` by numpy's least squares."""
    a = np.c_[np.ones_like(t), np.maximum(0.0, t - t0)]
    coef, *_ = np.linalg.lstsq(a, h, rcond=None)
    return float(((h - a @ coef) ** 2).sum())


def test_left_plate_at_finds_the_hinge_of_exact_and_noisy_heights():
    t = np.arange(20, dtype=float)
    h = 7e-5 + 2e-5 * np.maximum(0.0, t - 6.3)  # resting 70 µm above the plate
    assert abs(left_plate_at(t, h) - 6.3) < 0.051
    rng = np.random.default_rng(3)
    noisy = h + rng.normal(0.0, 2e-5, t.size)
    got = left_plate_at(t, noisy, step=0.01)
    # The least-squares hinge by a bounded scalar search on the same objective
    # (v eliminated in closed form), from a coarse grid's best start.
    grid = np.arange(0.0, 17.0, 0.5)
    start = grid[int(np.argmin([_hinge_sse(g, t, noisy) for g in grid]))]
    ref = minimize_scalar(
        _hinge_sse, bounds=(start - 0.5, start + 0.5), args=(t, noisy), method="bounded"
    ).x
    assert abs(got - ref) < 0.02
    assert abs(got - 6.3) < 1.5


def test_left_plate_at_needs_a_rise():
    t = np.arange(8, dtype=float)
    assert left_plate_at(t, -1e-5 * t) is None
    assert left_plate_at(t[:2], np.array([0.0, 1e-4])) is None


def test_fit_frames_hold_a_time_across_frame_rates():
    p = {"detach_fit_s": 0.002, "detach_fit_min_frames": 4}
    assert fit_frames(1000.0, p) == 4
    assert fit_frames(5000.0, p) == 10
    assert fit_frames(10000.0, p) == 20
    assert fit_frames(None, p) == 4


def _associated(tmp_path, track, n: int, height: float):
    """One sphere's ``track`` (frame → (centre, r)) drawn over ``n`` frames, segmented and
    associated with ``nucleation_height`` = ``height`` at 1,000 fps: per view, the id
    covering the sphere in each frame (:func:`_ids`), and the events."""
    truth = write_ingest(tmp_path, [track], n)
    labels, scores = _segment(tmp_path, truth)
    params = {**ASSOCIATE_DEFAULTS, "nucleation_height": height}
    out, _inst, events = associate(labels, scores, rig(128), params, fps=1000.0)
    return {c: _ids(truth[c], out[c], 0) for c in truth}, events


def test_a_slow_bubble_is_free_from_when_it_leaves_the_plate(tmp_path):
    r, rest, rise = 0.0008, 4, 4e-5  # resting until frame 4, then 40 µm a frame
    height = 3e-4  # about two pixels of this rig: the height rule alone waits 7 frames

    def slow(t):
        return np.array([0.0005, r + rise * max(0, t - rest), 0.0]), r

    n = 20
    ids, events = _associated(tmp_path, slow, n, height)
    assert ids["cam0"] == ids["cam1"]
    free = [t for t, b in enumerate(ids["cam0"]) if b is not None and b >= 1]
    first = free[0]
    by_height = rest + int(np.ceil(height / rise))  # first frame the rule alone frees
    # Frame ``rest`` is the instant it leaves: either side is right.
    assert rest <= first < by_height
    assert free == list(range(first, n))  # free from then on
    assert set(ids["cam0"][:rest]) == {0}
    assert (events["event"] == "detach").sum() == 2  # one per view, at the new date
    assert set(events.loc[events["event"] == "detach", "frame"]) == {first}


def test_a_bubble_that_hops_off_the_plate_and_lands_back_stays_attached(tmp_path):
    r, height = 0.0008, 3e-4

    def hopping(t):  # its bottom above the nucleation height in frames 6 and 7 only
        return np.array([0.0005, r + (4e-4 if t in (6, 7) else 0.0), 0.0]), r

    n = 14
    ids, events = _associated(tmp_path, hopping, n, height)
    for c in ids:
        assert ids[c] == [0] * n
    assert (events["event"] == "detach").sum() == 0


def test_a_slow_bubble_whose_bottom_dips_under_the_height_rule_stays_free(tmp_path):
    r, rest, rise, height = 0.0008, 4, 4e-5, 3e-4

    def dipping(t):  # above the height from frame 11, lower in frame 13, the last
        y = r + rise * max(0, t - rest) - (1.5e-4 if t == 13 else 0.0)
        return np.array([0.0005, y, 0.0]), r

    n = 14
    ids, events = _associated(tmp_path, dipping, n, height)
    assert ids["cam0"] == ids["cam1"]
    free = [t for t, b in enumerate(ids["cam0"]) if b is not None and b >= 1]
    assert rest <= free[0] < 11
    assert free == list(range(free[0], n))  # frame 13 included: one bubble throughout
    assert len(set(ids["cam0"][free[0] :])) == 1
    assert (events["event"] == "detach").sum() == 2
