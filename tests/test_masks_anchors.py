"""Triangulated silhouette centres (surfphase.masks.anchors), the labels' downscaling, the
anchored bubbles table (surfphase.fit.outputs.anchored_table) and the mesh's visual-hull
carve, against analytic truth and brute force."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import ndimage as ndi

from surfphase.cameras import look_at
from surfphase.fit.outputs import anchored_table
from surfphase.masks.anchors import (
    ANCHOR_DEFAULTS,
    anchor_table,
    apparent_size,
    border_ids,
    coverage_centroids,
    cut_centres,
    downsample_labels,
    visible_shares,
)
from surfphase.masks.stage import scaled_instances
from surfphase.mesh.stage import silhouette_distance


def disk_cover(h: int, w: int, u0: float, v0: float, r: float, ss: int = 16) -> np.ndarray:
    """(H, W) fraction of each pixel inside the disk (centre (u0, v0) px, radius r px),
    by ss × ss supersampling (pixel centres at integers, docs/conventions.md §4)."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    cover = np.zeros((h, w))
    for dv in off:
        for du in off:
            cover += (uu + du - u0) ** 2 + (vv + dv - v0) ** 2 <= r * r
    return cover / ss**2


@pytest.mark.parametrize("u0, v0, r", [(20.3, 17.8, 3.2), (31.71, 24.45, 6.6), (15.5, 15.5, 2.1)])
def test_coverage_centroid_is_sub_pixel_where_the_binary_one_is_not(u0, v0, r):
    cover = disk_cover(48, 56, u0, v0, r)
    contrast = 0.6 * cover  # a dark disk on a flat backlight: darkness ∝ cover
    labels = np.where(cover >= 0.5, 0, -1)
    binary = ndi.center_of_mass(labels == 0)  # reference: scipy, (row, col)
    u_b, v_b, _ = coverage_centroids(contrast, labels, ring_px=0)[0]
    assert (u_b, v_b) == pytest.approx((binary[1], binary[0]), abs=1e-9)
    u, v, area = coverage_centroids(contrast, labels, ring_px=2)[0]
    err = np.hypot(u - u0, v - v0)
    assert err < 0.02, err
    assert err <= np.hypot(u_b - u0, v_b - v0) + 1e-9
    assert area == pytest.approx(np.pi * r * r, rel=0.06)


@pytest.mark.parametrize("edge", [22.3, 25.0, 27.6])
def test_a_bubble_partly_in_front_of_the_plate_weighs_each_part_by_its_own_darkness(edge):
    """A dark disk whose lower part lies in front of the plate: darkness ∝ cover there
    too, but relative to the plate's dimmer light, 0.3 instead of 0.8. With the plate's
    image given, each part's edge has its own reference and the centroid is the disk's
    (the analytic centre); one reference for the whole edge weighs the part in front of
    the plate light and lifts the centroid."""
    u0, v0, r = 30.4, 24.3, 7.0
    cover = disk_cover(48, 60, u0, v0, r)
    static = np.arange(48)[:, None] >= np.full((1, 60), int(np.ceil(edge)))
    contrast = np.where(static, 0.3, 0.8) * cover
    labels = np.where(cover >= 0.5, 0, -1)
    u, v, _ = coverage_centroids(contrast, labels, ring_px=1, static=static)[0]
    assert np.hypot(u - u0, v - v0) < 0.03
    _, v_one, _ = coverage_centroids(contrast, labels, ring_px=1)[0]
    assert v_one < v0 - 0.05  # lifted (rows grow downwards)
    off = coverage_centroids(contrast, labels, ring_px=1, static=np.zeros_like(static))[0]
    assert off == coverage_centroids(contrast, labels, ring_px=1)[0]


def test_coverage_centroids_keep_out_of_a_neighbour():
    a, b = disk_cover(40, 60, 20.2, 20.0, 5.0), disk_cover(40, 60, 32.0, 20.0, 5.0)
    labels = np.full((40, 60), -1)
    labels[a >= 0.5] = 3
    labels[b >= 0.5] = 7
    cen = coverage_centroids(0.5 * np.clip(a + b, 0, 1), labels, ring_px=2)
    assert abs(cen[3][0] - 20.2) < 0.05 and abs(cen[7][0] - 32.0) < 0.05


def _rig():
    target = np.array([0.0, 0.005, 0.0])
    c0 = look_at("cam0", [-0.04, 0.006, -0.11], target, 900.0, 160, 120)
    c1 = look_at("cam1", [0.04, 0.006, -0.11], target, 880.0, 160, 120)
    return c0, c1


def rig_40():
    """cam0 of :func:`_rig` and a cam1 40° about its target (the target (3,) m too), for
    bubbles one view sees one behind another."""
    c0, _ = _rig()
    target = np.array([0.0, 0.005, 0.0])
    a = np.deg2rad(40.0)
    eye = target + (c0.center - target) @ np.array(
        [[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]]
    )
    return c0, look_at("cam1", eye, target, 880.0, 160, 120), target


def test_anchor_table_triangulates_and_checks_agreement():
    c0, c1 = _rig()
    X = np.array([0.0011, 0.0052, -0.0007])
    r = 0.0009
    cents = []
    for cam in (c0, c1):
        uv = cam.project(X[None], distort=False)[0]
        depth = cam.world_to_camera(X[None])[0, 2]
        area = np.pi * (r * np.sqrt(cam.K[0, 0] * cam.K[1, 1]) / depth) ** 2
        cents.append({1: (uv[0], uv[1], area)})
    tab = anchor_table([c0, c1], [[cents[0]], [cents[1]]], np.array([5]))
    row = tab.iloc[0]
    assert row["frame"] == 5 and row["bubble"] == 1 and bool(row["consistent"])
    assert np.allclose(row[["x", "y", "z"]].to_numpy(float), X, atol=1e-12)
    assert row["reproj_px"] < 1e-6 and row["size_ratio"] == pytest.approx(1.0, abs=1e-9)
    assert apparent_size(c0, X, cents[0][1][2]) == pytest.approx(r, rel=1e-9)
    # A centroid 3 px off the epipolar line: the views disagree.
    off = {1: (cents[1][1][0], cents[1][1][1] + 3.0, cents[1][1][2])}
    assert not bool(anchor_table([c0, c1], [[cents[0]], [off]], np.array([5]))["consistent"][0])
    # One silhouette four times the other's area (twice the size): they disagree.
    big = {1: (*cents[1][1][:2], 4 * cents[1][1][2])}
    bad = anchor_table([c0, c1], [[cents[0]], [big]], np.array([5])).iloc[0]
    assert bad["size_ratio"] == pytest.approx(2.0, rel=1e-6) and not bool(bad["consistent"])
    # Seen by one view only, or the nucleation region: no centre.
    assert anchor_table([c0, c1], [[cents[0]], [{0: cents[1][1]}]], np.array([5])).empty


def test_the_views_agreement_limit_grows_with_the_bubble():
    """A centroid 3 px off its epipolar line puts the triangulated centre about 1.5 px
    from both: outside the 1 px floor, inside 0.15 of a 20 px radius, outside 0.15 of
    a 7 px one (a deformed bubble's centroid strays by a share of its size); a bubble
    just born of a merge is held to the 1 px."""
    c0, c1 = _rig()
    X = np.array([0.0011, 0.0052, -0.0007])
    for r_px, agree in ((20.0, True), (7.0, False)):
        cents = []
        for cam in (c0, c1):
            uv = cam.project(X[None], distort=False)[0]
            cents.append({1: (uv[0], uv[1], np.pi * r_px**2)})
        cents[1][1] = (cents[1][1][0], cents[1][1][1] + 3.0, cents[1][1][2])
        row = anchor_table([c0, c1], [[cents[0]], [cents[1]]], np.array([0])).iloc[0]
        assert 1.2 < row["reproj_px"] < 1.8
        assert bool(row["consistent"]) is agree
        fixed = anchor_table(
            [c0, c1], [[cents[0]], [cents[1]]], np.array([0]), {"max_reproj_r": 0.0}
        )
        assert not bool(fixed["consistent"][0])
        # A bubble just born of a merge (two lobes) keeps the 1 px limit.
        lobes = anchor_table([c0, c1], [[cents[0]], [cents[1]]], np.array([0]), young={0: {1}})
        assert not bool(lobes["consistent"][0])


def test_downsample_labels_is_the_block_majority():
    rng = np.random.default_rng(0)
    lab = np.full((40, 60), -1)
    for k, (u, v, r) in enumerate([(10.3, 12.1, 6), (30.2, 20.7, 9), (47.0, 28.0, 5)]):
        lab[disk_cover(40, 60, u, v, r, ss=4) >= 0.5] = k
    lab[rng.random(lab.shape) < 0.02] = 1  # scattered pixels of region 1
    out = downsample_labels(lab, (30, 20))
    # Brute force: each 2 × 2 block's most frequent region, if it covers > half.
    ref = np.full((20, 30), -1)
    for i in range(20):
        for j in range(30):
            block = lab[2 * i : 2 * i + 2, 2 * j : 2 * j + 2].ravel()
            vals, counts = np.unique(block[block >= 0], return_counts=True)
            if len(vals) and counts.max() > 2:
                ref[i, j] = vals[np.argmax(counts)]
    assert np.array_equal(out, ref)


def test_scaled_instances_match_the_downscaled_masks():
    lab = np.full((64, 80), -1)
    lab[disk_cover(64, 80, 33.4, 27.9, 10.0, ss=4) >= 0.5] = 0
    rows, cols = np.nonzero(lab == 0)
    inst = pd.DataFrame(
        {"frame": [0], "camera": ["cam0"], "bubble": [1], "area": [rows.size],
         "cx": [cols.mean()], "cy": [rows.mean()], "x0": [cols.min()], "y0": [rows.min()],
         "x1": [cols.max()], "y1": [rows.max()], "score": [1.0]}
    )  # fmt: skip
    small = downsample_labels(lab, (40, 32))
    r2, c2 = np.nonzero(small == 0)
    s = scaled_instances(inst, 0.5, 0.5).iloc[0]
    # Within the downscaled mask's own quantisation (a fraction of its pixel).
    assert s["cx"] == pytest.approx(c2.mean(), abs=0.15)
    assert s["cy"] == pytest.approx(r2.mean(), abs=0.15)
    assert s["area"] == pytest.approx(r2.size, rel=0.08)
    assert s["x0"] <= c2.min() and s["x1"] >= c2.max() and s["y0"] <= r2.min()


def _surfel_table(frames, bubbles):
    rows = []
    for f in frames:
        for b in bubbles:
            rows.append((f, f / 1000.0, b, 9.0, 9.0, 9.0, 9.0, 9.0, 9.0, 50))
    cols = ["frame", "time_s", "bubble", "x", "y", "z", "vx", "vy", "vz", "n_surfels"]
    return pd.DataFrame(rows, columns=cols)


def test_anchored_table_reports_triangulated_tracks():
    frames = np.arange(10)
    v = np.array([0.02, 0.25, -0.01])
    x0 = np.array([0.001, 0.002, 0.0])
    anchors = pd.DataFrame(
        [(f, 1, *(x0 + v * f / 1000.0)) for f in frames if f != 6]  # frame 6: not agreed
        + [(f, 2, 0.0, 0.01 + 0.3 * f / 1000.0, 0.0) for f in frames[:3]],
        columns=["frame", "bubble", "x", "y", "z"],
    )
    table = _surfel_table(frames, [0, 1, 2, 3])  # bubble 3: no centre in any frame
    out = anchored_table(table, anchors, {2, 3}, 0.0, 1)
    assert set(out[out.bubble == 0]["frame"]) == {2, 3}  # the nucleation region's frames
    assert 3 not in set(out["bubble"]) and 6 not in set(out[out.bubble == 1]["frame"])
    b1 = out[out.bubble == 1].set_index("frame")
    assert np.allclose(b1.loc[9, ["x", "y", "z"]].to_numpy(float), x0 + v * 0.009, atol=1e-15)
    # Runs 0-5 and 7-9: central differences inside, one-sided at their ends, all exact.
    assert np.allclose(b1[["vx", "vy", "vz"]].to_numpy(float), v, atol=1e-9)
    assert np.allclose(out[out.bubble == 2][["vy"]].to_numpy(float), 0.3, atol=1e-9)
    assert (out[out.bubble == 1]["n_surfels"] == 50).all()
    # Track smoothing (order 1 over 5 frames) keeps a straight track and agrees with it.
    rng = np.random.default_rng(1)
    noisy = anchors.copy()
    noisy[["x", "y", "z"]] += rng.normal(0, 2e-6, (len(noisy), 3))
    sm = anchored_table(table, noisy, set(), 0.005, 1)
    b1 = sm[sm.bubble == 1].sort_values("frame")
    run = b1[b1.frame <= 5]
    grad = np.gradient(run[["x", "y", "z"]].to_numpy(float), run["time_s"].to_numpy(), axis=0)
    assert np.allclose(grad, run[["vx", "vy", "vz"]].to_numpy(float), atol=1e-12)
    assert np.abs(run[["vx", "vy", "vz"]].to_numpy(float) - v).max() < 0.01


def test_anchored_table_reports_centres_the_fit_has_no_surfels_for():
    """A bubble leaving the frame whose continued centres (``continued``) outlast its
    surfels (frames 10-12 here) is reported there all the same, at those centres,
    with no surfels, the session's time of the frame and no velocity (their visible
    share is under ``min_visible``); so is a measured centre the fit has no surfels for
    (bubble 2 at frame 11), with or without the ``continued`` column."""
    frames = np.arange(13)
    v = np.array([0.0, 0.3, 0.0])
    X = np.array([0.0, 0.005, 0.0]) + v * frames[:, None] / 1000.0
    visible = np.r_[np.ones(8), 0.2, 0.1, 0.05, 0.02, 0.0]
    anchors = pd.DataFrame(
        [(f, 1, *X[f], visible[f], f >= 10) for f in frames]
        + [(11, 2, 0.0, 0.0, 0.0, 1.0, False)],  # measured, no surfels
        columns=["frame", "bubble", "x", "y", "z", "visible", "continued"],
    )
    table = _surfel_table(frames[:10], [1])
    out = anchored_table(table, anchors, set(), 0.0, 1, 1, None, (), 0.25)
    b1 = out[out.bubble == 1].set_index("frame")
    assert list(b1.index) == list(frames) and set(out["bubble"]) == {1, 2}
    assert np.allclose(b1.loc[10:, "time_s"], frames[10:] / 1000.0)
    assert (b1.loc[10:, "n_surfels"] == 0).all() and (b1.loc[:9, "n_surfels"] == 50).all()
    assert b1.loc[8:, ["vx", "vy", "vz"]].isna().all().all()
    assert np.abs(b1.loc[10:, ["x", "y", "z"]].to_numpy(float) - X[10:]).max() < 1e-12
    b2 = out[out.bubble == 2]
    assert list(b2["frame"]) == [11] and np.isclose(b2["time_s"].iloc[0], 0.011)
    # A lone frame is still no track: min_track_frames 3 drops bubble 2, keeps bubble 1.
    three = anchored_table(table, anchors, set(), 0.0, 1, 3, None, (), 0.25)
    assert set(three["bubble"]) == {1} and len(three) == len(frames)
    old = anchored_table(table, anchors.drop(columns="continued"), set(), 0.0, 1, 3, None, (), 0.25)
    assert old[["frame", "bubble", "x", "y", "z"]].equals(three[["frame", "bubble", "x", "y", "z"]])


def test_anchored_table_reports_a_mostly_hidden_centre_without_a_velocity():
    # A bubble rising at v leaves the frame: its last four centres come from short arcs
    # (visible share under 0.15) and drift 20-80 µm off, as a shape mode moves them.
    frames = np.arange(16)
    v = np.array([0.01, 0.3, 0.0])
    x0 = np.array([0.0, 0.005, 0.0])
    rng = np.random.default_rng(3)
    line = x0 + v * frames[:, None] / 1000.0
    centres = line + rng.normal(0, 1e-6, (16, 3))
    centres[12:, 1] += [2e-5, 4e-5, 6e-5, 8e-5]
    visible = np.r_[np.ones(10), 0.5, 0.2, 0.12, 0.09, 0.06, 0.05]
    anchors = pd.DataFrame(
        [(f, 1, *centres[f], visible[f]) for f in frames],
        columns=["frame", "bubble", "x", "y", "z", "visible"],
    )
    table = _surfel_table(frames, [1])
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    for window in (0.0, 0.005):
        out = anchored_table(table, anchors, set(), window, 1, 3, None, (), 0.15)
        out = out.set_index("frame")
        assert list(out.index) == list(frames)  # every centre is reported ...
        assert out.loc[12:, vel].isna().all().all()  # ... without a velocity there,
        # placed on the track of the others (the straight line here), not the drift.
        assert np.abs(out.loc[12:, xyz].to_numpy(float) - line[12:]).max() < 1e-5
        # The others: the track of the sure centres alone, its velocities near v ...
        alone = anchored_table(table, anchors[anchors.frame < 12], set(), window, 1, 3)
        assert np.allclose(out.loc[:11, xyz].to_numpy(float), alone[xyz].to_numpy(float))
        assert np.allclose(out.loc[:10, vel].to_numpy(float), alone[vel].to_numpy(float)[:11])
        assert np.abs(out.loc[:11, vel].to_numpy(float) - v).max() < 0.005
        # ... and the track's central differences are its velocities.
        p, t = out[xyz].to_numpy(float), out["time_s"].to_numpy(float)
        d = (p[2:12] - p[:10]) / (t[2:12] - t[:10])[:, None]
        assert np.allclose(d, out.loc[1:10, vel].to_numpy(float), atol=1e-9)
        assert np.allclose(np.gradient(p, t, axis=0)[11], out.loc[11, vel].to_numpy(float))
    # Every centre counting (the default 0), the hidden centres bend the track's end.
    out = anchored_table(table, anchors, set(), 0.005, 1, 3).set_index("frame")
    assert np.abs(out.loc[9:11, vel].to_numpy(float) - v).max() > 0.008
    # With fewer than three sure centres in its run, nothing places the hidden centres:
    # the run is reported as measured, without velocities.
    few = anchors[anchors.frame >= 10]
    out = anchored_table(table, few, set(), 0.005, 1, 3, None, (), 0.15)
    assert np.array_equal(out[xyz].to_numpy(float), centres[10:])
    assert out[vel].isna().all().all()


def test_visible_shares_of_a_disc_the_border_cuts():
    # A disc of radius 20 px centred d px inside the left border: its visible share is
    # the circular segment's area over the disc's (analytic), its pixels as counted.
    r, h, w = 20.0, 80, 80
    yy, xx = np.mgrid[0:h, 0:w]
    frames = np.array([4, 5, 6])
    labels, cents, cuts, want = [], [], [], []
    for d in (-14.0, 0.0, 9.0):
        lab = np.where((xx - d) ** 2 + (yy - 40.0) ** 2 <= r * r, 3, -1).astype(np.int32)
        labels.append(lab)
        cents.append({3: (d, 40.0, np.pi * r * r)})
        cuts.append({3})
        a = np.arccos(np.clip(-(d + 0.5) / r, -1, 1))  # pixels from column 0 (edge -0.5)
        want.append((r * r * (a - np.sin(a) * np.cos(a))) / (np.pi * r * r))
    table = pd.DataFrame({"frame": frames, "bubble": [3, 3, 3]})
    whole = [{3: (40.0, 40.0, np.pi * r * r)}] * 3
    got = visible_shares(table, [cents, whole], [cuts, [set()] * 3], [labels, labels], frames)
    assert np.allclose(got, want, atol=0.02)
    assert got[0] < 0.15 < got[1] < got[2] < 1
    # Neither view fitted: the whole silhouette is seen.
    none = [[set()] * 3, [set()] * 3]
    assert np.array_equal(
        visible_shares(table, [cents, whole], none, [labels] * 2, frames), [1, 1, 1]
    )


def test_silhouette_distance_against_brute_force_projection():
    c0, c1 = _rig()
    X = np.array([0.0, 0.005, 0.0])
    r = 0.001
    sils = []
    for cam in (c0, c1):
        uv = cam.project(X[None], distort=False)[0]
        depth = cam.world_to_camera(X[None])[0, 2]
        rp = r * cam.K[0, 0] / depth
        sils.append(disk_cover(cam.height, cam.width, uv[0], uv[1], rp, ss=2) >= 0.5)
    origin, voxel, shape = X - 0.002, 1e-4, (41, 41, 41)
    d = silhouette_distance(origin, shape, voxel, [c0, c1], sils)
    axes = [origin[i] + voxel * np.arange(shape[i]) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.ones(len(P), bool)
    for cam, sil in zip((c0, c1), sils, strict=True):
        uv = np.round(cam.project(P, distort=False)).astype(int)
        inside &= sil[uv[:, 1], uv[:, 0]]
    d = d.ravel()
    assert np.array_equal(d <= 0, inside)  # the hull is where every view sees the disk
    # The sphere is inside its own hull, the points 2 r away are not.
    dist = np.linalg.norm(P - X, axis=1)
    assert (d[dist < 0.8 * r] < 0).all() and (d[dist > 2 * r] > 0).any()


def _downscaled_ingest(native: Path, out: Path, scale: float = 0.5) -> None:
    """``out``: the ingest a run with ``ingest: scale`` and ``native_masks`` writes for the
    frames of ``native`` (cv2.INTER_AREA, cameras by the ingest's own pixel convention)."""
    import cv2

    from surfphase.cameras import load_cameras, save_cameras
    from surfphase.ingest import output_camera

    cams = load_cameras(native / "cameras.json")
    meta = json.loads((native / "meta.json").read_text())
    out.mkdir(parents=True)
    small = {}
    for name, cam in cams.items():
        st = np.load(native / f"{name}.npy")
        size = (int(round(cam.width * scale)), int(round(cam.height * scale)))
        np.save(
            out / f"{name}.npy",
            np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in st]),
        )
        small[name] = output_camera(cam, None, size)
    save_cameras(out / "cameras.json", small)
    shutil.copytree(native, out / "native")
    (out / "meta.json").write_text(json.dumps({**meta, "native": "native"}))


def test_mask_stage_centres_at_native_resolution(tmp_path):
    from test_masks_scene import rising, write_ingest

    from surfphase.cameras import load_cameras
    from surfphase.masks.stage import run_mask_stage

    tracks = [rising(-0.0015, 0.004, 0.0, 0.0006), rising(0.0016, 0.0035, 0.001, 0.0008)]
    n = 6
    native = tmp_path / "native"
    write_ingest(native, tracks, n, size=128)
    both = tmp_path / "ingest"
    _downscaled_ingest(native, both)
    coarse = tmp_path / "coarse"  # the same fit-size frames, without native ones
    shutil.copytree(both, coarse, ignore=shutil.ignore_patterns("native"))
    meta = json.loads((coarse / "meta.json").read_text())
    (coarse / "meta.json").write_text(json.dumps({**meta, "native": None}))
    run_mask_stage(both, tmp_path / "m_native")
    run_mask_stage(coarse, tmp_path / "m_coarse")
    info = json.loads((tmp_path / "m_native" / "masks.json").read_text())
    assert info["native"] and info["segmented_size"]["cam0"] == [128, 128]
    small = load_cameras(both / "cameras.json")["cam0"]
    labels = np.load(tmp_path / "m_native" / "cam0_labels.npy")
    assert labels.shape == (n, small.height, small.width) == (n, 64, 64)
    inst = pd.read_csv(tmp_path / "m_native" / "instances.csv")
    assert inst["cx"].max() < 64 and set(inst["bubble"]) == {1, 2}
    errors = {}
    for name in ("m_native", "m_coarse"):
        tab = pd.read_csv(tmp_path / name / "anchors.csv")
        assert len(tab) == 2 * n and (tab["reproj_px"] < 1).all()
        assert not tab["cut"].any()  # both spheres inside both frames
        err = []
        for r in tab.itertuples():
            # Bubble ids follow first appearance, then x: 1 is the left sphere.
            c, rad = tracks[int(r.bubble) - 1](int(r.frame))
            err.append(np.linalg.norm(np.array([r.x, r.y, r.z]) - c) / rad)
        errors[name] = float(np.mean(err))
    # A sphere's silhouettes' centroids triangulate to its centre (to perspective's
    # second order); the native masks get closer than the fit-size ones.
    assert errors["m_native"] < 0.03, errors
    assert errors["m_native"] < errors["m_coarse"], errors


def test_border_ids_are_the_regions_the_frame_may_cut():
    from surfphase.masks.anchors import border_ids

    lab = np.full((20, 30), -1)
    lab[0:4, 10:14] = 1  # touches the top
    lab[8:12, 8:12] = 2  # inside
    lab[15:19, 28:30] = 3  # touches the right
    lab[19, 0] = 0  # the nucleation region in a corner
    assert border_ids(lab) == {0, 1, 3}
    assert border_ids(lab, margin_px=9) == {0, 1, 2, 3}


def test_anchored_table_drops_runs_shorter_than_min_track_frames():
    anchors = pd.DataFrame(
        [(f, 1, 0.0, 0.001 * f, 0.0) for f in (0, 1, 2, 3, 6, 7, 9)],
        columns=["frame", "bubble", "x", "y", "z"],
    )
    out = anchored_table(_surfel_table(np.arange(10), [1]), anchors, set(), 0.0, 1, 3)
    assert list(out["frame"]) == [0, 1, 2, 3]  # runs 6-7 and 9 are too short
    assert len(anchored_table(_surfel_table(np.arange(10), [1]), anchors, set(), 0.0, 1)) == 7
    # A session shorter than min_track_frames keeps the runs that span all of it.
    two = anchors[anchors["frame"] <= 1]
    out = anchored_table(_surfel_table(np.arange(2), [1]), two, set(), 0.0, 1, 3, n_frames=2)
    assert list(out["frame"]) == [0, 1]


def test_anchored_table_without_any_anchor_keeps_the_nucleation_region():
    # No bubble has a centre both views agree on (every pair inconsistent): the table
    # holds the nucleation region's frames only, smoothing or not.
    empty = pd.DataFrame(columns=["frame", "bubble", "x", "y", "z", "low", "reproj_px"])
    table = _surfel_table(np.arange(6), [0, 1])
    for window in (0.0, 0.005):
        out = anchored_table(table, empty, {1, 2}, window, 2)
        assert list(out["bubble"]) == [0, 0] and list(out["frame"]) == [1, 2]
        assert list(out.columns) == list(table.columns)


def ellipse_cover(
    h: int, w: int, u0: float, v0: float, a: float, b: float, theta: float, ss: int = 16
) -> np.ndarray:
    """(H, W) fraction of each pixel inside the ellipse of centre (u0, v0) px,
    semi-axes a, b px, the a axis at ``theta`` rad from the columns, by ss × ss
    supersampling (pixel centres at integers)."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    c, s = np.cos(theta), np.sin(theta)
    cover = np.zeros((h, w))
    for dv in off:
        for du in off:
            x, y = uu + du - u0, vv + dv - v0
            cover += ((c * x + s * y) / a) ** 2 + ((-s * x + c * y) / b) ** 2 <= 1.0
    return cover / ss**2


def centre_row_for_visible(frac: float, a: float, b: float, theta: float) -> float:
    """Row of the centre of an ellipse (semi-axes a, b px, angle theta) of which ``frac``
    of the area lies below the image's top edge (row −0.5). A line's cut of an ellipse
    is an affine image of a circle's: at the distance t·h from the centre, h the
    ellipse's half-height ``sqrt(a² sin² θ + b² cos² θ)``, the part beyond the line is
    ``1/2 − (t sqrt(1 − t²) + asin t)/π`` of it."""
    from scipy.optimize import brentq

    hv = np.hypot(a * np.sin(theta), b * np.cos(theta))
    t = brentq(lambda t: 0.5 + (t * np.sqrt(1 - t * t) + np.arcsin(t)) / np.pi - frac, -1, 1)
    return t * hv - 0.5


# Visible fractions and the tolerance on the fitted centre (px). The outline is the
# half-cover line of the anti-aliased edge, exact to a few hundredths of a pixel
# (depending on the edge's phase on the pixel grid); the ellipse's five parameters from
# an arc amplify that as the arc shortens (up to about 0.2 px at 60 % visible, 0.12 px
# at 70 %, under 0.1 px from 80 % on these shapes), well inside the views' agreement
# limit (max_reproj_px, 1 px).
CUT_TOL = {0.6: 0.25, 0.7: 0.15, 0.8: 0.1, 0.9: 0.1}


@pytest.mark.parametrize(
    "a, b, theta, core",
    [(9.0, 9.0, 0.0, False), (11.0, 8.0, 0.3, False), (14.5, 10.2, 1.2, True), (7.0, 6.0, 2.0, False)],
)  # fmt: skip
@pytest.mark.parametrize("frac", sorted(CUT_TOL))
def test_cut_centre_is_the_fitted_ellipse_of_the_visible_outline(a, b, theta, core, frac):
    u0 = 23.3
    v0 = centre_row_for_visible(frac, a, b, theta)
    cover = ellipse_cover(40, 48, u0, v0, a, b, theta)
    assert cover.sum() / (np.pi * a * b) == pytest.approx(frac, abs=0.01)  # the reference
    contrast = 0.6 * cover
    inside = cover >= 0.5
    if core:  # a backlit bubble's bright core, cut open by the frame: the mask is a ring
        bright = ellipse_cover(40, 48, u0, v0, 0.5 * a, 0.5 * b, theta)
        contrast = contrast - 0.55 * bright
        inside &= bright < 0.5
        if frac <= 0.7:  # the core reaches the border: no hole to fill in the mask
            assert np.array_equal(ndi.binary_fill_holes(inside), inside)
    labels = np.where(inside, 4, -1)
    assert border_ids(labels) == {4}
    u, v, area = cut_centres(contrast, labels, {4}, ring_px=2, min_visible=0.55)[4]
    err = np.hypot(u - u0, v - v0)
    assert err < CUT_TOL[frac], err
    # The full ellipse's area, not the visible part's (the views' size check).
    assert area == pytest.approx(np.pi * a * b, rel=0.05)


def test_cut_centres_give_none_when_too_little_is_visible():
    a, b, theta = 11.0, 8.0, 0.3
    lim = ANCHOR_DEFAULTS["min_visible"]
    for frac, expect in ((lim - 0.15, False), (lim + 0.1, True)):
        cover = ellipse_cover(40, 48, 23.3, centre_row_for_visible(frac, a, b, theta), a, b, theta)
        labels = np.where(cover >= 0.5, 2, -1)
        assert (2 in cut_centres(0.6 * cover, labels, {2}, 2, lim)) is expect, frac
    assert cut_centres(0.6 * cover, labels, {2}, 2, 1.01) == {}  # above 1: fits off
    # A sliver along the border (a few rows): no outline to fit, no centre.
    cover = ellipse_cover(40, 48, 23.3, -b + 1.5, a, b, theta)
    assert cut_centres(0.6 * cover, np.where(cover >= 0.5, 2, -1), {2}, 2, 0.0) == {}


@pytest.mark.parametrize(
    ("a", "b", "theta", "frac"), [(9.0, 8.0, 0.3, 0.1), (14.0, 13.0, 1.0, 0.05)]
)
def test_a_short_arc_across_the_border_gets_no_ellipse_of_its_own(a, b, theta, frac):
    """A bubble 5-10 % inside the frame: with sensor noise, the ellipse fitted to its
    short visible arc is often flat and closes just past the border, so that 60 % or
    more of it reads as visible and its centre is a radius or more off. Such fits fail
    the aspect or the inside-area test; the bubble gets no centre from its own arc."""
    v0 = centre_row_for_visible(frac, a, b, theta)
    cover = ellipse_cover(40, 48, 23.3, v0, a, b, theta)
    rng = np.random.default_rng(0)
    loose, strict = [], []
    for _ in range(20):
        con = 0.6 * cover + rng.normal(0.0, 0.03, cover.shape) * (cover > 0)
        lab = np.where(con >= 0.3, 2, -1)
        assert border_ids(lab) == {2}
        loose.append(cut_centres(con, lab, {2}, 1, 0.6, max_aspect=np.inf, max_area_error=np.inf))
        strict.append(cut_centres(con, lab, {2}, 1, 0.6))
    off = [np.hypot(f[2][0] - 23.3, f[2][1] - v0) / np.sqrt(a * b) for f in loose if 2 in f]
    assert len(off) >= 3 and min(off) > 0.5, off  # the fault, without the two tests
    assert all(f == {} for f in strict)


def test_ellipse_area_inside_the_frame_against_the_circular_segment():
    """A circle cut by the top border: its part inside is the circular segment
    (analytic); a whole rotated ellipse: pi a b."""
    from surfphase.masks.anchors import ellipse_area_inside

    r, h, w = 10.0, 40, 48
    for v in (-6.0, -0.5, 4.0):
        d = v + 0.5  # the centre's distance below the frame's top edge (row -0.5)
        seg = r * r * np.arccos(-d / r) + d * np.sqrt(r * r - d * d)
        assert ellipse_area_inside((20.0, v, r, r, 0.0), (h, w), 0.05) == pytest.approx(
            seg, rel=5e-3
        )
    assert ellipse_area_inside((24.0, 20.0, 9.0, 6.0, 35.0), (h, w), 0.05) == pytest.approx(
        np.pi * 54.0, rel=5e-3
    )


@pytest.mark.parametrize("frac", [0.3, 0.4, 0.5])
def test_a_bubble_leaving_the_frame_keeps_the_shape_its_track_showed_whole(frac):
    """A bubble rising out of the top of the frame: whole in frame 0, then 50 to 30 %
    inside, too little for an ellipse of its own. Its centre is the whole frame's
    ellipse moved onto the visible outline: within 0.2 px of the truth, with the whole
    area; below ``min_visible_tracked`` of it inside, none."""
    from surfphase.masks.anchors import tracked_cut_centres

    a, b, theta, u0 = 11.0, 8.0, 0.3, 23.3
    rows = [20.0, centre_row_for_visible(frac, a, b, theta)]
    covers = [ellipse_cover(40, 48, u0, v, a, b, theta) for v in rows]
    labels = np.stack([np.where(c >= 0.5, 2, -1) for c in covers]).astype(np.int32)
    contrasts = [0.6 * c for c in covers]
    assert border_ids(labels[1]) == {2} and border_ids(labels[0]) == set()
    assert cut_centres(contrasts[1], labels[1], {2}, 1, ANCHOR_DEFAULTS["min_visible"]) == {}
    lim = ANCHOR_DEFAULTS["min_visible_tracked"]
    got = tracked_cut_centres(contrasts.__getitem__, labels, {1: {2}}, 1, lim)
    u, v, area = got[1][2]
    assert np.hypot(u - u0, v - rows[1]) < 0.2, (u - u0, v - rows[1])
    assert area == pytest.approx(np.pi * a * b, rel=0.03)
    # Less inside than min_visible_tracked, or no frame showing it whole: no centre.
    assert tracked_cut_centres(contrasts.__getitem__, labels, {1: {2}}, 1, frac + 0.05) == {}
    assert tracked_cut_centres(contrasts[1:].__getitem__, labels[1:], {0: {2}}, 1, lim) == {}


def test_anchor_table_triangulates_a_bubble_cut_by_one_view_border():
    c0, _ = _rig()
    r = 0.0009
    # The sphere's centre where cam0 sees it 2.5 px below its top row (its silhouette
    # about 70 % inside the frame); cam1 looks straight at it.
    x0 = np.array([0.0011, 0.0, -0.0007])

    def row(y: float) -> float:
        return float(c0.project(np.array([[x0[0], y, x0[2]]]), distort=False)[0, 1]) - 2.5

    from scipy.optimize import brentq

    X = np.array([x0[0], brentq(row, -0.02, 0.03), x0[2]])
    c1 = look_at("cam1", [0.04, 0.006, -0.11], X, 880.0, 160, 120)
    cents, cut = [], []
    for cam in (c0, c1):
        uv = cam.project(X[None], distort=False)[0]
        rp = r * np.sqrt(cam.K[0, 0] * cam.K[1, 1]) / cam.world_to_camera(X[None])[0, 2]
        cover = disk_cover(cam.height, cam.width, uv[0], uv[1], rp)
        labels = np.where(cover >= 0.5, 1, -1)
        cen = coverage_centroids(0.6 * cover, labels)
        edge = border_ids(labels)
        fits = cut_centres(0.6 * cover, labels, edge, min_visible=ANCHOR_DEFAULTS["min_visible"])
        cents.append({**{k: v for k, v in cen.items() if k not in edge}, **fits})
        cut.append(set(fits))
    assert cut == [{1}, set()]  # cut in cam0 only
    row = anchor_table(
        [c0, c1], [[cents[0]], [cents[1]]], np.array([3]), None, [[cut[0]], [cut[1]]]
    )
    row = row.iloc[0]
    assert bool(row["cut"]) and bool(row["consistent"])
    assert row["size_ratio"] < 1.05  # the fitted full area, not the cut one
    # The fitted centre is within 0.12 px (test above), the other view's centroid within
    # 0.02 px: at about 0.12 m and f ≈ 900 px, with the depth error ~1.6 × the lateral
    # one for these views' 40° apart, the 3D centre is within 0.05 r.
    err = np.linalg.norm(row[["x", "y", "z"]].to_numpy(float) - X)
    assert err < 0.05 * r, err / r
    assert row["reproj_px"] < 0.2


def test_nucleation_frames_need_every_view():
    """The nucleation region is reported in a frame only when every view shows it."""
    from surfphase.fit.outputs import nucleation_frames

    a = np.full((3, 4, 4), -1, np.int32)
    b = a.copy()
    a[1, 0, 0] = b[1, 3, 3] = 0  # both views
    a[2, 1, 1] = 0  # one view only
    b[0, 2, 2] = 5  # a bubble, not the nucleation region
    assert nucleation_frames([a, b], np.array([10, 11, 12])) == {11}


def test_low_bottoms_triangulates_each_silhouettes_lowest_row():
    """A bubble whose lowest pixels are the projections of a point 40 µm above the plate
    is low; one whose lowest pixels project a point 1 mm up is not (heights 0.3 mm)."""
    import pandas as pd
    from test_masks_scene import rig

    from surfphase.masks.anchors import low_bottoms

    cams = [c.undistorted() for c in rig(512).values()]
    labels = [np.full((1, 512, 512), -1, np.int32) for _ in cams]
    for b, y in ((1, 4e-5), (2, 1e-3)):
        X = np.array([[0.002 * b - 0.003, y, 0.0]])
        for cam, lab in zip(cams, labels, strict=True):
            u, v = np.rint(cam.project(X)[0]).astype(int)
            lab[0, v - 6 : v + 1, u - 3 : u + 4] = b  # a blob whose lowest row is row v
    table = pd.DataFrame({"frame": [7, 7], "bubble": [1, 2]}, index=[5, 3])
    assert low_bottoms(table, cams, labels, np.array([7]), 3e-4).tolist() == [True, False]
    table = pd.DataFrame({"frame": [7, 7, 7], "bubble": [2, 9, 1]})  # 9: not in the frame
    assert low_bottoms(table, cams, labels, np.array([7]), 3e-4).tolist() == [False, False, True]


def test_lowest_point_follows_a_disk_by_tenths_of_a_pixel():
    """A disk (r 6 px) moved down 0.1 px and across 0.37 px a frame over 20 frames:
    the vertex of the parabola through its bottom outline follows its lowest pixel
    centre (v0 + r − 0.5) with under half the rms error of the lowest row, which moves
    in whole pixels (0.12 against 0.29 px here); a flat bottom gives the lowest row."""
    from surfphase.masks.anchors import lowest_point

    vertex, row = [], []
    for k in range(20):
        u0, v0, r = 20.3 + 0.37 * k, 15.0 + 0.1 * k, 6.0
        ys, xs = np.nonzero(disk_cover(60, 60, u0, v0, r, ss=8) >= 0.5)
        u, v = lowest_point(ys, xs, r / 2)
        vertex.append(v - (v0 + r - 0.5))
        row.append(ys.max() - (v0 + r - 0.5))
        assert abs(u - u0) < 0.5
    rms = [float(np.sqrt(np.mean(np.square(e)))) for e in (vertex, row)]
    assert rms[0] < 0.5 * rms[1] and max(map(abs, vertex)) < 0.3, rms
    flat = np.zeros((10, 10), bool)
    flat[2:6, 1:9] = True
    ys, xs = np.nonzero(flat)
    assert lowest_point(ys, xs, 2.0) == (4.5, 5.0)


@pytest.mark.parametrize("rows_in", [(-2.0, -1.0), (-4.0, 0.0), (0.5, -3.5)])
def test_a_bubble_never_whole_gets_the_sphere_both_views_arcs_agree_on(rows_in):
    """A sphere leaving the top of both views, never whole in either: only an arc of
    each silhouette is inside (``rows_in`` rows of its centre's projection below the top
    edge, negative = above; 15-60 % visible). The sphere fitted to both arcs at once
    gives each view's projected centre within 0.35 px and its radius within 5 %
    (reference: the sphere projected analytically), and the triangulated centre is
    within 0.1 r; with a ``min_visible_sphere`` above the visible share, none."""
    from scipy.optimize import brentq

    from surfphase.masks.anchors import sphere_centres, visible_outline

    c0, _ = _rig()
    r = 0.0011
    x0 = np.array([0.0008, 0.0, -0.0006])

    def row(y: float, cam, k: float) -> float:
        return float(cam.project(np.array([[x0[0], y, x0[2]]]), distort=False)[0, 1]) - k

    X = np.array([x0[0], brentq(lambda y: row(y, c0, rows_in[0]), -0.02, 0.03), x0[2]])
    # cam1 tilted so that the centre's row is rows_in[1]: its target moved up or down.
    dy = brentq(
        lambda d: (
            float(
                look_at("cam1", [0.04, 0.006, -0.11], X + [0, d, 0], 880.0, 160, 120).project(
                    X[None], distort=False
                )[0, 1]
            )
            - rows_in[1]
        ),
        -0.03,
        0.03,
    )
    c1 = look_at("cam1", [0.04, 0.006, -0.11], X + [0, dy, 0], 880.0, 160, 120)
    outlines, covers, truth = [], [], []
    for cam in (c0, c1):
        uv = cam.project(X[None], distort=False)[0]
        rp = r * np.sqrt(cam.K[0, 0] * cam.K[1, 1]) / cam.world_to_camera(X[None])[0, 2]
        cover = disk_cover(cam.height, cam.width, uv[0], uv[1], rp)
        labels = np.where(cover >= 0.5, 3, -1)
        assert border_ids(labels) == {3}
        frac = cover.sum() / (np.pi * rp * rp)
        assert frac < ANCHOR_DEFAULTS["min_visible"]  # too little for cut_centres
        pts, cov = visible_outline(0.6 * cover, labels, labels, 3, 0)
        outlines.append(pts)
        covers.append(cov)
        truth.append((uv, rp, frac))
    got = sphere_centres([c0, c1], outlines, covers, min_visible=0.1)
    assert got is not None
    for (u, v, area), (uv, rp, _) in zip(got, truth, strict=True):
        assert np.hypot(u - uv[0], v - uv[1]) < 0.35, (u - uv[0], v - uv[1])
        assert np.sqrt(area / np.pi) == pytest.approx(rp, rel=0.05)
    tab = anchor_table([c0, c1], [[{3: got[0]}], [{3: got[1]}]], np.array([0]))
    err = np.linalg.norm(tab[["x", "y", "z"]].to_numpy(float)[0] - X)
    assert bool(tab["consistent"][0]) and err < 0.1 * r, err / r
    least = min(t[2] for t in truth)
    assert sphere_centres([c0, c1], outlines, covers, min_visible=least + 0.05) is None


@pytest.mark.parametrize("rows_in", [-5.0, -3.0, 0.0])
def test_a_bubble_cut_in_one_view_gets_its_depth_from_that_views_arc(rows_in):
    """A sphere 15-50 % inside cam0 (its centre ``rows_in`` rows from the top edge) and
    whole in cam1: on cam1's centre ray, with cam1's size, the depth that puts cam0's
    circle on cam0's visible arc gives cam0's projected centre within 0.2 px and the
    sphere's centre within 0.05 r (reference: the sphere projected analytically)."""
    from scipy.optimize import brentq

    from surfphase.masks.anchors import sphere_centres, visible_outline

    c0, _ = _rig()
    r = 0.0011
    x0 = np.array([0.0008, 0.0, -0.0006])

    def row(y: float) -> float:
        return float(c0.project(np.array([[x0[0], y, x0[2]]]), distort=False)[0, 1]) - rows_in

    X = np.array([x0[0], brentq(row, -0.02, 0.03), x0[2]])
    c1 = look_at("cam1", [0.04, 0.006, -0.11], X, 880.0, 160, 120)
    uv0 = c0.project(X[None], distort=False)[0]
    rp0 = r * np.sqrt(c0.K[0, 0] * c0.K[1, 1]) / c0.world_to_camera(X[None])[0, 2]
    cover = disk_cover(c0.height, c0.width, uv0[0], uv0[1], rp0)
    labels = np.where(cover >= 0.5, 3, -1)
    frac = cover.sum() / (np.pi * rp0 * rp0)
    assert 0.1 < frac < ANCHOR_DEFAULTS["min_visible"]
    pts, cov = visible_outline(0.6 * cover, labels, labels, 3, 0)
    uv1 = c1.project(X[None], distort=False)[0]
    rp1 = r * np.sqrt(c1.K[0, 0] * c1.K[1, 1]) / c1.world_to_camera(X[None])[0, 2]
    known = (None, (float(uv1[0]), float(uv1[1]), float(np.pi * rp1 * rp1)))
    got = sphere_centres([c0, c1], [pts, None], [cov, 0.0], known, min_visible=0.1)
    assert got is not None and got[1] == known[1]
    u, v, area = got[0]
    assert np.hypot(u - uv0[0], v - uv0[1]) < 0.2, (u - uv0[0], v - uv0[1])
    assert np.sqrt(area / np.pi) == pytest.approx(rp0, rel=0.02)
    tab = anchor_table([c0, c1], [[{3: got[0]}], [{3: got[1]}]], np.array([0]))
    err = np.linalg.norm(tab[["x", "y", "z"]].to_numpy(float)[0] - X)
    assert bool(tab["consistent"][0]) and err < 0.05 * r, err / r


@pytest.mark.parametrize("a, b, theta", [(11.0, 8.0, 0.0), (9.0, 9.0, 0.0), (12.0, 9.5, 0.4)])
def test_a_shrinking_arc_registers_onto_the_arc_it_is_part_of(a, b, theta):
    """An oblate silhouette leaving the top of the frame: 55 % inside in the reference
    frame, 40 / 30 / 20 % in later ones. Laying each visible arc onto the reference's
    by a translation gives the true displacement within 0.1 px, where a circle fitted
    anew to each arc drifts by half a pixel to a pixel or more (the arc bends less than a circle)."""
    from surfphase.masks.anchors import (
        circle_fit,
        region_owners,
        register_outline,
        visible_outline,
    )

    u0 = 23.3
    outs, rows = [], []
    for frac in (0.55, 0.4, 0.3, 0.2):
        v0 = centre_row_for_visible(frac, a, b, theta)
        cover = ellipse_cover(40, 48, u0 + 0.37 * len(rows), v0, a, b, theta)
        labels = np.where(cover >= 0.5, 5, -1)
        outs.append(visible_outline(0.6 * cover, labels, region_owners(labels, 1), 5, 1)[0])
        rows.append(v0)
    drift = []
    for k in range(1, 4):
        truth = np.array([0.37 * k, rows[k] - rows[0]])
        d, rms = register_outline(outs[k], outs[0])
        assert np.hypot(*(-d - truth)) < 0.1, (-d, truth)
        assert rms < 0.1
        c0, ck = circle_fit(outs[0]), circle_fit(outs[k])
        drift.append(np.hypot(*(np.subtract(ck[:2], c0[:2]) - truth)))
    if a != b:
        assert max(drift) > 0.5, drift


@pytest.mark.parametrize("angle", [90.0, 60.0, 0.0])
def test_two_lobes_centroid_weighs_each_by_its_volume(angle):
    """Two touching spheres of 10 and 13 px radius along an axis at ``angle`` degrees
    (the silhouette of a young merged bubble): the solid of revolution about the
    silhouette's long axis has its centroid within 0.15 px of the spheres' volume
    centroid (analytic, r³-weighted), where the silhouette's centroid (r²-weighted)
    is 1.3 px off, towards the smaller lobe."""
    from surfphase.masks.anchors import lobe_centroids

    r1, r2 = 10.0, 13.0
    a = np.radians(angle)
    d = np.array([np.cos(a), np.sin(a)])
    c1 = np.array([40.3, 39.6]) - 0.5 * (r1 + r2) * d
    c2 = c1 + (r1 + r2 - 0.5) * d
    cover = np.clip(disk_cover(80, 84, *c1, r1) + disk_cover(80, 84, *c2, r2), 0, 1)
    labels = np.where(cover >= 0.5, 2, -1)
    vol = (r1**3 * c1 + r2**3 * c2) / (r1**3 + r2**3)
    area = (r1**2 * c1 + r2**2 * c2) / (r1**2 + r2**2)
    u, v, s = lobe_centroids(0.6 * cover, labels, {2}, ring_px=1)[2]
    assert np.hypot(u - vol[0], v - vol[1]) < 0.15, (u - vol[0], v - vol[1])
    uc, vc, sc = coverage_centroids(0.6 * cover, labels, ring_px=1)[2]
    assert np.hypot(uc - area[0], vc - area[1]) < 0.15
    assert np.hypot(*(vol - area)) > 1.0
    assert s == pytest.approx(sc, rel=1e-12)  # the same cover, the same area
    # One sphere: its centre either way.
    one = disk_cover(60, 60, 30.3, 29.8, 11.0)
    lab1 = np.where(one >= 0.5, 1, -1)
    u, v, _ = lobe_centroids(0.6 * one, lab1, {1}, ring_px=1)[1]
    assert np.hypot(u - 30.3, v - 29.8) < 0.05


def test_young_merged_spans_the_lobe_time_from_the_merge_both_views_saw():
    from surfphase.masks.stage import young_merged

    ev = pd.DataFrame(
        [
            (10, "cam0", "merge", "3+4", "5"),
            (11, "cam1", "merge", "3+4", "5"),
            (4, "cam0", "merge", "1", "6"),  # one view only: not a merge of the bubbles
            (2, "cam0", "split", "2", "7+8"),
        ],
        columns=["frame", "camera", "event", "parents", "children"],
    )
    got = young_merged(ev, ["cam0", "cam1"], 24, 7500.0, 0.001)  # 7.5 → 8 frames
    assert got == {k: {5} for k in range(10, 18)}
    assert young_merged(ev, ["cam0", "cam1"], 14, 7500.0, 0.001) == {k: {5} for k in range(10, 14)}
    assert young_merged(ev, ["cam0", "cam1"], 24, 1000.0, 0.0001) == {10: {5}}  # ≥ 1
    assert young_merged(ev, ["cam0", "cam1"], 24, None, 0.001) == {}
    assert young_merged(ev, ["cam0", "cam1"], 24, 7500.0, 0.0) == {}


def test_a_spheroid_leaving_both_views_keeps_its_velocity():
    """An oblate bubble (semi-axes 1.2 and 0.85 of its radius across and along the
    vertical) rising out of the top of both views, never whole: 55 % inside in the first
    frame, then down to 25 %. The mask stage's centres (the sphere both views' arcs give in the
    most visible frame, the other frames' arcs moved onto it) rise with the bubble to
    within 3 % of its true displacement per frame, where a sphere fitted anew in each
    frame drifts by more than 10 % (reference: the true centres)."""
    from surfphase.masks.classical import CLASSICAL_DEFAULTS
    from surfphase.masks.stage import sphere_cut_centres

    c0, c1 = _rig()
    r = 0.0011
    x0 = np.array([0.0008, 0.0, -0.0006])
    f0 = np.sqrt(c0.K[0, 0] * c0.K[1, 1])

    def centre_for_row(v: float) -> np.ndarray:
        from scipy.optimize import brentq

        y = brentq(lambda y: c0.project(np.array([[x0[0], y, x0[2]]]), distort=False)[0, 1] - v,
                   -0.02, 0.03)  # fmt: skip
        return np.array([x0[0], y, x0[2]])

    rp = f0 * r / c0.world_to_camera(centre_for_row(0.0)[None])[0, 2]
    start = centre_for_row(centre_row_for_visible(0.55, 1.2 * rp, 0.85 * rp, 0.0))
    depth = float(c0.world_to_camera(start[None])[0, 2])
    step = np.array([0.0, 0.9 * depth / f0, 0.0])  # 0.9 px a frame upwards
    X = [start + k * step for k in range(4)]
    stacks, labels = {}, {}
    for cam in (c0, c1):
        imgs, labs = [], []
        for Xk in X:
            uv = cam.project(Xk[None], distort=False)[0]
            rho = np.sqrt(cam.K[0, 0] * cam.K[1, 1]) * r / cam.world_to_camera(Xk[None])[0, 2]
            cover = ellipse_cover(cam.height, cam.width, uv[0], uv[1], 1.2 * rho, 0.85 * rho, 0.0)
            imgs.append(1.0 - 0.6 * cover)
            labs.append(np.where(cover >= 0.5, 1, -1).astype(np.int32))
        stacks[cam.name], labels[cam.name] = np.stack(imgs), np.stack(labs)
    bgs = {c: (np.ones((c1.height, c1.width)), np.zeros((c1.height, c1.width), bool))
           for c in stacks}  # fmt: skip
    params = {"classical": CLASSICAL_DEFAULTS, "anchors": ANCHOR_DEFAULTS}
    cents = [[{} for _ in X] for _ in (0, 1)]
    cuts = [[set() for _ in X] for _ in (0, 1)]
    sphere_cut_centres(stacks, labels, bgs, [c0, c1], cents, cuts, params)
    assert all(1 in cents[k][t] for k in (0, 1) for t in range(len(X)))
    tab = anchor_table([c0, c1], cents, np.arange(len(X)), None, cuts)
    got = tab[["x", "y", "z"]].to_numpy(float)
    moves = np.linalg.norm(np.diff(got, axis=0) - step, axis=1) / np.linalg.norm(step)
    assert moves.max() < 0.03, moves
    # A sphere fitted anew in every frame.
    from surfphase.masks.anchors import region_owners, sphere_centres, visible_outline

    alone = []
    for t in range(len(X)):
        vis = []
        for cam in (c0, c1):
            lab = labels[cam.name][t]
            con = 1.0 - stacks[cam.name][t]
            vis.append(visible_outline(con, lab, region_owners(lab, 1), 1, 1))
        fit = sphere_centres([c0, c1], [v[0] for v in vis], [v[1] for v in vis], min_visible=0.05)
        alone.append(anchor_table([c0, c1], [[{1: fit[0]}], [{1: fit[1]}]], np.array([t]))
                     [["x", "y", "z"]].to_numpy(float)[0])  # fmt: skip
    drift = np.linalg.norm(np.diff(alone, axis=0) - step, axis=1) / np.linalg.norm(step)
    assert drift.max() > 0.1, drift


@pytest.mark.parametrize("lateral", [0.0006, 0.0012])
def test_two_bubbles_one_view_fuses_get_their_circles_from_its_outline(lateral):
    """Two spheres (r 1.1 and 0.9 mm) one behind the other for cam1 (4 mm apart along
    its line of sight, ``lateral`` across it), apart for cam0, 40° away. From cam0's
    whole silhouettes (centres and areas) and the fused silhouette's visible outline in
    cam1, each sphere's circle in cam1 is within 0.25 px of its analytic projection
    (radius within 3 %), the depths order them as they are, and the triangulated
    centres are within 0.05 r of the truth."""
    from surfphase.masks.anchors import occluded_centres, visible_outline

    c0, c1, target = rig_40()
    d = (target - c1.center) / np.linalg.norm(target - c1.center)
    side = np.cross(d, [0.0, 1.0, 0.0])
    X = [target - 0.002 * d, target + 0.002 * d + lateral * side / np.linalg.norm(side)]
    r = [0.0011, 0.0009]

    def circle(cam, x, rr):
        uv = cam.project(x[None], distort=False)[0]
        return uv, rr * np.sqrt(cam.K[0, 0] * cam.K[1, 1]) / cam.world_to_camera(x[None])[0, 2]

    known = {}
    for b, x, rr in zip((4, 7), X, r, strict=True):
        uv, rp = circle(c0, x, rr)
        known[b] = (float(uv[0]), float(uv[1]), float(np.pi * rp * rp))
    truth = [circle(c1, x, rr) for x, rr in zip(X, r, strict=True)]
    assert np.hypot(*(truth[0][0] - truth[1][0])) < truth[0][1] + truth[1][1]  # fused
    cover = np.maximum(*(disk_cover(120, 160, uv[0], uv[1], rp) for uv, rp in truth))
    labels = np.where(cover >= 0.5, 4, -1)
    assert ndi.label(labels == 4)[1] == 1
    pts, _cov = visible_outline(0.6 * cover, labels, labels, 4, 0)
    got = occluded_centres([c0, c1], 1, pts, known)
    assert got is not None
    for b, (uv, rp) in zip((4, 7), truth, strict=True):
        u, v, area, _z = got[b]
        assert np.hypot(u - uv[0], v - uv[1]) < 0.25, (b, u - uv[0], v - uv[1])
        assert np.sqrt(area / np.pi) == pytest.approx(rp, rel=0.03)
    assert got[4][3] < got[7][3]  # the first sphere is in front
    tab = anchor_table([c0, c1], [[known], [{b: got[b][:3] for b in got}]], np.array([0]))
    for b, x, rr in zip((4, 7), X, r, strict=True):
        row = tab[tab.bubble == b]
        assert np.linalg.norm(row[["x", "y", "z"]].to_numpy(float)[0] - x) < 0.05 * rr
    # One bubble alone does not explain the outline: no fit with the other left out.
    assert occluded_centres([c0, c1], 1, pts, {4: known[4]}) is None


@pytest.mark.parametrize(
    "lateral, lift, keep", [(0.0006, 0.0012, 0.6), (0.0012, 0.0012, 0.6), (0.0009, 0.001, 0.5)]
)
def test_a_bubble_fused_with_an_attached_one_gets_its_circle(lateral, lift, keep):
    """A free sphere (r 1.1 mm, ``lift`` m up) in front of an attached bubble for cam1
    (4 mm apart along its line of sight, ``lateral`` across it), apart for cam0, 40°
    away. The attached bubble is no sphere: the plate's line cuts its disc in both
    views, ``keep`` of its diameter left, and cam0's entry for it is that cut disc's
    centroid and area (its sphere's ray and size biased). The fused outline misses the
    sphere's rms test with both held to their rays; with the attached one ``loose`` (a
    circle free in cam1), the free sphere's circle in cam1 is within 0.1 px of its
    analytic projection (radius within 1 %), in front."""
    from surfphase.masks.anchors import occluded_centres, visible_outline

    c0, c1, target = rig_40()
    d = (target - c1.center) / np.linalg.norm(target - c1.center)
    side = np.cross(d, [0.0, 1.0, 0.0])
    X = [
        target - 0.002 * d + [0.0, lift, 0.0],
        target + 0.002 * d + lateral * side / np.linalg.norm(side),
    ]
    r = [0.0011, 0.0009]

    def circle(cam, x, rr):
        uv = cam.project(x[None], distort=False)[0]
        return uv, rr * np.sqrt(cam.K[0, 0] * cam.K[1, 1]) / cam.world_to_camera(x[None])[0, 2]

    def attached(cam):
        uv, rp = circle(cam, X[1], r[1])
        rows = np.arange(120)[:, None]
        return disk_cover(120, 160, uv[0], uv[1], rp) * (rows <= uv[1] + (2 * keep - 1) * rp)

    uv, rp = circle(c0, X[0], r[0])
    cover0 = attached(c0)
    known = {
        4: (float(uv[0]), float(uv[1]), float(np.pi * rp * rp)),
        7: coverage_centroids(0.6 * cover0, np.where(cover0 >= 0.5, 7, -1), 0)[7],
    }
    (u4, v4), r4 = circle(c1, X[0], r[0])
    cover = np.maximum(disk_cover(120, 160, u4, v4, r4), attached(c1))
    labels = np.where(cover >= 0.5, 4, -1)
    assert ndi.label(labels == 4)[1] == 1
    pts, _cov = visible_outline(0.6 * cover, labels, labels, 4, 0)
    assert occluded_centres([c0, c1], 1, pts, known) is None
    got = occluded_centres([c0, c1], 1, pts, known, loose=[7])
    assert got is not None
    assert np.hypot(got[4][0] - u4, got[4][1] - v4) < 0.1
    assert np.sqrt(got[4][2] / np.pi) == pytest.approx(r4, rel=0.01)
    assert got[4][3] < got[7][3]


def _leaving_sphere(fps: float, n: int):
    """A 0.8 mm sphere rising at 0.3 m/s out of the top of both views of :func:`_rig`:
    its (n, 3) centres (m), radius (m) and per view (n, H, W) labels (id 4 where the
    sphere covers at least half of a pixel)."""
    from scipy.optimize import brentq

    c0, c1 = _rig()
    r = 0.0008
    x0 = np.array([0.0004, 0.0, -0.0003])
    # The height where the centre projects onto cam0's top edge; start 0.4 mm below.
    top = brentq(lambda y: c0.project((x0 + [0, y, 0])[None], distort=False)[0, 1] + 0.5, 0, 0.03)
    t = np.arange(n) / fps
    X = x0 + [0.0, top - 0.0004, 0.0] + np.outer(t, [0.01, 0.3, -0.02])
    labs = []
    for cam in (c0, c1):
        f = np.sqrt(cam.K[0, 0] * cam.K[1, 1])
        stack = []
        for x in X:
            u, v = cam.project(x[None], distort=False)[0]
            rp = r * f / cam.world_to_camera(x[None])[0, 2]
            stack.append(np.where(disk_cover(cam.height, cam.width, u, v, rp, 4) >= 0.5, 4, -1))
        labs.append(np.stack(stack))
    return (c0, c1), X, r, labs


def _disc_meets(u: float, v: float, rho: float, shape: tuple[int, int]) -> bool:
    """Brute force: whether a point of the disc (polar samples, 0.002 px apart at most
    along the rim) lies in the image's pixel area [-0.5, W - 0.5) x [-0.5, H - 0.5)."""
    s = np.linspace(0.0, 1.0, 201)[:, None]
    a = np.linspace(0.0, 2.0 * np.pi, max(int(2 * np.pi * rho / 0.002), 16))[None]
    x, y = u + rho * s * np.cos(a), v + rho * s * np.sin(a)
    return bool(((x >= -0.5) & (x < shape[1] - 0.5) & (y >= -0.5) & (y < shape[0] - 0.5)).any())


def _leaving_anchors(X: np.ndarray, r: float) -> pd.DataFrame:
    """:func:`_leaving_sphere`'s consistent centres of frames 0-7, cut from frame 3."""
    return pd.DataFrame(
        [(f, 4, *X[f], 0.0, 1.0, r, f >= 3, True) for f in range(8)],
        columns=["frame", "bubble", "x", "y", "z", "reproj_px", "size_ratio", "r_m", "cut",
                 "consistent"],
    )  # fmt: skip


def test_a_leaving_bubble_is_continued_along_its_track_while_both_views_see_it():
    """A sphere leaving the top of both views whose centres stop while slivers still
    show (here: after frame 7): its centre continues the line of its last centres
    (analytic truth: straight at constant speed) in each later frame where a view still
    has its pixels and its circle (grown by 0.1 radius + 1 px) reaches into both
    frames, with its radius, for up to ``continue_s``, and no further; a sliver off the
    continued circle, a run that does not end cut, or ``continue_s`` 0 stops it."""
    from surfphase.masks.anchors import continued_centres

    fps, n = 5000.0, 40
    cams, X, r, labs = _leaving_sphere(fps, n)
    anchors = _leaving_anchors(X, r)
    frames = np.arange(n)

    def seen(f: int) -> bool:  # pixels in a view, and the circle reaches both frames
        rho = [
            r * np.sqrt(c.K[0, 0] * c.K[1, 1]) / c.world_to_camera(X[f][None])[0, 2] for c in cams
        ]
        uv = [c.project(X[f][None], distort=False)[0] for c in cams]
        return any((lab[f] == 4).any() for lab in labs) and all(
            _disc_meets(*uv[k], 1.1 * rho[k] + 1.0, (c.height, c.width)) for k, c in enumerate(cams)
        )

    last = next(f for f in range(8, n) if not seen(f))  # the first frame it is not seen
    assert 8 + 10 < last < n  # seen past continue_s (10 frames), gone before the end
    out = continued_centres(anchors, cams, labs, frames, fps, 0.02)
    assert list(out["frame"]) == list(range(8, last))
    assert np.abs(out[["x", "y", "z"]].to_numpy(float) - X[out["frame"]]).max() < 1e-9
    assert np.allclose(out["r_m"], r) and out["cut"].all() and out["consistent"].all()
    share = [
        min(
            (lab[f] == 4).sum()
            / (
                np.pi
                * (r * np.sqrt(c.K[0, 0] * c.K[1, 1]) / c.world_to_camera(X[f][None])[0, 2]) ** 2
            )
            for c, lab in zip(cams, labs, strict=True)
        )
        for f in out["frame"]
    ]  # the least share of its circle that a view's pixels cover
    assert np.allclose(out["visible"], share)
    # Within continue_s only (2 ms: 10 frames at 5,000 fps).
    assert list(continued_centres(anchors, cams, labs, frames, fps, 0.002)["frame"]) == list(
        range(8, 18)
    )
    assert continued_centres(anchors, cams, labs, frames, fps, 0.0).empty
    # Played backwards, the bubble enters the frame: continued before its first centre.
    back = anchors.assign(frame=n - 1 - anchors["frame"])
    rev = continued_centres(back, cams, [lab[::-1] for lab in labs], frames, fps, 0.02)
    assert list(rev["frame"]) == [n - 1 - f for f in range(last - 1, 7, -1)]
    assert np.abs(rev[["x", "y", "z"]].to_numpy(float) - X[n - 1 - rev["frame"]]).max() < 1e-9
    # A run that does not end cut is not a bubble leaving: nothing continued.
    assert continued_centres(anchors.assign(cut=False), cams, labs, frames, fps, 0.02).empty
    # Frame 11's pixels of id 4 moved 6 px aside in both views: not on the continued
    # circle, the continuation stops before it.
    moved = [lab.copy() for lab in labs]
    for lab in moved:
        lab[11] = np.roll(lab[11], 6, axis=1)
    assert list(continued_centres(anchors, cams, moved, frames, fps, 0.02)["frame"]) == [8, 9, 10]


def _circle_outlines(cams, X, r, labs, shift=None):
    """``outline(q, k, b)`` of :func:`_leaving_sphere`'s id 4: the arc of the sphere's
    image circle inside view k's frame (1 px margin, as the visible outline), with its
    pixels' count as cover; None where the view has no pixels of it. ``shift``:
    ``{(q, k): (du, dv)}`` pixels added to that outline."""
    a = np.linspace(0.0, 2 * np.pi, 1440, endpoint=False)

    def outline(q: int, k: int, b: int):
        m = labs[k][q] == b
        if not m.any():
            return None
        cam = cams[k]
        u, v = cam.project(X[q][None], distort=False)[0]
        rho = r * np.sqrt(cam.K[0, 0] * cam.K[1, 1]) / cam.world_to_camera(X[q][None])[0, 2]
        p = np.c_[u + rho * np.cos(a), v + rho * np.sin(a)] + (shift or {}).get((q, k), 0.0)
        keep = (p[:, 0] >= 1) & (p[:, 0] <= cam.width - 2) & (p[:, 1] >= 1)
        keep &= p[:, 1] <= cam.height - 2
        return p[keep], float(m.sum())

    return outline


def test_a_moving_sphere_is_fitted_to_the_arcs_of_both_views():
    """The sphere leaving :func:`_leaving_sphere`'s frames (analytic truth, constant
    velocity): fitted to its image arcs over frames 4-19, of which view 1 shows only
    4-7, it is found to within 1 % of its radius in every frame; without a frame that
    both views show, nothing is fitted."""
    from surfphase.masks.anchors import moving_sphere

    fps = 5000.0
    cams, X, r, labs = _leaving_sphere(fps, 40)
    outline = _circle_outlines(cams, X, r, labs)
    arcs = {q: [outline(q, 0, 4)[0], outline(q, 1, 4)[0] if q < 8 else None] for q in range(4, 20)}
    Xf, V, R, q0 = moving_sphere(cams, arcs, fps)
    assert q0 == 11.5 and abs(R - r) < 0.002 * r
    for q in range(4, 20):
        assert np.linalg.norm(Xf + V * (q - q0) / fps - X[q]) < 0.01 * r
    assert moving_sphere(cams, {q: [a[0], None] for q, a in arcs.items()}, fps) is None


def test_a_bubble_whose_sliver_one_view_loses_gets_centres_from_its_moving_sphere():
    """:func:`_leaving_sphere` with its centres up to frame 7 and its pixels in view 1
    lost from frame 10 on (a sliver under the segmenter's smallest area), the line
    continuation off: the cut frames after it get the moving sphere's centres
    (analytic truth to within 2 % of the radius) while view 0 shows at least 5 % of its
    circle and its sphere's image reaches into both frames; a frame whose outline lies
    off the sphere's circle (moved 6 px in view 0) gets none."""
    from surfphase.masks.anchors import sphere_track_centres

    fps, n = 5000.0, 40
    cams, X, r, labs = _leaving_sphere(fps, n)
    labs[1][10:] = -1
    anchors = _leaving_anchors(X, r)
    frames = np.arange(n)

    def seen(f: int) -> bool:
        rho = [
            r * np.sqrt(c.K[0, 0] * c.K[1, 1]) / c.world_to_camera(X[f][None])[0, 2] for c in cams
        ]
        uv = [c.project(X[f][None], distort=False)[0] for c in cams]
        shown = max(
            (lab[f] == 4).sum() / (np.pi * rr**2) for lab, rr in zip(labs, rho, strict=True)
        )
        return shown >= 0.05 and all(
            _disc_meets(*uv[k], 1.1 * rho[k] + 1.0, (c.height, c.width)) for k, c in enumerate(cams)
        )

    last = next(f for f in range(8, n) if not seen(f))
    assert 12 < last < n
    out = sphere_track_centres(anchors, cams, labs, _circle_outlines(cams, X, r, labs), frames, fps)
    assert list(out["frame"]) == list(range(8, last))
    err = np.linalg.norm(out[["x", "y", "z"]].to_numpy(float) - X[out["frame"]], axis=1)
    assert err.max() < 0.02 * r and np.allclose(out["r_m"], r, rtol=0.01)
    assert (
        out["cut"].all()
        and out["consistent"].all()
        and (out["visible"][out.frame >= 10] == 0).all()
    )
    moved = _circle_outlines(cams, X, r, labs, {(11, 0): (6.0, 0.0)})
    out = sphere_track_centres(anchors, cams, labs, moved, frames, fps)
    assert 11 not in set(out["frame"]) and {8, 9, 10, 12} <= set(out["frame"])
    # Frames 8-13 with continued centres (predictions, here 0.1 r off), fitted over
    # 0.8 ms (4 frames) each side: they are kept as they are, yet the run the sphere is
    # fitted over spans them, back to frames 4-9 that both views show (from frame 14
    # on, 4 frames back reach none).
    pred = pd.DataFrame(
        [(f, 4, *(X[f] + [0.1 * r, 0, 0]), 0.0, 1.0, r, True, True) for f in range(8, 14)],
        columns=list(anchors.columns),
    )
    table = pd.concat([anchors.assign(continued=False), pred.assign(continued=True)])
    outline = _circle_outlines(cams, X, r, labs)
    out = sphere_track_centres(table, cams, labs, outline, frames, fps, 0.0008)
    assert list(out["frame"]) == list(range(14, last))
    err = np.linalg.norm(out[["x", "y", "z"]].to_numpy(float) - X[out["frame"]], axis=1)
    assert err.max() < 0.02 * r


def test_anchored_table_fills_a_frame_missing_within_a_track():
    """A frame missing between two sound centres of one bubble (``gap_frames`` 1) is
    reported on the parabola of its track (analytic truth: a bubble accelerating at
    20 m/s², placed exactly), without a velocity, and the track runs through it: the
    central differences beside it are exact, and a 2-frame end after the gap is kept
    (``min_track_frames`` 3). A gap next to a centre whose views disagree by 2 px is
    not filled; ``gap_frames`` 0 keeps every gap. Smoothed, the track still agrees
    with its velocities across the filled frame."""
    frames = np.arange(20)
    t = frames / 1000.0
    v, a = np.array([0.01, 0.2, -0.02]), np.array([0.0, 20.0, 0.0])
    X = np.array([0.001, 0.002, 0.0]) + np.outer(t, v) + 0.5 * np.outer(t**2, a)
    cols = ["frame", "bubble", "x", "y", "z", "reproj_px", "low", "visible"]
    rows = [(f, 1, *X[f], 0.1, False, 1.0) for f in frames if f != 14]
    rows += [(f, 2, *(X[f] + 0.003), 0.1, False, 1.0) for f in (*range(10), 11, 12)]
    rows += [
        (f, 3, *(X[f] - 0.003), 2.0 if f == 4 else 0.1, False, 1.0) for f in range(10) if f != 5
    ]
    anchors = pd.DataFrame(rows, columns=cols)
    table = _surfel_table(frames, [1, 2, 3])
    out = anchored_table(table, anchors, set(), 0.0, 1, 3, None, (), 0.25, gap_frames=1)
    b1 = out[out.bubble == 1].set_index("frame")
    assert list(b1.index) == list(frames)
    assert np.abs(b1[["x", "y", "z"]].to_numpy(float) - X).max() < 1e-12
    assert b1.loc[14, ["vx", "vy", "vz"]].isna().all()
    assert np.allclose(
        b1.loc[[13, 15], ["vx", "vy", "vz"]].to_numpy(float), v + np.outer(t[[13, 15]], a)
    )
    assert list(out[out.bubble == 2]["frame"]) == list(range(13))
    assert list(out[out.bubble == 3]["frame"]) == [f for f in range(10) if f != 5]
    off = anchored_table(table, anchors, set(), 0.0, 1, 3, None, (), 0.25, gap_frames=0)
    assert 14 not in set(off[off.bubble == 1]["frame"])
    assert list(off[off.bubble == 2]["frame"]) == list(range(10))
    rng = np.random.default_rng(2)
    noisy = anchors.copy()
    noisy[["x", "y", "z"]] += rng.normal(0, 2e-6, (len(noisy), 3))
    sm = anchored_table(table, noisy, set(), 0.005, 1, 3, None, (), 0.25, gap_frames=1)
    b1 = sm[sm.bubble == 1].sort_values("frame")
    grad = np.gradient(b1[["x", "y", "z"]].to_numpy(float), b1["time_s"].to_numpy(), axis=0)
    sure = b1["frame"].to_numpy() != 14
    assert np.allclose(grad[sure], b1[["vx", "vy", "vz"]].to_numpy(float)[sure], atol=1e-12)


@pytest.mark.parametrize("height", [-0.0009, 0.0008])
def test_nucleation_pieces_pair_above_the_plate_only(height):
    """Two pieces of the nucleation region, one per view, that are the images of one
    sphere: they agree (reprojection 0, sizes equal), and pair where that sphere's
    centre is above the plate (y > 0), not where it is under it, millimetres in front
    of the sites: what of an attached bubble the views see is above the plate."""
    from surfphase.masks.anchors import agreeing_pieces, sphere_image

    c0, c1 = _rig()
    X, r = np.array([0.001, height, -0.008]), 0.0009
    labs = []
    for cam in (c0, c1):
        u, v, rho = sphere_image(cam, X, r)
        yy, xx = np.mgrid[0 : cam.height, 0 : cam.width]
        lab = np.full((cam.height, cam.width), -1, np.int32)
        lab[np.hypot(xx - u, yy - v) <= rho] = 0
        labs.append(lab)
    pairs = agreeing_pieces([c0, c1], labs[0], labs[1], 0)
    if height > 0:
        assert len(pairs) == 1 and np.allclose(pairs[0][0], X, atol=2e-5)
    else:
        assert pairs == []
