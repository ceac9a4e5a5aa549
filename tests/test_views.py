"""Novel views: scene centre, orbit cameras against the synthetic rig's truth, view files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from surfphase.cameras import Camera, load_cameras, look_at, orbit_cameras, save_cameras
from surfphase.cli import main
from surfphase.fit.outputs import render_surfels
from surfphase.folders.views import read_mp4
from surfphase.synth.rig import SCENE_CENTER, default_rig
from surfphase.views import orbit_view_cameras, scene_center

NATIVE = 64  # tiny images: the rig at 64×64 pixels
FPS = 1500.0


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def sphere_fit(n_frames: int = 3, n: int = 300, seed: int = 0) -> dict[str, np.ndarray]:
    """A hand-made stage-1 fit: dark surfels on a 1.5 mm sphere at the scene centre,
    rising 0.2 mm per frame, over per-camera background images of 64×64 pixels."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    means = np.stack([SCENE_CENTER + 1.5e-3 * d + [0, 2e-4 * f, 0] for f in range(n_frames)])
    yy, xx = np.mgrid[:NATIVE, :NATIVE] / NATIVE
    bg = np.stack([0.7 + 0.1 * xx, 0.8 - 0.1 * yy])[..., None]  # (2, H, W, 1)
    return {
        "frame": np.arange(10, 10 + n_frames),
        "time_s": np.arange(10, 10 + n_frames) / FPS,
        "alive": np.ones((n_frames, n), bool),
        "means": means.astype(np.float32),
        "quats": np.broadcast_to(q, (n_frames, n, 4)).astype(np.float32),
        "log_scales": np.full((n_frames, n, 2), np.log(3e-4), np.float32),
        "colors": np.full((n_frames, n, 1), 0.15, np.float32),
        "opacity": np.full((n_frames, n), 0.8, np.float32),
        "background": np.array([0.75], np.float32),
        "bg_images": bg.astype(np.float32),
        "extent": np.float64(0.01),
    }


def make_tiny_session(root: Path, n_frames: int = 3) -> tuple[Path, Path]:
    """``root/fit/surfels.npz`` (:func:`sphere_fit`) and ``root/ingest`` (the rig's cam0 and
    cam1, undistorted, at 64×64, with frame stacks and meta.json); returns both paths."""
    rig = default_rig(native=NATIVE)
    ingest = root / "ingest"
    ingest.mkdir(parents=True)
    save_cameras(ingest / "cameras.json", [rig["cam0"].undistorted(), rig["cam1"].undistorted()])
    for cam in ("cam0", "cam1"):
        np.save(ingest / f"{cam}.npy", np.full((n_frames, NATIVE, NATIVE), 0.7, np.float32))
    (ingest / "meta.json").write_text(json.dumps({"session": "tiny", "fps": FPS}))
    fit = root / "fit"
    fit.mkdir()
    np.savez_compressed(fit / "surfels.npz", **sphere_fit(n_frames))
    return fit, ingest


def test_scene_center_is_where_the_axes_meet():
    target = np.array([0.001, 0.004, -0.002])
    cams = [look_at(f"c{k}", target + 0.03 * np.array([np.sin(a), 0.2, np.cos(a)]), target,
                    100.0, 64, 64) for k, a in enumerate([0.0, 0.6, 1.9])]  # fmt: skip
    np.testing.assert_allclose(scene_center(cams), target, atol=1e-12)


def test_scene_center_matches_brute_force_least_squares():
    """Skew axes: the closed form equals a numerical minimum of Σ squared distances."""
    rng = np.random.default_rng(3)
    cams = []
    for k in range(3):
        eye = rng.normal(size=3) * 0.03
        cams.append(look_at(f"c{k}", eye, rng.normal(size=3) * 0.003, 100.0, 64, 64))

    def cost(x):
        total = 0.0
        for c in cams:
            r = x - c.center
            total += r @ r - (r @ c.view_dir) ** 2
        return total

    ref = minimize(cost, np.zeros(3), method="BFGS", options={"gtol": 1e-14}).x
    np.testing.assert_allclose(scene_center(cams), ref, atol=1e-7)
    with pytest.raises(ValueError, match="parallel"):
        scene_center([cams[0], cams[0]])


def assert_same_camera(a: Camera, b: Camera, atol: float = 1e-9) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.R, b.R, atol=atol)
    np.testing.assert_allclose(a.t, b.t, atol=atol)
    np.testing.assert_allclose(a.K, b.K, atol=atol)


def test_orbit_cameras_coincide_with_the_rigs_truth():
    rig = default_rig(native=NATIVE)
    inputs = [rig["cam0"].undistorted(), rig["cam1"].undistorted()]
    cams, center = orbit_view_cameras(inputs)
    np.testing.assert_allclose(center, SCENE_CENTER, atol=1e-12)
    assert [c.name for c in cams] == [f"orbit{k:02d}" for k in range(1, 12)]
    for cam in cams:
        assert_same_camera(cam, rig[cam.name])
    # options: another reference camera, count and step
    cams, _ = orbit_view_cameras(inputs, n_views=3, step_deg=45.0, reference="cam1")
    for a, b in zip(cams, orbit_cameras(inputs[1], SCENE_CENTER, 3, 45.0), strict=True):
        assert_same_camera(a, b)
    with pytest.raises(ValueError, match="cam7"):
        orbit_view_cameras(inputs, reference="cam7")


def test_render_views_writes_the_interface(tmp_path):
    fit, ingest = make_tiny_session(tmp_path)
    out = tmp_path / "views"
    assert main(["render-views", "--fit", str(fit), "--ingest", str(ingest),
                 "--out", str(out), "--device", "cpu"]) == 0  # fmt: skip
    rig = default_rig(native=NATIVE)
    names = [f"orbit{k:02d}" for k in range(1, 12)]
    cams = load_cameras(out / "cameras.json")
    assert list(cams) == names
    for name in names:
        assert_same_camera(cams[name], rig[name], atol=1e-9)
    meta = json.loads((out / "cameras.json").read_text())
    assert meta["fps"] == FPS and meta["frame"] == [10, 11, 12]

    surfels = sphere_fit()
    bg = np.load(out / "background.npy")
    assert bg.dtype == np.float32 and bg.shape == (NATIVE, NATIVE)
    np.testing.assert_allclose(bg, surfels["bg_images"].mean(0)[..., 0], atol=1e-7)
    for name in names:
        v, a = np.load(out / f"{name}.npy"), np.load(out / f"{name}_alpha.npy")
        assert v.dtype == np.uint16 and v.shape == (3, NATIVE, NATIVE)
        assert a.dtype == np.float16 and a.shape == (3, NATIVE, NATIVE)
        assert 0 <= a.min() and a.max() <= 1 and a.max() > 0.5  # the sphere is in view
        # independent composite: the fit's own renderer over the same background
        ref = render_surfels(surfels, 1, [cams[name]], backgrounds=bg[None, ..., None])
        np.testing.assert_allclose(v[1] / 65535.0, ref[0, ..., 0], atol=2e-5)
        movie = read_mp4(out / f"{name}.mp4")
        assert movie.shape == (3, NATIVE, NATIVE)
        assert np.abs(movie.astype(float) - v / 257.0).mean() < 3.0  # H.264, 8-bit
    # the sphere rises: its dark centre moves up (smaller v) in every view
    rows = np.arange(NATIVE)
    for name in ("orbit01", "orbit06"):
        a = np.load(out / f"{name}_alpha.npy").astype(np.float64)
        cy = [(a[t].sum(1) * rows).sum() / a[t].sum() for t in range(3)]
        assert cy[0] > cy[1] > cy[2]
    assert not list(tmp_path.glob(".views.part-*"))


def test_render_views_errors_name_the_file(tmp_path, capsys):
    fit, ingest = make_tiny_session(tmp_path)
    (ingest / "meta.json").unlink()
    rc = main(["render-views", "--fit", str(fit), "--ingest", str(ingest),
               "--out", str(tmp_path / "views")])  # fmt: skip
    assert rc == 2 and "meta.json" in capsys.readouterr().err
    rc = main(["render-views", "--fit", str(tmp_path / "nofit"), "--ingest", str(ingest),
               "--out", str(tmp_path / "views")])  # fmt: skip
    assert rc == 2 and "nofit" in capsys.readouterr().err
    assert not (tmp_path / "views").exists()


def test_oracle_views_are_the_true_frames_of_the_orbit_cameras(tmp_path):
    import cv2

    from surfphase.views import oracle_views

    cams = [
        look_at(f"orbit{k:02d}", [0.03 * np.sin(a), 0.005, 0.03 * np.cos(a)], [0, 0, 0],
                fx=40.0, width=12, height=10)
        for k, a in ((1, 0.5), (2, 1.0))
    ]  # fmt: skip
    views, gt = tmp_path / "views", tmp_path / "gt"
    views.mkdir()
    save_cameras(views / "cameras.json", cams, fps=1000.0, frame=[3, 4])
    # The true cameras: the same, one shifted by 20 µm (a calibration error).
    shifted = look_at("orbit02", [0.03 * np.sin(1.0) + 2e-5, 0.005, 0.03 * np.cos(1.0)],
                      [2e-5, 0, 0], fx=40.0, width=12, height=10)  # fmt: skip
    save_cameras(gt / "cameras.json", [cams[0], shifted])
    rng = np.random.default_rng(0)
    truth = {}
    for c in cams:
        (gt / "views_clean" / c.name).mkdir(parents=True)
        for f in (2, 3, 4):
            img = rng.integers(0, 65536, size=(10, 12), dtype=np.uint16)
            cv2.imwrite(str(gt / "views_clean" / c.name / f"{f:06d}.png"), img)
            truth[c.name, f] = img
    info = oracle_views(gt, views, tmp_path / "oracle")
    for c in cams:
        got = np.load(tmp_path / "oracle" / f"{c.name}.npy")
        assert got.dtype == np.uint16
        np.testing.assert_array_equal(got, np.stack([truth[c.name, 3], truth[c.name, 4]]))
    assert info["offsets_m"]["orbit01"] == pytest.approx(0.0, abs=1e-12)
    assert info["offsets_m"]["orbit02"] == pytest.approx(2e-5, rel=1e-6)
    # A missing frame and a view of another size are named.
    (gt / "views_clean" / "orbit02" / "000004.png").unlink()
    with pytest.raises(FileNotFoundError, match="000004.png"):
        oracle_views(gt, views, tmp_path / "o2")
    cv2.imwrite(str(gt / "views_clean" / "orbit02" / "000004.png"), np.zeros((5, 5), np.uint16))
    with pytest.raises(ValueError, match="orbit02 is 12×10"):
        oracle_views(gt, views, tmp_path / "o3")
