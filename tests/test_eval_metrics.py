"""Image metrics against scikit-image; Chamfer against brute force; PLY reading and
area-uniform sampling on hand-made meshes."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from surfphase.eval import geometry, image_metrics


def _pair(shape, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    b = np.clip(a + 0.1 * rng.standard_normal(shape), 0, 1)
    return a, b


@pytest.mark.parametrize("shape", [(32, 40), (64, 48, 3), (11, 11)])
def test_ssim_matches_skimage(shape):
    a, b = _pair(shape)
    ref = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
        channel_axis=2 if len(shape) == 3 else None,
    )  # fmt: skip
    assert image_metrics.ssim(b, a) == pytest.approx(ref, abs=1e-10)


def test_ssim_smooth_images_and_identity():
    yy, xx = np.mgrid[0:48, 0:48] / 48.0
    a = 0.5 + 0.3 * np.sin(6 * xx) * np.cos(4 * yy)
    b = 0.9 * a + 0.05
    ref = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0
    )
    assert image_metrics.ssim(b, a) == pytest.approx(ref, abs=1e-10)
    assert image_metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_gaussian_window_is_11_taps_sigma_15():
    w = image_metrics.gaussian_window()
    assert w.shape == (11,)
    assert w.sum() == pytest.approx(1.0)
    assert w[5] / w[6] == pytest.approx(np.exp(0.5 / 1.5**2))


def test_psnr_and_l1():
    a, b = _pair((20, 30, 3), seed=3)
    assert image_metrics.psnr(b, a) == pytest.approx(
        peak_signal_noise_ratio(a, b, data_range=1.0), abs=1e-10
    )
    assert image_metrics.l1(b, a) == pytest.approx(np.abs(a - b).mean())
    c = np.full((8, 8), 0.5)
    # Constant offset 0.1: MSE 0.01 → 20 dB; L1 0.1.
    assert image_metrics.psnr(c + 0.1, c) == pytest.approx(20.0)
    assert image_metrics.l1(c + 0.1, c) == pytest.approx(0.1)
    assert image_metrics.psnr(c, c) == np.inf
    with pytest.raises(ValueError, match="shape"):
        image_metrics.l1(c, np.zeros((8, 9)))


def _brute_chamfer(A, B):
    d = np.linalg.norm(A[:, None] - B[None], axis=-1)
    ab, ba = d.min(axis=1), d.min(axis=0)
    return 0.5 * (ab.mean() + ba.mean()) * 1e3, 0.5 * ((ab**2).mean() + (ba**2).mean()) * 1e6


def test_chamfer_matches_brute_force():
    rng = np.random.default_rng(1)
    A = rng.normal(scale=1e-3, size=(57, 3))
    B = rng.normal(scale=1e-3, size=(80, 3)) + [2e-4, 0, 0]
    res = geometry.chamfer(A, B)
    mean_mm, sq_mm2 = _brute_chamfer(A, B)
    assert res["mean_mm"] == pytest.approx(mean_mm, rel=1e-12)
    assert res["mean_sq_mm2"] == pytest.approx(sq_mm2, rel=1e-12)
    assert geometry.chamfer(A, A)["mean_mm"] == 0.0
    # A pure shift of a single point by 1 mm: 1 mm both ways.
    assert geometry.chamfer([[0, 0, 0]], [[0, 1e-3, 0]])["mean_mm"] == pytest.approx(1.0)


def _box(size=2e-3):
    """Closed axis-aligned cube of side ``size`` (m), 12 triangles."""
    v = np.array([[x, y, z] for x in (0, size) for y in (0, size) for z in (0, size)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = [(q[0], q[1], q[2]) for q in quads] + [(q[0], q[2], q[3]) for q in quads]
    return v, np.array(f)


def test_sample_surface_on_cube_faces_uniformly():
    v, f = _box()
    p = geometry.sample_surface(v, f, 60000, seed=4)
    on_face = np.isclose(p, 0, atol=1e-12) | np.isclose(p, 2e-3, atol=1e-12)
    assert on_face.any(axis=1).all()
    # Six faces of equal area: each gets ~1/6 of the points.
    axis = np.argmax(on_face, axis=1)  # the coordinate that is pinned to 0 or 2 mm
    face_id = 2 * axis + (p[np.arange(len(p)), axis] > 1e-3)
    counts = np.bincount(face_id, minlength=6) / len(p)
    assert np.allclose(counts, 1 / 6, atol=0.01)
    # Uniform inside a face: mean of the free coordinates at the centre.
    assert np.allclose(p.mean(axis=0), 1e-3, atol=2e-5)
    assert np.array_equal(p, geometry.sample_surface(v, f, 60000, seed=4))


def _write_ascii_ply(path, v, f):
    lines = [
        "ply", "format ascii 1.0", f"element vertex {len(v)}", "property double x",
        "property double y", "property double z", "property uchar red",
        f"element face {len(f)}", "property list uchar int vertex_indices", "end_header",
    ]  # fmt: skip
    lines += [f"{a} {b} {c} 7" for a, b, c in v]
    lines += [f"{len(q)} " + " ".join(map(str, q)) for q in f]
    path.write_text("\n".join(lines) + "\n")


def _write_binary_ply(path, v, f):
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment units: metres\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"], rec["i"] = 3, f
    path.write_bytes(header.encode() + np.asarray(v, "<f4").tobytes() + rec.tobytes())


def test_read_ply_ascii_binary_and_quads(tmp_path):
    v, f = _box()
    _write_binary_ply(tmp_path / "b.ply", v, f)
    vb, fb = geometry.read_ply(tmp_path / "b.ply")
    assert np.allclose(vb, v, atol=1e-9) and np.array_equal(fb, f)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5)]
    _write_ascii_ply(tmp_path / "a.ply", v, quads)
    va, fa = geometry.read_ply(tmp_path / "a.ply")
    assert np.allclose(va, v) and fa.tolist() == [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]]
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        geometry.read_ply(tmp_path / "missing.ply")


def test_mesh_chamfer_of_shifted_cube(tmp_path):
    v, f = _box()
    _write_binary_ply(tmp_path / "a.ply", v, f)
    _write_binary_ply(tmp_path / "b.ply", v + [0.5e-3, 0, 0], f)
    res = geometry.mesh_chamfer(tmp_path / "a.ply", tmp_path / "b.ply", n=1500, seed=0)
    # Shift 0.5 mm along x: points on the ±x faces are 0.5 mm from the other cube's
    # same face; points on the other faces that lie in the overlap are at distance ~0,
    # those outside it ≤ 0.5 mm. Bounded, nonzero, and within the brute force.
    A = geometry.sample_surface(*geometry.read_ply(tmp_path / "a.ply"), 1500, 0)
    B = geometry.sample_surface(*geometry.read_ply(tmp_path / "b.ply"), 1500, 1)
    assert res["mean_mm"] == pytest.approx(_brute_chamfer(A, B)[0], rel=1e-9)
    assert 0.05 < res["mean_mm"] < 0.5


def test_in_all_views_by_hand():
    """A camera at z = −0.1 m looking along +z, fx = fy = 100 px, 64×48 pixels with the
    principal point at the centre: u = 31.5 ± 100·x/0.1 must lie in −0.5 … 63.5 and
    v in −0.5 … 47.5; points behind the camera are out whatever their projection."""
    from surfphase.cameras import look_at

    cam = look_at("c", [0, 0, -0.1], [0, 0, 0], 100.0, 64, 48)
    pts = np.array(
        [
            [0, 0, 0],  # centre
            [0.0319, 0, 0],  # |u − 31.5| = 31.9: on the image, just
            [0.0321, 0, 0],  # |u − 31.5| = 32.1: off it
            [0, 0.0239, 0],  # image v runs along −y: v = 23.5 − 23.9 = −0.4, inside
            [0, -0.0241, 0],  # v = 23.5 + 24.1 = 47.6: outside
            [0, 0, -0.2],  # behind
        ]
    )
    uv = cam.project(pts[:5])
    by_hand = (uv[:, 0] >= -0.5) & (uv[:, 0] <= 63.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= 47.5)
    assert by_hand.tolist() == [True, True, False, True, False]
    assert geometry.in_all_views(pts, [cam]).tolist() == [*by_hand.tolist(), False]
    # Two cameras: the intersection of what each sees.
    side = look_at("s", [-0.1, 0, 0], [0, 0, 0], 100.0, 64, 48)
    both = geometry.in_all_views(pts, [cam, side])
    assert (
        both.tolist()
        == (geometry.in_all_views(pts, [cam]) & geometry.in_all_views(pts, [side])).tolist()
    )


def test_mesh_chamfer_restricted_to_the_input_views(tmp_path):
    """The true mesh has a second cube outside the camera's view: the restricted Chamfer
    ignores it and equals the brute force on the samples each camera sees."""
    from surfphase.cameras import look_at

    v, f = _box()
    far = v + [0.08, 0, 0]  # 80 mm to the side, outside a ±32 mm field at 0.1 m
    _write_binary_ply(tmp_path / "pred.ply", v + [0.2e-3, 0, 0], f)
    _write_binary_ply(tmp_path / "true.ply", np.vstack([v, far]), np.vstack([f, f + 8]))
    cam = look_at("c", [1e-3, 1e-3, -0.1], [1e-3, 1e-3, 0], 100.0, 64, 64)
    whole = geometry.mesh_chamfer(tmp_path / "pred.ply", tmp_path / "true.ply", n=3000)
    seen = geometry.mesh_chamfer(tmp_path / "pred.ply", tmp_path / "true.ply", 3000, 0, [cam])
    A = geometry.sample_surface(*geometry.read_ply(tmp_path / "pred.ply"), 3000, 0)
    B = geometry.sample_surface(*geometry.read_ply(tmp_path / "true.ply"), 3000, 1)
    B = B[B[:, 0] < 0.04]  # the near cube's samples: what the camera sees
    assert seen["points_pred"] == 3000 and seen["points_true"] == len(B)
    assert 1000 < len(B) < 2000  # about half the area is the far cube
    assert seen["mean_mm"] == pytest.approx(_brute_chamfer(A, B)[0], rel=1e-9)
    assert seen["mean_mm"] < 0.2 < whole["mean_mm"] == seen["whole_truth_mean_mm"]
    # Nothing true in view: NaN, not a number that averages in.
    _write_binary_ply(tmp_path / "far.ply", far, f)
    none = geometry.mesh_chamfer(tmp_path / "pred.ply", tmp_path / "far.ply", 500, 0, [cam])
    assert np.isnan(none["mean_mm"]) and none["points_true"] == 0
