"""The evaluate stage and commands on a small hand-built session: two bubbles moving at
known velocities, seen by two cameras (disk masks), a fit whose velocities are off by a
known amount, surfels rendered into a held-out camera whose true view differs by a known
constant, and meshes with a known offset."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_eval_metrics import _box, _write_binary_ply  # noqa: E402
from test_eval_velocity import _disk_labels, _rig  # noqa: E402

from surfphase.cameras import look_at, save_cameras  # noqa: E402
from surfphase.cli import main  # noqa: E402
from surfphase.eval.stage import campaign_table, run_evaluate  # noqa: E402
from surfphase.fit.outputs import render_surfels  # noqa: E402
from surfphase.io import atomic_write_json, save_npy  # noqa: E402

FPS = 1000.0
FRAMES = np.arange(10, 15)
V = {1: np.array([0.05, 0.3, 0.0]), 2: np.array([-0.02, 0.2, 0.01])}
X0 = {1: np.array([-1.2e-3, -1e-3, 0.0]), 2: np.array([2.0e-3, -0.5e-3, 0.3e-3])}


def _pos(b: int) -> np.ndarray:
    return X0[b] + (FRAMES - FRAMES[0])[:, None] / FPS * V[b]


def _surfels(size: int) -> dict:
    """20 small disks around bubble 1's centre per frame, facing the cameras."""
    F, N = len(FRAMES), 20
    rng = np.random.default_rng(0)
    off = rng.normal(scale=2e-4, size=(N, 3))
    means = np.stack([_pos(1)[t] + off for t in range(F)]).astype(np.float32)
    return {
        "frame": FRAMES,
        "time_s": FRAMES / FPS,
        "alive": np.ones((F, N), bool),
        "means": means,
        "quats": np.tile(np.array([1, 0, 0, 0], np.float32), (F, N, 1)),
        "log_scales": np.full((F, N, 2), np.log(1.5e-4), np.float32),
        "colors": np.full((F, N, 1), 0.2, np.float32),
        "opacity": np.full((F, N), 0.9, np.float32),
        "background": np.array([0.5], np.float32),
        "bg_images": np.full((2, size, size, 1), 0.5, np.float32),
    }


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalsession")
    size = 96
    cams = _rig(size=size, fx=900.0 * size / 256)
    ingest, masks, fit, gt = (root / n for n in ("ingest", "masks", "fit", "gt"))
    save_cameras(ingest / "cameras.json", cams)
    meta = {"session": "s01", "fps": FPS, "frame_indices": FRAMES.tolist()}
    atomic_write_json(ingest / "meta.json", meta)
    lab1 = _disk_labels(cams, _pos(1), radius_px=5.0, bubble=1)
    lab2 = _disk_labels(cams, _pos(2), radius_px=5.0, bubble=2)
    for c, cam in enumerate(cams):
        save_npy(ingest / f"{cam.name}.npy", np.zeros((len(FRAMES), size, size), np.float32))
        lab = np.maximum(lab1[c], lab2[c])
        lab[:, -4:, 10:20] = 0  # nucleation region at the plate
        save_npy(masks / f"{cam.name}_labels.npy", lab)
    # The fit: true centroids; bubble 1's vx off by 0.1 m/s, bubble 0 nonsense.
    rows = []
    for b in (1, 2):
        for t, f in enumerate(FRAMES):
            v = V[b] + (np.array([0.1, 0, 0]) if b == 1 else 0)
            rows.append([f, f / FPS, b, *_pos(b)[t], *v, 20])
    rows += [[f, f / FPS, 0, 0, 0, 0, 9, 9, 9, 5] for f in FRAMES]
    cols = ["frame", "time_s", "bubble", "x", "y", "z", "vx", "vy", "vz", "n_surfels"]
    fit.mkdir()
    pd.DataFrame(rows, columns=cols).to_csv(fit / "bubbles.csv", index=False)
    surfels = _surfels(size)
    np.savez_compressed(fit / "surfels.npz", **surfels)
    # Ground truth: other ids, a third bubble far away, a held-out camera whose true
    # views are the surfels' renders + 0.1 (16-bit PNG).
    truth = [[f, 10 + b, *_pos(b)[t], *V[b], 5e-4] for b in (1, 2) for t, f in enumerate(FRAMES)]
    truth += [[f, 30, 0.01, 0.01, 0, 0, 1, 0, 5e-4] for f in FRAMES]
    gt.mkdir()
    gt_cols = ["frame", "bubble", "x", "y", "z", "vx", "vy", "vz", "r_eq"]
    pd.DataFrame(truth, columns=gt_cols).to_csv(gt / "bubbles.csv", index=False)
    mid = look_at(
        "mid", [0.03, 0.006, 0.052], [0, 0, 0], 900.0 * size / 256, size, size, role="heldout"
    )
    save_cameras(gt / "cameras.json", [*cams, mid], fps=FPS)
    for t, f in enumerate(FRAMES[:4]):  # frame 14 has no true view
        img = render_surfels(surfels, t, [mid], "cpu", surfels["bg_images"][:1])[0, ..., 0]
        q = np.round(np.clip(img + 0.1, 0, 1) * 65535).astype(np.uint16)
        (gt / "views" / "mid").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(gt / "views" / "mid" / f"{f:06d}.png"), q)
    v, fc = _box()
    (gt / "meshes").mkdir()
    (root / "meshes").mkdir()
    for f in FRAMES[:2]:
        _write_binary_ply(gt / "meshes" / f"{f:06d}.ply", v, fc)
        _write_binary_ply(root / "meshes" / f"{f:06d}.ply", v + [0, 1e-4, 0], fc)
    return {
        "root": root,
        "ingest": ingest,
        "masks": masks,
        "fit": fit,
        "gt": gt,
        "mid": mid,
        "surfels": surfels,
    }


def test_evaluate_with_ground_truth(session):
    s = session
    out = s["root"] / "eval"
    m = run_evaluate(
        s["ingest"], s["masks"], s["fit"], out, gt_dir=s["gt"], meshes_dir=s["root"] / "meshes"
    )
    assert json.loads((out / "metrics.json").read_text()) == m
    assert m["session"] == "s01" and m["frames"] == 5
    assert m["settings"]["frames_compared"] == 5
    # Method: bubble 1's 5 frames off by 0.1 m/s, bubble 2's exact → 0.05 m/s mean.
    vm = m["velocity"]["method"]
    assert vm["matched"] == 10
    assert vm["mean_abs_error_mps"] == pytest.approx(0.05, abs=1e-9)
    speed = np.mean([np.linalg.norm(V[1]), np.linalg.norm(V[2])])
    assert vm["relative_error"] == pytest.approx(0.05 / speed, rel=1e-9)
    # Baseline: triangulated centroids of 5-pixel disks moving ~1 px per frame; their
    # digitisation (~0.1 px) makes the differences noisy: 10 % here.
    vb = m["velocity"]["baseline"]
    assert vb["matched"] == 10 and 0.01 < vb["relative_error"] < 0.3
    base = pd.read_csv(out / "baseline_bubbles.csv")
    assert set(base.bubble) == {0, 1, 2}
    b1 = base[base.bubble == 1][["x", "y", "z"]].to_numpy()
    assert np.abs(b1 - _pos(1)).max() < 1e-4  # ≈ 0.5 px at 0.18 mm per pixel
    tab = pd.read_csv(out / "velocity_table.csv")
    assert sorted(set(tab.source)) == ["baseline", "method"]
    assert set(tab[tab.source == "method"].gt_bubble) == {11, 12}
    # Held-out view: 4 frames with a true view, each exactly the render + 0.1.
    h = m["heldout"]
    assert h["mid"]["frames"] == 4 and h["mean"]["cameras"] == 1
    assert h["mid"]["l1"] == pytest.approx(0.1, abs=2e-5)
    assert h["mid"]["psnr"] == pytest.approx(20.0, abs=0.01)
    assert 0.5 < h["mid"]["ssim"] < 1.0
    assert h["mean"]["psnr"] == h["mid"]["psnr"]
    # Meshes shifted by 0.1 mm along y: Chamfer ≤ 0.1 mm, > 0, on both frames.
    ch = m["chamfer_mm"]
    assert ch["frames"] == 2 and 0.0 < ch["mean_mm"] <= 0.1
    # The 2D reference from cam0 is computed too, for method and baseline.
    assert m["reference2d"]["camera"] == "cam0"
    assert m["reference2d"]["method"]["matched"] == 10
    # The truth against the 2D reference: the reference itself is within a few %.
    t = m["reference2d"]["truth"]
    assert t["matched"] == 10 and t["relative_error_y"] < 0.1


def test_heldout_renders_the_right_frame(session, tmp_path):
    """Swapping two true views breaks the match: a wrong frame would go unnoticed only
    if the stage rendered frame t for view t+1."""
    s = session
    gt2 = tmp_path / "gt"
    shutil.copytree(s["gt"], gt2)
    a, b = gt2 / "views" / "mid" / "000010.png", gt2 / "views" / "mid" / "000013.png"
    tmp = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(tmp)
    m = run_evaluate(s["ingest"], s["masks"], s["fit"], tmp_path / "eval", gt_dir=gt2)
    assert m["heldout"]["mid"]["l1"] > 0.1 + 1e-4


def test_evaluate_without_ground_truth_and_campaign_table(session, tmp_path):
    s = session
    rc = main([
        "evaluate", "--session", "real01", "--ingest", str(s["ingest"]), "--masks",
        str(s["masks"]), "--fit", str(s["fit"]), "--out", str(tmp_path / "e1"),
    ])  # fmt: skip
    assert rc == 0
    m = json.loads((tmp_path / "e1" / "metrics.json").read_text())
    assert m["session"] == "real01" and "velocity" not in m and "heldout" not in m
    r = m["reference2d"]
    # cam0 looks nearly along −z: the reference matches the true in-plane motion, so the
    # exact method velocity of bubble 2 and the off-by-0.1 vx of bubble 1 show up in x.
    assert r["method"]["matched"] == 10 and r["baseline"]["matched"] == 10
    assert r["method"]["mean_abs_error_x_mps"] == pytest.approx(0.05, abs=0.02)
    assert r["method"]["relative_error_y"] < 0.1
    tab = pd.read_csv(tmp_path / "e1" / "velocity_table.csv")
    assert set(tab.source) == {"method", "baseline"} and "ref_vx" in tab.columns
    rc = main([
        "evaluate", "--ingest", str(s["ingest"]), "--masks", str(s["masks"]), "--fit",
        str(s["fit"]), "--gt", str(s["gt"]), "--out", str(tmp_path / "e2"),
    ])  # fmt: skip
    assert rc == 0
    rc = main([
        "campaign-table", "--metrics", str(tmp_path / "e1" / "metrics.json"),
        str(tmp_path / "e2" / "metrics.json"), "--out", str(tmp_path / "table.csv"),
    ])  # fmt: skip
    assert rc == 0
    t = pd.read_csv(tmp_path / "table.csv")
    assert t.session.tolist() == ["real01", "s01"]
    cols = list(t.columns)
    assert cols[0] == "session"
    i = cols.index("velocity.method.relative_error")
    assert "velocity.baseline.relative_error" in cols[i : i + 9]
    assert np.isnan(t["velocity.method.relative_error"][0])
    assert t["velocity.method.mean_abs_error_mps"][1] == pytest.approx(0.05, abs=1e-9)
    assert t["heldout.mean.psnr"][1] == pytest.approx(20.0, abs=0.01)
    direct = campaign_table([m])
    assert direct.session.tolist() == ["real01"]


def test_errors_name_the_file(session, tmp_path):
    s = session
    with pytest.raises(FileNotFoundError, match=r"nofit/bubbles.csv: session s01"):
        run_evaluate(s["ingest"], s["masks"], tmp_path / "nofit", tmp_path / "o")
    with pytest.raises(FileNotFoundError, match="cameras.json: not found in the ingest"):
        run_evaluate(tmp_path, s["masks"], s["fit"], tmp_path / "o")
    assert not (tmp_path / "o" / "metrics.json").exists()
    assert (
        main(
            [
                "campaign-table",
                "--metrics",
                str(tmp_path / "x.json"),
                "--out",
                str(tmp_path / "t.csv"),
            ]
        )
        == 2
    )


def test_region_metrics_ignore_the_background(session, tmp_path):
    """True views = render + 0.05, and + 0.25 in a corner far from the bubbles: inside the
    bubbles' region the error is exactly 0.05 (26.02 dB), the full frame is worse."""
    s = session
    gt2 = tmp_path / "gt"
    shutil.copytree(s["gt"], gt2)
    for t, f in enumerate(FRAMES[:4]):
        img = render_surfels(s["surfels"], t, [s["mid"]], "cpu", s["surfels"]["bg_images"][:1])
        img = img[0, ..., 0].astype(np.float64) + 0.05
        img[:12, :12] += 0.2
        q = np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)
        cv2.imwrite(str(gt2 / "views" / "mid" / f"{f:06d}.png"), q)
    m = run_evaluate(s["ingest"], s["masks"], s["fit"], tmp_path / "eval", gt_dir=gt2)
    h = m["heldout"]["mid"]
    r = h["region"]
    assert r["frames"] == 4 and 20 < r["pixels"] < 96 * 96 / 4
    assert r["l1"] == pytest.approx(0.05, abs=2e-5)
    assert r["psnr"] == pytest.approx(20 * np.log10(1 / 0.05), abs=0.01)
    assert r["ssim"] > 0.9  # a constant offset of 0.05 over a textured region
    assert h["psnr"] < r["psnr"] - 1.0 and h["l1"] > 0.05 + 1e-3
    assert m["heldout"]["mean"]["region"]["psnr"] == r["psnr"]
    assert m["heldout"]["mean"]["region"]["cameras"] == 1
    assert "1.5·r_eq" in m["settings"]["region"]
    # A larger region reaches the corner? No: 3·r_eq still leaves it out, but grows.
    m3 = run_evaluate(
        s["ingest"], s["masks"], s["fit"], tmp_path / "e3", gt_dir=gt2, region_scale=3.0
    )
    assert m3["heldout"]["mid"]["region"]["pixels"] > 3 * r["pixels"]


def test_heldout_over_the_reference_frame_against_the_noiseless_views(session, tmp_path):
    """With ``views_background`` and ``views_clean``, ``heldout`` renders the bubbles over
    the held-out camera's own reference frame and compares with the noiseless views:
    noiseless views made exactly so give L1 ≈ 0 (16-bit rounding), while
    ``heldout_whole`` keeps the recorded views over the input backgrounds (render +
    0.1, so L1 0.1 as in the plain case)."""
    s = session
    gt2 = tmp_path / "gt"
    shutil.copytree(s["gt"], gt2)
    mid = s["mid"]
    yy, xx = np.mgrid[0 : mid.height, 0 : mid.width]
    ref = 0.5 + 0.3 * xx / mid.width - 0.1 * yy / mid.height  # a backlight the inputs lack
    (gt2 / "views_background").mkdir()
    cv2.imwrite(str(gt2 / "views_background" / "mid.png"), np.round(ref * 65535).astype(np.uint16))
    ref16 = np.round(ref * 65535) / 65535
    for t, f in enumerate(FRAMES[:4]):
        bg = ref16.reshape(1, mid.height, mid.width, 1).astype(np.float32)
        img = render_surfels(s["surfels"], t, [mid], "cpu", bg)[0, ..., 0]
        (gt2 / "views_clean" / "mid").mkdir(parents=True, exist_ok=True)
        q = np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)
        cv2.imwrite(str(gt2 / "views_clean" / "mid" / f"{f:06d}.png"), q)
    m = run_evaluate(s["ingest"], s["masks"], s["fit"], tmp_path / "eval", gt_dir=gt2)
    assert "views_background" in m["settings"]["heldout"]
    h, w = m["heldout"]["mid"], m["heldout_whole"]["mid"]
    assert h["frames"] == 4 and h["l1"] < 1e-5 and h["psnr"] > 90
    assert w["frames"] == 4 and w["l1"] == pytest.approx(0.1, abs=2e-5)
    assert m["heldout_whole"]["mean"]["psnr"] == pytest.approx(20.0, abs=0.01)
    # Without the reference frames the protocol is the plain one and there is no "whole".
    plain = run_evaluate(s["ingest"], s["masks"], s["fit"], tmp_path / "e2", gt_dir=s["gt"])
    assert "heldout_whole" not in plain and "mean background" in plain["settings"]["heldout"]
    table = campaign_table([m])
    assert "heldout_whole.mean.psnr" in table.columns
    assert list(table.columns).index("heldout.mean.region.psnr") < list(table.columns).index(
        "heldout_whole.mean.psnr"
    )


def test_stage1_and_ablations(session, tmp_path, capsys):
    """Stage 1: exact velocities, same surfels; ablation no_sdf: both bubbles off by
    0.1 m/s in vx, no surfels (no held-out views); ablation no_guidance: bubble 2 off by
    0.2 m/s in vy."""
    s = session
    fits = {}
    for name, dv in (
        ("stage1", {1: (0, 0, 0), 2: (0, 0, 0)}),
        ("no_sdf", {1: (0.1, 0, 0), 2: (0.1, 0, 0)}),
        ("no_guidance", {1: (0, 0, 0), 2: (0, 0.2, 0)}),
    ):
        d = tmp_path / name
        d.mkdir()
        rows = [
            [f, f / FPS, b, *_pos(b)[t], *(V[b] + np.array(dv[b]))]
            for b in (1, 2)
            for t, f in enumerate(FRAMES)
        ]
        cols = ["frame", "time_s", "bubble", "x", "y", "z", "vx", "vy", "vz"]
        pd.DataFrame(rows, columns=cols).to_csv(d / "bubbles.csv", index=False)
        if name != "no_sdf":
            shutil.copy(s["fit"] / "surfels.npz", d / "surfels.npz")
        fits[name] = d
    out = tmp_path / "eval"
    argv = ["evaluate", "--ingest", str(s["ingest"]), "--masks", str(s["masks"])]
    argv += ["--fit", str(s["fit"]), "--gt", str(s["gt"]), "--out", str(out)]
    argv += ["--fit-stage1", str(fits["stage1"])]
    argv += ["--ablation", f"no_sdf={fits['no_sdf']}"]
    argv += ["--ablation", f"no_guidance={fits['no_guidance']}"]
    # Meshes of stage 1 (the true box shifted 0.3 mm) and of no_guidance (0.1 mm).
    v, fc = _box()
    for name, dy in (("stage1", 3e-4), ("no_guidance", 1e-4)):
        (tmp_path / f"mesh_{name}").mkdir()
        for f in FRAMES[:2]:
            _write_binary_ply(tmp_path / f"mesh_{name}" / f"{f:06d}.ply", v + [0, dy, 0], fc)
        argv += ["--compare-meshes", f"{name}={tmp_path / f'mesh_{name}'}"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "[stage1: velocity error 0.000" in printed and "[no_sdf: velocity error" in printed
    m = json.loads((out / "metrics.json").read_text())
    assert m["velocity"]["method"]["mean_abs_error_mps"] == pytest.approx(0.05, abs=1e-9)
    st = m["stage1"]
    assert st["fit"] == str(fits["stage1"])
    assert st["velocity"]["mean_abs_error_mps"] == pytest.approx(0.0, abs=1e-12)
    assert st["velocity"]["matched"] == 10
    assert st["heldout"]["mid"]["psnr"] == pytest.approx(m["heldout"]["mid"]["psnr"], abs=1e-9)
    assert st["heldout"]["mid"]["region"]["frames"] == 4
    assert st["reference2d"]["matched"] == 10
    ab = m["ablations"]
    assert sorted(ab) == ["no_guidance", "no_sdf"]
    assert ab["no_sdf"]["velocity"]["mean_abs_error_mps"] == pytest.approx(0.1, abs=1e-9)
    assert "heldout" not in ab["no_sdf"]
    assert ab["no_guidance"]["velocity"]["mean_abs_error_mps"] == pytest.approx(0.1, abs=1e-9)
    assert ab["no_guidance"]["heldout"]["mean"]["cameras"] == 1
    # Chamfer of the compared meshes: a box shifted by d is within d of the truth, and the
    # larger shift scores worse; no meshes given, no Chamfer.
    c1, cg = st["chamfer_mm"], ab["no_guidance"]["chamfer_mm"]
    assert c1["frames"] == 2 and cg["frames"] == 2
    assert 0 < cg["mean_mm"] <= 0.1 < c1["mean_mm"] <= 0.3
    assert "chamfer_mm" not in ab["no_sdf"] and "chamfer_mm" not in m
    tab = pd.read_csv(out / "velocity_table.csv")
    assert sorted(set(tab.source)) == ["baseline", "method", "no_guidance", "no_sdf", "stage1"]
    assert (tab.source == "stage1").sum() == 10
    # The campaign table: stage 1 and the ablations beside the method, means only.
    t = campaign_table([m])
    cols = list(t.columns)
    assert t["stage1.velocity.mean_abs_error_mps"][0] == pytest.approx(0.0, abs=1e-12)
    assert t["ablations.no_sdf.velocity.relative_error"][0] > 0
    assert "stage1.heldout.mean.region.psnr" in cols and "heldout.mean.region.psnr" in cols
    assert not any(c.startswith("stage1.heldout.mid") for c in cols)
    assert "heldout.mid.region.psnr" in cols
    velocity_cols = [c for c in cols if ".velocity." in c or c.startswith("velocity.")]
    first_heldout = min(i for i, c in enumerate(cols) if "heldout" in c)
    assert all(cols.index(c) < first_heldout for c in velocity_cols)
    assert cols.index("heldout.mean.psnr") < cols.index("heldout.mean.region.psnr")
    assert t["stage1.chamfer_mm.mean_mm"][0] == pytest.approx(c1["mean_mm"])
    assert not any("per_frame" in c for c in cols)
    # Meshes of a fit that is not scored: an error naming the folder.
    with pytest.raises(ValueError, match="meshes of 'no_x'"):
        run_evaluate(
            s["ingest"], s["masks"], s["fit"], tmp_path / "o2", gt_dir=s["gt"],
            compare_meshes={"no_x": tmp_path / "mesh_stage1"},
        )  # fmt: skip
    # Bad arguments: a malformed --ablation, a missing ablation fit, a reserved name.
    assert main(argv[:-2] + ["--ablation", "no_sdf"]) == 2
    assert "NAME=DIR" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match=r"nowhere/bubbles.csv: session s01 no_x"):
        run_evaluate(
            s["ingest"],
            s["masks"],
            s["fit"],
            tmp_path / "o",
            ablations={"no_x": tmp_path / "nowhere"},
        )
    with pytest.raises(ValueError, match="not allowed"):
        run_evaluate(
            s["ingest"],
            s["masks"],
            s["fit"],
            tmp_path / "o",
            ablations={"baseline": fits["no_sdf"]},
        )
