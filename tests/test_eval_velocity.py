"""Velocity error on a hand-computed case; finite differences; the two-view centroid
baseline and the 2D single-view reference on exactly known motions."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest

from surfphase.cameras import look_at
from surfphase.eval import baseline, reference2d, velocity

COLS = ["frame", "bubble", "x", "y", "z", "vx", "vy", "vz"]


def test_velocity_error_hand_case():
    mm = 1e-3
    pred = pd.DataFrame(
        [
            [0, 1, 0, 0, 0, 0, 1.0, 0],
            [0, 2, 5 * mm, 0, 0, 0, 0.5, 0],
            [1, 1, 0, 1 * mm, 0, 0.3, 0.4, 0],
            [1, 3, 9 * mm, 0, 0, np.nan, np.nan, np.nan],  # matched, velocity unknown
            [1, 4, 30 * mm, 0, 0, 1, 1, 1],  # 2 mm from the nearest truth: gated out
        ],
        columns=COLS,
    )
    truth = pd.DataFrame(
        [
            [0, 7, 5.1 * mm, 0, 0, 0, 0.4, 0],
            [0, 8, 0.1 * mm, 0, 0, 0, 1.0, 0],
            [0, 9, 20 * mm, 0, 0, 0, 2.0, 0],  # no prediction near it
            [1, 8, 0, 1.1 * mm, 0, 0, 0, 0],
            [1, 10, 9 * mm, 0, 0, 0, 1, 0],
            [1, 11, 32 * mm, 0, 0, 0, 1, 0],
        ],
        columns=COLS,
    )
    m = velocity.match_bubbles(pred, truth, max_dist=1.5 * mm)
    pairs = sorted(zip(m.frame, m.bubble, m.gt_bubble, strict=True))
    assert pairs == [(0, 1, 8), (0, 2, 7), (1, 1, 8), (1, 3, 10)]
    e = velocity.velocity_errors(m)
    # |Δv| = 0, 0.1, 0.5 → 0.2 m/s; mean |v_gt| = (1 + 0.4 + 0)/3.
    assert e["matched"] == 3
    assert e["mean_abs_error_mps"] == pytest.approx(0.2)
    assert e["relative_error"] == pytest.approx(0.2 / (1.4 / 3))
    assert e["mean_speed_gt_mps"] == pytest.approx(1.4 / 3)
    # A wider gate adds the (1, 4) ↔ (1, 11) pair: |Δv| = |(1, 0, 1)| = √2.
    e2 = velocity.velocity_errors(velocity.match_bubbles(pred, truth, max_dist=3 * mm))
    assert e2["matched"] == 4
    assert e2["mean_abs_error_mps"] == pytest.approx((0.6 + np.sqrt(2)) / 4)


def test_finite_difference_runs():
    keys = np.array([1, 2, 1, 1, 1])
    index = np.array([2, 0, 0, 1, 4])
    values = np.array([4.0, 5.0, 0.0, 1.0, 9.0])[:, None]
    out = baseline.finite_difference(keys, index, index / 100.0, values)[:, 0]
    # Bubble 1 run 0..2: forward 100, central 200, backward 300; frame 4 alone: NaN.
    assert out[2] == pytest.approx(100) and out[3] == pytest.approx(200)
    assert out[0] == pytest.approx(300)
    assert np.isnan(out[1]) and np.isnan(out[4])


def test_mask_centroids_exact():
    lab = np.full((2, 6, 7), -1, np.int32)
    lab[0, 1:3, 2:6] = 5  # rows 1–2, columns 2–5: centroid (u, v) = (3.5, 1.5)
    lab[0, 5, 0] = 0
    lab[1, 4, 6] = 5
    c = baseline.mask_centroids(lab)
    assert c.values.tolist() == [[0, 0, 0.0, 5.0, 1], [0, 5, 3.5, 1.5, 8], [1, 5, 6.0, 4.0, 1]]


def _rig(size=256, fx=900.0):
    """Two cameras 6 cm from the origin, 35° apart in azimuth, slightly above."""
    cams = []
    for name, az in (("cam0", 0.0), ("cam1", 35.0)):
        a = np.deg2rad(az)
        eye = 0.06 * np.array([np.sin(a), 0.1, np.cos(a)])
        cams.append(look_at(name, eye, [0, 0, 0], fx, size, size))
    return cams


def _disk_labels(cams, centers, radius_px=7.0, bubble=3):
    """Per camera a (T, H, W) label stack with a disk of ``radius_px`` around the exact
    projection of each centre."""
    stacks = []
    for cam in cams:
        vv, uu = np.mgrid[0 : cam.height, 0 : cam.width]
        lab = np.full((len(centers), cam.height, cam.width), -1, np.int32)
        for t, uv in enumerate(cam.project(centers)):
            lab[t][(uu - uv[0]) ** 2 + (vv - uv[1]) ** 2 <= radius_px**2] = bubble
        stacks.append(lab)
    return stacks


def test_baseline_recovers_constant_velocity():
    cams = _rig()
    fps = 1000.0
    v = np.array([0.05, 0.3, -0.02])
    frames = np.arange(10, 16)
    X = np.array([-1e-3, -1e-3, 0.5e-3]) + (frames - 10)[:, None] / fps * v
    labels = _disk_labels(cams, X, radius_px=15.0)
    # A second bubble seen by cam0 only is not triangulated.
    labels[0][:, 5:9, 5:9] = 4
    tab = baseline.baseline_bubbles(cams, labels, frames, fps)
    assert list(tab.columns) == baseline.BUBBLE_COLUMNS
    assert tab.bubble.unique().tolist() == [3]
    assert tab.frame.tolist() == frames.tolist()
    assert np.allclose(tab.time_s, frames / fps)
    # Independent check of the triangulation: OpenCV on the same centroids.
    c0 = baseline.mask_centroids(labels[0]).query("bubble == 3")[["u", "v"]].to_numpy()
    c1 = baseline.mask_centroids(labels[1]).query("bubble == 3")[["u", "v"]].to_numpy()
    Xh = cv2.triangulatePoints(cams[0].P, cams[1].P, c0.T, c1.T)
    assert np.allclose(tab[["x", "y", "z"]].to_numpy(), (Xh[:3] / Xh[3]).T, atol=1e-9)
    # Velocities: central differences inside the run, one-sided at its ends.
    P, V = tab[["x", "y", "z"]].to_numpy(), tab[["vx", "vy", "vz"]].to_numpy()
    assert np.allclose(V[0], (P[1] - P[0]) * fps)
    assert np.allclose(V[3], (P[4] - P[2]) * fps / 2)
    assert np.allclose(V[-1], (P[-1] - P[-2]) * fps)
    # Digitised disk centroids sit within ~0.1 px of the centre's projection (66 µm per
    # pixel here): positions within 15 µm, velocities within 6 % of the true one.
    assert np.abs(P - X).max() < 1.5e-5
    assert np.linalg.norm(V - v, axis=1).max() < 0.06 * np.linalg.norm(v)


def test_reference2d_in_plane_motion():
    # cam0 looks along −z; the bubble moves in the plane z = 0, 6 cm from it.
    cam = look_at("cam0", [0, 0, 0.06], [0, 0, 0], 900.0, 256, 256)
    fps = 2000.0
    v = np.array([0.1, 0.2, 0.0])
    frames = np.arange(8)
    X = np.array([-0.5e-3, -1e-3, 0.0]) + frames[:, None] / fps * v
    (lab,) = _disk_labels([cam], X, radius_px=6.0, bubble=2)
    depths = pd.DataFrame({"frame": frames, "bubble": 2, "x": X[:, 0], "y": X[:, 1], "z": X[:, 2]})
    ref = reference2d.reference_velocities(cam, lab, frames, fps, depths)
    assert list(ref.columns) == reference2d.REFERENCE_COLUMNS
    assert np.allclose(ref.depth_m, 0.06)
    # Image +u is lab +x and image +v is lab −y for this camera; no depth component.
    got = ref[["ref_vx", "ref_vy", "ref_vz"]].to_numpy()
    assert np.allclose(got[:, 2], 0, atol=1e-12)
    assert np.abs(got - v).max() < 0.03 * np.linalg.norm(v)
    # Exact: Z·Δu/fx over the central difference of the mask centroids.
    c = baseline.mask_centroids(lab)
    du = (c.u.iloc[2] - c.u.iloc[0]) * fps / 2
    assert got[1, 0] == pytest.approx(0.06 * du / 900.0, rel=1e-12)


def test_compare_to_reference_hand_case():
    cam = look_at("cam0", [0, 0, 0.06], [0, 0, 0], 900.0, 64, 64)
    ref = pd.DataFrame(
        {"frame": [0, 1], "bubble": [1, 1], "ref_vx": [1.0, 2.0], "ref_vy": [2.0, -2.0],
         "ref_vz": [0.0, 0.0]}
    )  # fmt: skip
    pred = pd.DataFrame(
        {"frame": [0, 1, 2], "bubble": [1, 1, 1], "vx": [1.5, 2.0, 9.0], "vy": [2.0, -1.0, 9.0],
         "vz": [7.0, -3.0, 9.0]}
    )  # fmt: skip
    res, rows = reference2d.compare_to_reference(pred, ref, cam)
    # The depth component (vz, along the optical axis) is dropped; x errors 0.5, 0 over
    # mean |r_x| 1.5; y errors 0, 1 over mean |r_y| 2.
    assert res["matched"] == 2
    assert res["relative_error_x"] == pytest.approx(0.25 / 1.5)
    assert res["relative_error_y"] == pytest.approx(0.25)
    assert res["mean_abs_error_y_mps"] == pytest.approx(0.5)
    assert np.allclose(rows.plane_vz, 0)


def test_smoothed_velocity_is_exact_on_polynomials_and_holds_across_fps():
    """Savitzky–Golay of order 2 differentiates a quadratic track exactly (ends too, by
    its interpolating fit); the window is in seconds, so 2000 fps uses twice the frames
    of 1000 fps; noise is averaged down against plain finite differences."""
    rng = np.random.default_rng(0)
    for fps in (1000.0, 2000.0):
        n = int(0.02 * fps)
        idx = np.arange(n)
        t = idx / fps
        x = np.stack([0.1 * t, 0.2 * t + 3.0 * t**2, -0.05 * t], axis=1)
        v_true = np.stack([np.full(n, 0.1), 0.2 + 6.0 * t, np.full(n, -0.05)], axis=1)
        keys = np.ones(n, dtype=int)
        v = baseline.smoothed_velocity(keys, idx, t, x, fps, window_s=0.007, order=2)
        np.testing.assert_allclose(v, v_true, atol=1e-9)
        noisy = x + rng.normal(0, 5e-6, x.shape)
        e_fd = np.abs(baseline.finite_difference(keys, idx, t, noisy) - v_true).mean()
        e_sg = np.abs(
            baseline.smoothed_velocity(keys, idx, t, noisy, fps, 0.007, 2) - v_true
        ).mean()
        assert e_sg < 0.5 * e_fd
    # The window in frames: round(window_s·fps) made odd; compare with scipy directly.
    from scipy.signal import savgol_filter

    fps, n = 2000.0, 40
    idx = np.arange(n)
    y = np.sin(idx / 5.0)[:, None]
    v = baseline.smoothed_velocity(np.zeros(n), idx, idx / fps, y, fps, 0.007, 3)
    ref = savgol_filter(y[:, 0], 15, 3, deriv=1, delta=1 / fps, mode="interp")
    np.testing.assert_allclose(v[:, 0], ref, rtol=1e-12)


def test_smoothed_velocity_keeps_tracks_and_gaps_apart():
    fps = 1000.0
    # Bubble 1: frames 0–9 then 20–22 (a gap), bubble 2: frames 0–1 (too short: FD).
    idx = np.r_[np.arange(10), np.arange(20, 23), [0, 1]]
    keys = np.r_[np.ones(13, dtype=int), [2, 2]]
    t = idx / fps
    x = np.where(keys == 1, 0.3 * t, -0.1 * t + 5.0)[:, None]
    x[10:13] += 1.0  # a jump across the gap must not leak into either run
    v = baseline.smoothed_velocity(keys, idx, t, x, fps, window_s=0.005, order=2)
    np.testing.assert_allclose(v[:13, 0], 0.3, atol=1e-9)
    np.testing.assert_allclose(v[13:, 0], -0.1, atol=1e-9)
    with pytest.raises(ValueError, match="order"):
        baseline.smoothed_velocity(keys, idx, t, x, fps, 0.005, 0)


def test_relative_gate_matching_and_component_errors():
    mm = 1e-3
    pred = pd.DataFrame(
        [[0, 1, 0.4 * mm, 0, 0, 0.1, 0.3, 0.0], [0, 2, 10.6 * mm, 0, 0, 0, 0.2, 0.1]],
        columns=COLS,
    )
    truth = pd.DataFrame(
        [[0, 5, 0, 0, 0, 0.0, 0.2, 0.0, 1.0 * mm], [0, 6, 10 * mm, 0, 0, 0, 0.2, 0, 1.0 * mm]],
        columns=[*COLS, "r_eq"],
    )
    m = velocity.match_bubbles_relative(pred, truth, gate_r_eq=0.5)
    assert list(zip(m.bubble, m.gt_bubble, strict=True)) == [(1, 5)]  # 0.6 r_eq: gated out
    e = velocity.component_errors(m)
    assert e == pytest.approx({"vx": 0.1, "vy": 0.1, "vz": 0.0})
    m2 = velocity.match_bubbles_relative(pred, truth, gate_r_eq=0.7)
    assert len(m2) == 2
    assert velocity.component_errors(m2)["vz"] == pytest.approx(0.05)


def test_gated_assignment_gates_before_assigning():
    import itertools

    from surfphase.eval.velocity import gated_assignment

    # A far report (row 2) must not take row 1's perfect partner to lower the sum.
    cost = np.array([[0.0, 9.0, 9.0], [9.0, 0.01, 9.0], [9.0, 7.5, 20.0]])
    assert sorted(gated_assignment(cost, 0.5)) == [(0, 0), (1, 1)]
    # Brute force on random small cases: the most pairs within the gate, then the least
    # summed cost among those.
    rng = np.random.default_rng(0)
    for _ in range(200):
        n, m = (int(k) for k in rng.integers(1, 5, size=2))
        c = rng.exponential(1.0, size=(n, m))
        c[rng.random((n, m)) < 0.1] = np.inf
        got = gated_assignment(c, 0.8)
        best = (0, 0.0)
        for perm in itertools.permutations(range(max(n, m)), n):
            pairs = [(i, j) for i, j in enumerate(perm) if j < m and c[i, j] <= 0.8]
            key = (len(pairs), -sum(c[i, j] for i, j in pairs))
            best = max(best, key)
        assert len(got) == best[0]
        assert sum(c[i, j] for i, j in got) == pytest.approx(-best[1])
        assert len({i for i, _ in got}) == len(got) == len({j for _, j in got})


def test_baseline_leaves_out_centroids_the_two_views_disagree_on():
    """A frame where one view's mask of the bubble is off its epipolar line (a fragment
    moved 6 px down) reprojects far from its centroids: it is left out, and the
    velocities are differenced over the runs on either side; without the gate it is
    kept (and its velocity is off)."""
    cams = _rig()
    fps = 1000.0
    v = np.array([0.05, 0.3, -0.02])
    frames = np.arange(10, 18)
    X = np.array([-1e-3, -1e-3, 0.5e-3]) + (frames - 10)[:, None] / fps * v
    labels = _disk_labels(cams, X, radius_px=15.0)
    labels[1][4] = np.roll(labels[1][4], 6, axis=0)
    tab = baseline.baseline_bubbles(cams, labels, frames, fps)
    assert tab.frame.tolist() == [f for f in frames.tolist() if f != 14]
    V = tab[["vx", "vy", "vz"]].to_numpy()
    assert np.linalg.norm(V - v, axis=1).max() < 0.06 * np.linalg.norm(v)
    every = baseline.baseline_bubbles(cams, labels, frames, fps, max_reproj_px=None)
    assert every.frame.tolist() == frames.tolist()
    err = np.linalg.norm(every[["vx", "vy", "vz"]].to_numpy() - v, axis=1)
    assert err.max() > 0.25 * np.linalg.norm(v)


def test_matching_equals_a_frame_by_frame_selection():
    """The matchers (grouped once, numpy per frame) against the plain per-frame pandas
    selection they replaced, on shuffled random tables: frames only one side has,
    non-finite centres, a true bubble with r_eq 0, several bubbles a frame."""
    from surfphase.eval.velocity import MATCH_COLUMNS, gated_assignment

    def reference(pred, truth, gate, relative):
        rows, xyz, vel = [], ["x", "y", "z"], ["vx", "vy", "vz"]
        for f, p in pred.groupby("frame", sort=True):
            g = truth[truth["frame"] == f]
            p = p[np.isfinite(p[xyz].to_numpy(np.float64)).all(axis=1)]
            keep = np.isfinite(g[xyz].to_numpy(np.float64)).all(axis=1)
            g = g[keep & (g["r_eq"] > 0)] if relative else g[keep]
            if p.empty or g.empty:
                continue
            d = np.linalg.norm(p[xyz].to_numpy()[:, None] - g[xyz].to_numpy()[None], axis=-1)
            r = g["r_eq"].to_numpy()
            for i, j in gated_assignment(d / r[None] if relative else d, gate):
                v, gv = p[vel].to_numpy()[i], g[vel].to_numpy()[j]
                row = [int(f), int(p["bubble"].iloc[i]), int(g["bubble"].iloc[j]), d[i, j],
                       *v, *gv, np.linalg.norm(v - gv)]  # fmt: skip
                rows.append([*row, r[j]] if relative else row)
        cols = [*MATCH_COLUMNS, "gt_r_eq"] if relative else MATCH_COLUMNS
        return pd.DataFrame(rows, columns=cols)

    rng = np.random.default_rng(4)
    matched = 0
    for _ in range(20):
        n_t, n_p = int(rng.integers(5, 40)), int(rng.integers(5, 40))
        truth = pd.DataFrame(
            {"frame": rng.integers(0, 8, n_t), "bubble": rng.integers(1, 6, n_t)}
            | {k: rng.normal(0, 1e-3, n_t) for k in ("x", "y", "z", "vx", "vy", "vz")}
            | {"r_eq": rng.uniform(0.3e-3, 1e-3, n_t)}
        )
        truth.loc[rng.random(n_t) < 0.1, "r_eq"] = 0.0
        pred = pd.DataFrame(
            {"frame": rng.integers(0, 10, n_p), "bubble": rng.integers(1, 9, n_p)}
            | {k: rng.normal(0, 1e-3, n_p) for k in ("x", "y", "z", "vx", "vy", "vz")}
        )
        pred.loc[rng.random(n_p) < 0.1, "y"] = np.nan
        truth.loc[rng.random(n_t) < 0.1, "z"] = np.inf
        pred.loc[rng.random(n_p) < 0.1, "vx"] = np.nan  # matched; its error unknown
        for gate in (0.5, 2.0):
            got = velocity.match_bubbles_relative(pred, truth, gate)
            pd.testing.assert_frame_equal(got, reference(pred, truth, gate, True))
            got = velocity.match_bubbles(pred, truth, gate * 1e-3)
            pd.testing.assert_frame_equal(got, reference(pred, truth, gate * 1e-3, False))
            matched += len(got)
    assert matched > 100  # the cases pair many bubbles, not only the empty ones
