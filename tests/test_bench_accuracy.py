"""``surfphase bench accuracy``: its metric functions against hand-made cases and brute
force, and a CI-sized run of the whole benchmark (table shape)."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from skimage.measure import marching_cubes

from surfphase.bench import accuracy as acc
from surfphase.bench import accuracy_metrics as am
from surfphase.eval.geometry import sample_surface
from surfphase.io import code_fingerprint

MM = 1e-3


def ellipsoid_mesh(center, semi, h=2e-5, rot=None):
    """Marching-cubes mesh (m) of an ellipsoid with semi-axes ``semi`` (m) about
    ``center``; ``rot`` (3, 3) turns its axes (columns) in the lab frame."""
    semi = np.asarray(semi, dtype=np.float64)
    R = np.eye(3) if rot is None else np.asarray(rot)
    r = semi.max() * 1.2
    ax = np.arange(-r, r + h, h)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    P = np.stack([X, Y, Z], axis=-1) @ R  # lab offsets -> body coordinates
    f = np.sqrt(((P / semi) ** 2).sum(axis=-1)) - 1.0
    v, faces, _, _ = marching_cubes(f, 0.0, spacing=(h, h, h))
    return v - r + np.asarray(center), faces.astype(np.int64)


def test_detection_precision_recall_hand_case():
    truth = pd.DataFrame(
        [  # frame, bubble, x, y, z, r_eq
            [0, 1, 0.0, 2 * MM, 0, 1 * MM],  # free, seen in both
            [0, 2, 5 * MM, 0.5 * MM, 0, 1 * MM],  # attached
            [0, 3, 9 * MM, 6 * MM, 0, 1 * MM],  # free, seen by one camera only
            [1, 1, 0.0, 2.2 * MM, 0, 1 * MM],
        ],
        columns=["frame", "bubble", "x", "y", "z", "r_eq"],
    )
    pred = pd.DataFrame(
        [
            [0, 0, 5 * MM, 0.4 * MM, 0],  # nucleation region, a bubble attached: real
            [0, 4, 0.3 * MM, 2 * MM, 0],  # 0.3 r_eq from bubble 1: real
            [0, 7, 20 * MM, 2 * MM, 0],  # nothing near it: not real
            [1, 0, 5 * MM, 0.4 * MM, 0],  # nucleation region, nothing attached: not real
            [1, 4, 0.0, 2.9 * MM, 0],  # 0.7 r_eq away: outside the gate
        ],
        columns=["frame", "bubble", "x", "y", "z"],
    )
    seen = {0: {1, 2}, 1: {1}}
    attached = {0: {2}, 1: set()}
    d = am.detection(pred, truth, seen, attached)
    assert (d["reported"], d["real"]) == (5, 2)
    assert (d["free_seen"], d["free_found"]) == (2, 1)  # bubble 1 in frames 0 and 1
    assert d["precision"] == pytest.approx(0.4) and d["recall"] == pytest.approx(0.5)
    wide = am.detection(pred, truth, seen, attached, gate_r_eq=0.8)
    assert (wide["real"], wide["free_found"]) == (3, 2)
    # Bubble 1's centre has left a view's frame in frame 1: the centred recall leaves it out.
    cen = am.detection(pred, truth, seen, attached, centred={0: {1, 2, 3}, 1: set()})
    assert (cen["centred_seen"], cen["centred_found"], cen["recall_centred"]) == (1, 1, 1.0)
    assert cen["recall"] == d["recall"]


def test_centred_in_views_is_the_pinhole_projection_inside_the_image():
    from surfphase.cameras import Camera

    # Camera at z = -0.1 m looking along +z; f = 1000 px, principal point (31.5, 23.5)
    # on a 64 x 48 image: x = ±1 mm at z = 0 lands ±10 px from the centre.
    cam = Camera(
        "cam0", 64, 48, np.array([[1000.0, 0, 31.5], [0, 1000.0, 23.5], [0, 0, 1]]),
        np.zeros(0), np.eye(3), np.array([0.0, 0.0, 0.1]),
    )  # fmt: skip
    truth = pd.DataFrame(
        [[0, 1, 0.0, 0.0, 0.0], [0, 2, 3.3 * MM, 0.0, 0.0], [1, 1, 0.0, -2.5 * MM, 0.0]],
        columns=["frame", "bubble", "x", "y", "z"],
    )
    # 3.3 mm -> u = 64.5, past the last pixel's edge (63.5); -2.5 mm -> v = -1.5.
    assert am.centred_in_views(truth, [cam]) == {0: {1}}
    near = truth.assign(x=[0.0, 3.0 * MM, 0.0], y=[0.0, 0.0, -2.3 * MM])
    assert am.centred_in_views(near, [cam, cam]) == {0: {1, 2}, 1: {1}}


def _truth_rows(ids, centres, r_eq):
    return pd.DataFrame(
        [[0, i, *c, r] for i, c, r in zip(ids, centres, r_eq, strict=True)],
        columns=["frame", "bubble", "x", "y", "z", "r_eq"],
    )


def test_chamfer_is_brute_force_over_the_bubbles_both_views_see():
    c1, c2 = np.array([0.0, 3 * MM, 0]), np.array([6 * MM, 4 * MM, 0])
    v1, f1 = ellipsoid_mesh(c1, [1 * MM] * 3)
    v2, f2 = ellipsoid_mesh(c2, [0.8 * MM] * 3)
    verts, faces = np.concatenate([v1, v2]), np.concatenate([f1, f2 + len(v1)])
    rows = _truth_rows([1, 2], [c1, c2], [1 * MM, 0.8 * MM])
    tf = am.true_frame(rows, verts, faces, seen_ids={1}, n=4000, seed=0)
    assert list(tf.seen) == [True, False]
    # Labels: each sample belongs to the sphere it was drawn on.
    on1 = np.abs(np.linalg.norm(tf.points - c1, axis=1) - 1 * MM) < 0.05 * MM
    assert np.array_equal(tf.label == 0, on1)
    pv, pf = ellipsoid_mesh(c1 + [0.2 * MM, 0, 0], [1.1 * MM] * 3, h=3e-5)
    out = am.frame_surface_metrics(tf, (pv, pf), np.array([0, 0, 1.0]), n=3000, seed=7)
    a = sample_surface(pv, pf, 3000, 7)
    b = tf.points[tf.label == 0]  # bubble 2 is seen by one view only: left out
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    brute = 0.5 * (d.min(axis=1).mean() + d.min(axis=0).mean()) * 1e3
    assert out["chamfer_mm"] == pytest.approx(brute, rel=1e-9)
    assert out["r_eq_mm"] == pytest.approx(1.0)
    # Share of the mesh within 0.25 r_eq of the truth (all true surfaces), brute force.
    dall = np.linalg.norm(a[:, None] - tf.points[None], axis=-1)
    j = dall.argmin(axis=1)
    near = np.mean(dall.min(axis=1) <= 0.25 * tf.r_eq[tf.label[j]])
    assert out["near"] == pytest.approx(near)
    assert 0.3 < near < 1.0


def test_near_share_and_volume_on_concentric_spheres():
    c = np.array([0.0, 3 * MM, 0])
    verts, faces = ellipsoid_mesh(c, [1 * MM] * 3)
    rows = _truth_rows([1], [c], [1 * MM])
    tf = am.true_frame(rows, verts, faces, seen_ids={1}, n=20000)
    bis = np.array([1.0, 0, 0])
    for scale, share in ((1.15, 1.0), (1.35, 0.0)):
        mv, mf = ellipsoid_mesh(c, [scale * MM] * 3, h=3e-5)
        out = am.frame_surface_metrics(tf, (mv, mf), bis, n=5000)
        assert out["near"] == share
        ((bid, vol_err, ratio),) = out["bubbles"]
        assert bid == 1 and vol_err == pytest.approx(scale**3 - 1, rel=0.03)
        assert ratio == pytest.approx(1.0, abs=0.03)
        assert out["chamfer_mm"] == pytest.approx(scale - 1, rel=0.1)
    # No mesh: nothing reconstructed, the bubble's volume error is −100 %.
    out = am.frame_surface_metrics(tf, None, bis)
    assert math.isnan(out["chamfer_mm"]) and out["bubbles"][0][1] == -1.0


def test_extent_ratio_on_an_analytic_spheroid():
    # Semi-axes 1.4 mm along the bisector (lab direction b), 0.9 mm across it, 1 mm up.
    b = np.array([np.sin(0.4), 0.0, np.cos(0.4)])
    across = np.cross([0.0, 1.0, 0.0], b)
    R = np.stack([b, [0.0, 1.0, 0.0], across], axis=1)
    verts, faces = ellipsoid_mesh([0, 0, 0], [1.4 * MM, 1.0 * MM, 0.9 * MM], rot=R)
    pts = sample_surface(verts, faces, 40000, 0)
    assert am.extent_ratio(pts, b) == pytest.approx(1.4 / 0.9, rel=0.01)
    assert am.extent_ratio(pts, across) == pytest.approx(0.9 / 1.4, rel=0.01)
    assert am.extent_ratio(verts, b) == pytest.approx(1.4 / 0.9, rel=0.01)
    # The bisector of two cameras' viewing directions, horizontal.
    d0, d1 = np.array([0.0, -0.1, -1.0]), np.array([-np.sin(0.8), -0.1, -np.cos(0.8)])
    bis = am.horizontal_bisector([d0, d1])
    np.testing.assert_allclose(bis, [-np.sin(0.4), 0, -np.cos(0.4)], atol=1e-12)


def test_mesh_components_and_volume():
    v1, f1 = ellipsoid_mesh([0, 0, 0], [1 * MM] * 3)
    v2, f2 = ellipsoid_mesh([5 * MM, 0, 0], [0.5 * MM, 0.5 * MM, 1 * MM])
    verts, faces = np.concatenate([v1, v2]), np.concatenate([f1, f2 + len(v1)])
    comp = am.mesh_components(verts, faces)
    assert len(np.unique(comp)) == 2
    vols = sorted(abs(am.signed_volume(verts, faces[comp == c])) for c in np.unique(comp))
    assert vols[0] == pytest.approx(4 / 3 * np.pi * 0.25e-9, rel=0.01)
    assert vols[1] == pytest.approx(4 / 3 * np.pi * 1e-9, rel=0.01)


def test_reported_volumes_scored_against_the_matched_true_bubbles():
    """Reported volumes 10 % over and 20 % under the true spheres' (the second cut by
    the frame), one bubble-frame without a volume, one reported bubble matching nothing."""
    r = np.array([1.0, 0.5]) * MM
    truth = pd.DataFrame(
        {"frame": [0, 0, 1, 1], "bubble": [1, 2, 1, 2], "x": [0, 5 * MM, 0, 5 * MM],
         "y": 0.0, "z": 0.0, "vx": 0.0, "vy": 0.1, "vz": 0.0, "r_eq": [*r, *r]}
    )  # fmt: skip
    true_v = 4 / 3 * np.pi * r**3
    sized = pd.DataFrame(
        {"frame": [0, 0, 1, 1, 1], "bubble": [3, 4, 3, 4, 9],
         "x": [0.1 * MM, 5 * MM, 0, 5.1 * MM, 20 * MM], "y": 0.0, "z": 0.0,
         "vx": 0.0, "vy": 0.1, "vz": 0.0,
         "volume_m3": [1.1 * true_v[0], 0.8 * true_v[1], np.nan, 1.1 * true_v[1], 1e-9],
         "cut": [False, True, False, False, False]}
    )  # fmt: skip
    out = am.reported_volume_scores(sized, truth)
    assert out["error_pct"] == pytest.approx((10 + 20 + 10) / 3)
    assert out["error_pct_cut"] == pytest.approx(20) and out["cut_share"] == pytest.approx(1 / 3)
    assert out["sized_share"] == pytest.approx(3 / 4)  # the unmatched one not counted
    none = am.reported_volume_scores(sized.assign(volume_m3=np.nan), truth)
    assert math.isnan(none["error_pct"]) and none["sized_share"] == 0


def test_paired_velocities_score_both_tables_on_the_bubble_frames_both_report():
    cols = ["frame", "bubble", "x", "y", "z", "vx", "vy", "vz"]
    truth = pd.DataFrame(
        [  # frame, bubble, x, y, z, vx, vy, vz, r_eq: one bubble rising, 0.2 then 0.4 m/s
            [0, 1, 0.0, 2 * MM, 0, 0, 0.2, 0, 1 * MM],
            [1, 1, 0.0, 2.2 * MM, 0, 0, 0.4, 0, 1 * MM],
            [2, 1, 0.0, 2.6 * MM, 0, 0, 0.4, 0, 1 * MM],
        ],
        columns=[*cols, "r_eq"],
    )
    pred = pd.DataFrame(  # frames 0 and 1, errors 0.1 and 0.02 m/s
        [[0, 3, 0.0, 2 * MM, 0, 0, 0.3, 0], [1, 3, 0.0, 2.2 * MM, 0, 0.02, 0.4, 0]], columns=cols
    )
    other = pd.DataFrame(  # frames 1 and 2 (errors 0.06 and 0.01), frame 1 out of the gate
        [
            [1, 5, 0.0, 2.2 * MM, 0, 0, 0.34, 0],
            [2, 5, 0.0, 2.6 * MM, 0, 0, 0.41, 0],
            [0, 5, 0.0, 2.7 * MM, 0, 0, 0.2, 0],
        ],
        columns=cols,
    )
    p = am.paired_velocity_scores(pred, other, truth)
    assert p["matched"] == 1  # frame 1 only
    assert p["method"] == pytest.approx(0.02 / 0.4) and p["baseline"] == pytest.approx(0.06 / 0.4)
    # Each table alone: its own frames and speeds.
    assert am.velocity_scores(pred, truth)["relative_error"] == pytest.approx(0.12 / 2 / 0.3)
    none = am.paired_velocity_scores(pred[pred.frame == 0], other, truth)
    assert none["matched"] == 0 and math.isnan(none["method"])


def test_table_rows_mean_and_worst():
    def row(name, v, p):
        return {
            "session": name,
            "method": {"relative_error": v, "abs_vx": 0.1, "abs_vy": v, "abs_vz": 0.0},
            "detection": {"precision": p, "recall": 1.0},
            "extent_ratio_vs_truth": 2.0 - v,
        }

    rows = acc.summary_rows([row("a", 0.2, 0.9), row("b", 0.4, 0.5)])
    assert [r[0] for r in rows] == ["a", "b", "mean", "worst"]
    k = [c[0] for c in acc.COLUMNS]
    mean, worst = dict(zip(k, rows[2][1], strict=True)), dict(zip(k, rows[3][1], strict=True))
    assert mean["v rel: method"] == pytest.approx(0.3) and worst["v rel: method"] == 0.4
    assert worst["precision"] == 0.5 and worst["bisector/across ÷ truth"] == pytest.approx(1.8)
    assert worst["abs err vx/vy/vz m/s: method"] == pytest.approx((0.1, 0.4, 0.0))
    assert math.isnan(mean["Chamfer mm"])
    text = acc.format_table([row("a", 0.2, 0.9)])
    assert text.count("\n") == 4 and "| a | 0.200 |" in text


def test_ci_sized_benchmark_table(tmp_path, capsys):
    """The whole benchmark on one bench session of 10 frames with short fits: the table
    has a row per session plus mean and worst, a column per metric, and the baseline's
    smoothing grid; every reported bubble is real and the method's velocity beats the
    smoothed baseline's (its best of the grid); the command scores the same results
    again with --skip-run."""
    from surfphase.cli import main as cli_main

    small = ["fit.iters_first=15", "fit.iters_next=5", "fit.n_init=400", "mesh.voxels=24"]
    small += ["mesh.n_orbit=4", "evaluate.compare_meshes=false"]
    res = acc.run_accuracy_bench(
        tmp_path / "w", sessions=1, frames=10, set_values=small, samples=2000, log=lambda s: None
    )
    rows = acc.summary_rows(res["rows"])
    assert [r[0] for r in rows] == ["session01", "mean", "worst"]
    lines = res["table"].splitlines()
    assert len(lines) == 2 + 3 and all(ln.count("|") == len(acc.COLUMNS) + 2 for ln in lines)
    r = res["rows"][0]
    assert "error" not in r
    for key in ("method", "baseline_raw", "baseline_smoothed"):
        assert r[key]["matched"] > 0 and np.isfinite(r[key]["relative_error"])
    assert r["detection"]["precision"] >= 0.98 and r["detection"]["reported"] > 0
    assert r["method"]["relative_error"] <= r["baseline_smoothed"]["relative_error"]
    assert r["method"]["matched"] >= 0.9 * r["baseline_smoothed"]["matched"]
    assert 0 < r["paired"]["matched"] <= r["baseline_smoothed"]["matched"]
    assert np.isfinite(r["paired"]["method"]) and np.isfinite(r["paired"]["baseline"])
    assert r["frames_without_mesh"] == 0 and np.isfinite(r["chamfer_mm"])
    assert np.isfinite(r["psnr"]) and 0 < r["ssim"] <= 1
    grid = res["smoothing"]["grid"]
    assert len(grid) == len(acc.SMOOTH_WINDOWS_S) * len(acc.SMOOTH_ORDERS)
    best = min(g["mean_relative_error"] for g in grid)
    assert r["baseline_smoothed"]["relative_error"] == pytest.approx(best)
    assert "0.5 r_eq" in res["notes"] and (tmp_path / "w" / "accuracy.md").is_file()
    capsys.readouterr()
    argv = ["bench", "accuracy", "--work", str(tmp_path / "w"), "--sessions", "1"]
    assert (
        cli_main(
            [*argv, "--skip-run", "--samples", "2000", *sum((["--set", s] for s in small), [])]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert out.splitlines()[:5] == lines
    # The native frames and masks are cached under the key of what made them: reused
    # as they are, redone when the key differs (another code, calibration, setting).
    native = tmp_path / "w" / "native" / "session01"
    stamp, masks_json = native / "inputs.json", native / "masks" / "masks.json"
    key = json.loads(stamp.read_text())
    assert key["code"] == code_fingerprint(acc.NATIVE_SOURCES)
    made = masks_json.stat().st_mtime_ns
    skip = [*argv, "--skip-run", "--samples", "2000", *sum((["--set", s] for s in small), [])]
    assert cli_main(skip) == 0 and masks_json.stat().st_mtime_ns == made
    capsys.readouterr()
    stamp.write_text(json.dumps({**key, "code": "an older code"}))
    assert cli_main(skip) == 0
    assert masks_json.stat().st_mtime_ns > made and json.loads(stamp.read_text()) == key
    assert capsys.readouterr().out.splitlines()[:5] == lines  # the same masks again
    # Where the method would lose, the smoothing or the centres: from the same results.
    from surfphase.bench.velocity_limits import PLAIN_RULES

    assert cli_main(["bench", "velocity-limits", "--work", str(tmp_path / "w")]) == 0
    assert "1 sessions: the method at most the bar on 1;" in capsys.readouterr().out
    lim = json.loads((tmp_path / "w" / "velocity_limits.json").read_text())["session01"]
    assert lim["bar"] == pytest.approx(r["baseline_smoothed"]["relative_error"], rel=1e-9)
    assert lim["method"] == pytest.approx(r["method"]["relative_error"], rel=1e-9)
    assert lim["limit"] == "" and lim["centres"]["n"] > 0
    assert lim["paired"]["method"] == pytest.approx(r["paired"]["method"], rel=1e-9)
    assert lim["paired"]["bar"] == pytest.approx(r["paired"]["baseline"], rel=1e-9)
    grids = {k: {(w, o): e for w, o, e in g} for k, g in lim["grids"].items()}
    # The fit's own bubbles.csv, recomputed from its surfels and anchors at the
    # default track settings (3 ms, order 1), and the baseline's at the draw's bar.
    assert grids["method"][(0.003, 1)] == pytest.approx(lim["method"], rel=1e-6)
    bar_setting = (res["smoothing"]["window_s"], res["smoothing"]["order"])
    assert grids["baseline"][bar_setting] == pytest.approx(lim["bar"], rel=1e-9)
    for k in ("method", "plain", "baseline"):
        assert lim[f"{k}_best"] == pytest.approx(min(grids[k].values()))
    # track_min_visible's sweep: the default's is bubbles.csv's; a higher threshold
    # gives fewer bubble-frames a velocity. The bubble-frames only the method gives one.
    from surfphase.fit.params import DEFAULTS as FIT

    vis = {v: (e, n) for v, e, n in lim["min_visible"]}
    assert vis[FIT["track_min_visible"]][0] == pytest.approx(lim["method"], rel=1e-6)
    counts = [vis[v][1] for v in sorted(vis)]
    assert counts == sorted(counts, reverse=True) and counts[0] > 0
    only = lim["method_only"]
    assert only["n"] == lim["matched"]["method"] - lim["paired"]["n"]
    # Plain Savitzky–Golay of the centres, by hand: scipy's filter along each run of
    # consecutive frames of an id, then np.gradient (the ground truth's convention).
    from scipy.signal import savgol_filter

    fit = tmp_path / "w" / "run" / "results" / "session01" / "fit"
    raw = acc.method_track_table(fit, 0.0, 1, None, PLAIN_RULES)
    row = pd.read_csv(tmp_path / "w" / "run" / "config" / "sessions.tsv", sep="\t").iloc[0]
    sg = raw[raw["bubble"] >= 1].sort_values(["bubble", "frame"]).copy()
    for _, g in sg.groupby("bubble"):
        assert (np.diff(g["frame"]) == 1).all()  # one run per id in these 10 frames
        n = 5 if len(g) >= 5 else len(g) - (1 - len(g) % 2)  # 5 ms at 1000 fps, odd
        if len(g) >= 3:
            xyz = savgol_filter(g[am.XYZ].to_numpy(), n, 1, axis=0, mode="interp")
            sg.loc[g.index, am.VEL] = np.gradient(xyz, g["time_s"].to_numpy(), axis=0)
    assert float(row["fps"]) == 1000.0
    truth = pd.read_csv(f"{row['gt']}/bubbles.csv")
    want = am.velocity_scores(sg, truth)["relative_error"]
    assert grids["plain"][(0.005, 1)] == pytest.approx(want, rel=1e-9)


def test_centre_noise_analytic():
    """Centre errors against the truth: an error alternating ±e frame to frame has rms e
    and jitter 2e; a constant offset has jitter 0; a reported centre beyond the gate is
    not matched."""
    from surfphase.bench.velocity_limits import centre_errors, centre_noise

    e = 10e-6
    f = np.arange(10)
    truth = pd.DataFrame({"frame": f, "bubble": 1, "x": 1e-3 * f, "y": 0.0, "z": 0.0,
                          "vx": 1.0, "vy": 0.0, "vz": 0.0, "r_eq": 1e-3})  # fmt: skip
    alt = truth.copy()
    alt["x"] += e * (-1.0) ** f
    err = centre_errors(alt, truth)
    assert len(err) == 10 and np.allclose(err["ex"], e * (-1.0) ** f)
    rms, jitter = centre_noise(err)
    assert rms == pytest.approx(e) and jitter == pytest.approx(2 * e)
    off = truth.copy()
    off["z"] += e
    off.loc[4, "y"] += 0.6e-3  # beyond the 0.5 r_eq gate: unmatched
    err = centre_errors(off, truth)
    assert len(err) == 9
    rms, jitter = centre_noise(err)
    assert rms == pytest.approx(e) and jitter == pytest.approx(0.0, abs=1e-15)
