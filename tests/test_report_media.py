"""Report media: mesh snapshots coloured by speed (checked pixel by pixel on hand-made
meshes of known speed), the novel-view videos, and the tables comparing a session's fits."""

from __future__ import annotations

import json
import re

import matplotlib.image as mpimg
import numpy as np
import pandas as pd
import pytest
from matplotlib import colormaps

from surfphase.cli import main
from surfphase.eval.stage import campaign_table
from surfphase.mesh.ply import speed_colors, write_mesh_ply
from surfphase.report.plots import campaign_page, copy_videos, videos_page
from surfphase.report.snapshots import mesh_snapshot, mesh_snapshots, project_view
from surfphase.report.tables import comparison_table, flatten, summary_table


def _write(path, verts, faces, speeds):
    """A PLY whose vertex i moves at speeds[i] m/s along +y."""
    verts = np.asarray(verts, float)
    vel = np.zeros_like(verts)
    vel[:, 1] = speeds
    write_mesh_ply(path, verts, np.asarray(faces), vel, speed_colors(np.abs(speeds), 0.4))


def _colour_pixels(img, rgb, box=None, tol=1.5 / 255):
    """(rows, cols) of the pixels of ``img`` equal to ``rgb`` within ``tol``."""
    if box is not None:
        c0, r0, c1, r1 = box
        sub = img[r0:r1, c0:c1, :3]
    else:
        c0 = r0 = 0
        sub = img[..., :3]
    rr, cc = np.nonzero(np.all(np.abs(sub - np.asarray(rgb)) <= tol, axis=-1))
    return rr + r0, cc + c0


def test_single_triangle_has_the_colour_of_its_speed(tmp_path):
    ply = tmp_path / "000000.ply"
    # a triangle facing +z (the front view), 2 mm wide, every vertex at 0.2 m/s
    _write(ply, [[-1e-3, 0, 0], [1e-3, 0, 0], [0, 2e-3, 0]], [[0, 1, 2]], [0.2, 0.2, 0.2])
    out = tmp_path / "snap.png"
    info = mesh_snapshot(ply, out, speed_max=0.4, views=("front",), shade=False, colorbar=False)
    assert info["faces"] == 1 and info["max_speed_mps"] == pytest.approx(0.2, rel=1e-6)
    img = mpimg.imread(out)
    want = colormaps["viridis"](0.5)[:3]  # 0.2 of 0.4 m/s
    rr, cc = _colour_pixels(img, want)
    c0, r0, c1, r1 = info["panels"]["front"]
    assert img.shape[1] >= c1 and img.shape[0] >= r1
    assert len(rr) > 2000  # the triangle fills much of the panel
    assert rr.min() >= r0 and rr.max() < r1 and cc.min() >= c0 and cc.max() < c1
    # its shape: apex at the top, base at the bottom (row widths grow downwards)
    widths = [np.count_nonzero(rr == r) for r in (rr.min() + 10, rr.max() - 10)]
    assert widths[0] < widths[1] / 4
    # every other pixel of the panel is white, black/grey (axes) or, along the
    # triangle's edges, a blend of its colour with the white background
    panel = img[r0:r1, c0:c1, :3].reshape(-1, 3).astype(np.float64)
    other = panel[~np.all(np.abs(panel - want) <= 1.5 / 255, axis=1)]
    coloured = other[np.ptp(other, axis=1) >= 0.02]
    assert len(coloured) < 0.05 * len(rr)
    mix = (1.0 - coloured) / (1.0 - np.asarray(want))  # the same in every channel
    assert np.ptp(mix, axis=1).max() < 0.03
    # with shading, the triangle (facing the viewer squarely) keeps its colour
    mesh_snapshot(ply, out, 0.4, views=("front",), shade=True, colorbar=False)
    assert len(_colour_pixels(mpimg.imread(out), want)[0]) == len(rr)


def test_two_triangles_left_slow_right_fast_and_the_side_view(tmp_path):
    ply = tmp_path / "000004.ply"
    verts = [[-3e-3, 0, 0], [-1e-3, 0, 0], [-2e-3, 2e-3, 1e-3],  # slow, left
             [1e-3, 0, 0], [3e-3, 0, 0], [2e-3, 2e-3, -1e-3]]  # fmt: skip
    speeds = [0.05, 0.05, 0.05, 0.6, 0.6, 0.6]  # 0.6 is above speed_max: clipped
    _write(ply, verts, [[0, 1, 2], [3, 4, 5]], np.array(speeds))
    out = tmp_path / "snap.png"
    info = mesh_snapshot(ply, out, speed_max=0.4, shade=False, colorbar=False)
    img = mpimg.imread(out)
    slow, fast = colormaps["viridis"](0.125)[:3], colormaps["viridis"](1.0)[:3]
    front, side = info["panels"]["front"], info["panels"]["side"]
    rs, cs = _colour_pixels(img, slow, front)
    rf, cf = _colour_pixels(img, fast, front)
    assert len(rs) > 300 and len(rf) > 300 and cs.max() < cf.min()
    # side view (looking along −x, −z to the right): the fast triangle (x > 0) is in
    # front; the slow one shows only where it sticks out (its apex at z = +1 mm is on
    # the left, the fast apex at z = −1 mm on the right)
    rs2, cs2 = _colour_pixels(img, slow, side)
    rf2, cf2 = _colour_pixels(img, fast, side)
    assert len(rf2) > 100 and len(rs2) > 20
    assert cs2.mean() < cf2.mean()
    np.testing.assert_allclose(
        project_view(np.array([[1e-3, 2e-3, 3e-3]]), "side")[0], [[-3.0, 2.0]]
    )


def test_mesh_snapshots_pick_frames_and_speed_max(tmp_path):
    meshes = tmp_path / "mesh"
    meshes.mkdir()
    tri = [[-1e-3, 0, 0], [1e-3, 0, 0], [0, 2e-3, 0]]
    for f in range(7):
        _write(meshes / f"{f:06d}.ply", tri, [[0, 1, 2]], np.full(3, 0.1))
    (meshes / "mesh.json").write_text(json.dumps({"speed_max": 0.2}))
    out = tmp_path / "snaps"
    out.mkdir()
    (out / "stale.png").write_bytes(b"x")
    pngs = mesh_snapshots(meshes, out, count=3, session="s1")
    assert [p.name for p in pngs] == ["000000.png", "000003.png", "000006.png"]
    assert sorted(p.name for p in out.glob("*.png")) == [p.name for p in pngs]
    # mesh.json's speed_max (0.2 m/s) sets the colour scale: 0.1 m/s is mid-scale
    img = mpimg.imread(pngs[0])
    assert len(_colour_pixels(img, colormaps["viridis"](0.5)[:3])[0]) > 500
    assert main(["mesh-snapshots", "--meshes", str(meshes), "--out", str(out), "--frames",
                 "2", "--speed-max", "0.1"]) == 0  # fmt: skip
    assert sorted(p.name for p in out.glob("*.png")) == ["000000.png", "000006.png"]
    img = mpimg.imread(out / "000000.png")
    assert len(_colour_pixels(img, colormaps["viridis"](1.0)[:3])[0]) > 500
    with pytest.raises(FileNotFoundError, match="nowhere: session s1"):
        mesh_snapshots(tmp_path / "nowhere", out, session="s1")


def test_videos_are_gathered_raw_beside_refined(tmp_path, capsys):
    views, refine = tmp_path / "views", tmp_path / "refine"
    views.mkdir()
    refine.mkdir()
    for v in ("orbit01", "orbit02"):
        (views / f"{v}.mp4").write_bytes(b"raw-" + v.encode())
        (refine / f"{v}.mp4").write_bytes(b"refined-" + v.encode())
    (views / "orbit01.npy").write_bytes(b"not a video")
    copies = copy_videos(views, refine, tmp_path / "out")
    assert [p.name for p in copies] == [
        "orbit01_raw.mp4", "orbit01_refined.mp4", "orbit02_raw.mp4", "orbit02_refined.mp4",
    ]  # fmt: skip
    assert (tmp_path / "out" / "orbit02_refined.mp4").read_bytes() == b"refined-orbit02"
    assert videos_page(copies, tmp_path / "v.html", "s1 novel views") == 2
    page = (tmp_path / "v.html").read_text()
    assert page.count("data:video/mp4;base64,") == 4 and "<th>refined</th>" in page
    # raw only (refinement off)
    assert [p.name for p in copy_videos(views, None, tmp_path / "raw")] == [
        "orbit01_raw.mp4", "orbit02_raw.mp4",
    ]  # fmt: skip
    with pytest.raises(FileNotFoundError, match="refined novel-view videos"):
        copy_videos(views, tmp_path / "missing", tmp_path / "out")
    argv = ["report-videos", "--session", "s1", "--views", str(views), "--out"]
    assert main([*argv, str(tmp_path / "rep")]) == 0
    assert "2 videos of 2 views" in capsys.readouterr().out
    assert (tmp_path / "rep" / "videos.html").is_file()
    assert main(["report-videos", "--out", str(tmp_path / "rep")]) == 2


def _metrics(session: str, ablations: bool) -> dict:
    m = {
        "session": session,
        "frames": 24,
        "velocity": {
            "method": {"relative_error": 0.08, "mean_abs_error_mps": 0.02, "matched": 50},
            "baseline": {"relative_error": 0.45, "mean_abs_error_mps": 0.14, "matched": 47},
        },
        "heldout": {
            "mid": {"psnr": 30.0, "ssim": 0.9, "l1": 0.01, "region": {"psnr": 25.0}},
            "mean": {
                "psnr": 31.0,
                "ssim": 0.95,
                "l1": 0.01,
                "region": {"psnr": 26.0, "ssim": 0.8, "l1": 0.03},
            },
        },  # fmt: skip
        "reference2d": {"method": {"relative_error_y": 0.1}},
        "stage1": {
            "velocity": {"relative_error": 0.15, "mean_abs_error_mps": 0.04, "matched": 56},
            "heldout": {"mid": {"psnr": 21.0}, "mean": {"psnr": 18.0, "region": {"psnr": 12.3}}},
        },
    }
    if ablations:
        m["ablations"] = {
            "no_sdf": {"velocity": {"relative_error": 0.3}, "heldout": {"mean": {"psnr": 17.0}}},
            "no_guidance": {"velocity": {"relative_error": 0.5}},
        }
    return m


def test_comparison_and_summary_tables():
    t = comparison_table(flatten(_metrics("s1", True)))
    assert t["fit"].tolist() == [
        "method (final fit)",
        "stage 1 (no refinement)",
        "baseline (two-view triangulation)",
        "ablation no_guidance (stage 1)",
        "ablation no_sdf (stage 1)",
    ]
    row = t.set_index("fit")
    assert row.loc["method (final fit)", "bubble-region PSNR dB"] == 26.0
    assert row.loc["stage 1 (no refinement)", "held-out PSNR dB"] == 18.0
    assert row.loc["stage 1 (no refinement)", "bubble-region PSNR dB"] == 12.3
    assert row.loc["baseline (two-view triangulation)", "velocity rel. error"] == 0.45
    assert np.isnan(row.loc["baseline (two-view triangulation)", "held-out PSNR dB"])
    assert row.loc["ablation no_sdf (stage 1)", "held-out PSNR dB"] == 17.0
    # a session without truth: only the 2D-reference column, method row only
    real = comparison_table({"session": "r", "reference2d.method.relative_error_y": 0.2})
    assert real.columns.tolist() == ["fit", "vy rel. error vs 2D ref."]
    assert real["fit"].tolist() == ["method (final fit)"]
    # the campaign summary, from the campaign table of two sessions (one with ablations)
    table = campaign_table([_metrics("s1", True), _metrics("s2", False)])
    s = summary_table(table)
    cols = s.columns.tolist()
    assert cols[:4] == [
        "session",
        "velocity rel. error (method)",
        "velocity rel. error (baseline)",
        "velocity rel. error (stage 1)",
    ]
    assert "bubble-region PSNR dB" in cols and "held-out PSNR dB (stage 1)" in cols
    assert cols.index("velocity rel. error (no_sdf)") > cols.index("bubble-region PSNR dB")
    assert s["velocity rel. error (no_sdf)"].tolist()[0] == 0.3
    assert np.isnan(s["velocity rel. error (no_sdf)"].tolist()[1])


def test_campaign_page_embeds_meshes_videos_and_the_comparison(tmp_path):
    csv = tmp_path / "metrics.csv"
    campaign_table([_metrics("s1", True), _metrics("s2", False)]).to_csv(csv, index=False)
    png = tmp_path / "a.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\nfake")
    mp4 = tmp_path / "orbit01_raw.mp4"
    mp4.write_bytes(b"video")
    out = tmp_path / "index.html"
    summary = campaign_page(
        csv, out, {"s1": [png]}, meshes={"s1": [png, png]}, videos={"s2": [mp4]}
    )
    assert len(summary) == 2
    page = out.read_text()
    assert page.count("data:image/png;base64,") == 3
    assert page.count("data:video/mp4;base64,") == 1 and "orbit01 raw" in page
    assert "Meshes coloured by speed" in page and "Novel views" in page
    # each session's fits compared: stage 1 and the ablations' rows in s1's table
    s1 = page[page.index('<h2 id="s1">') : page.index('<h2 id="s2">')]
    assert "stage 1 (no refinement)" in s1 and "ablation no_sdf (stage 1)" in s1
    assert "ablation no_sdf" not in page[page.index('<h2 id="s2">') :]
    assert re.search(r"<td>12\.3</td>", s1)  # stage-1 region PSNR
    with pytest.raises(ValueError, match="s3"):
        campaign_page(csv, out, videos={"s3": [mp4]})
    # plots' metrics.html carries the comparison too
    assert pd.read_csv(csv)["stage1.heldout.mean.region.psnr"].tolist() == [12.3, 12.3]
