"""Synthetic ChArUco calibration images: files, geometry (against OpenCV's detector)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surfphase.synth.charuco import (
    _camera_rays,
    board_yaml_dict,
    calibration_poses,
    reference_pose,
    render_board_view,
    write_calibration_images,
)
from surfphase.synth.rig import default_rig


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    out = tmp_path_factory.mktemp("charuco")
    write_calibration_images(default_rig(), out, seed=0, n_poses=3)
    return out


def _detector(board: dict) -> cv2.aruco.CharucoDetector:
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board["dictionary"]))
    cb = cv2.aruco.CharucoBoard(
        (board["squares_x"], board["squares_y"]),
        board["square_length"],
        board["marker_length"],
        dictionary,
    )
    return cv2.aruco.CharucoDetector(cb)


def test_board_description():
    b = board_yaml_dict()
    assert (b["squares_x"], b["squares_y"]) == (5, 7)
    assert (b["square_length"], b["marker_length"]) == (0.004, 0.003)
    assert b["dictionary"] == "DICT_4X4_50"
    assert b["reference_image"] == "pose000.png"
    assert b["lab_origin_in_board"] == pytest.approx([0.01, 0.028])


def test_files_only_for_input_cameras(images):
    assert sorted(p.name for p in images.iterdir()) == ["cam0", "cam1"]
    names0 = sorted(p.name for p in (images / "cam0").iterdir())
    assert names0 == ["pose000.png", "pose001.png", "pose002.png"]
    assert names0 == sorted(p.name for p in (images / "cam1").iterdir())
    img = cv2.imread(str(images / "cam1" / "pose001.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.shape == (512, 512)
    assert 0 < img.min() and img.max() < 255 and img.std() > 30


def test_reference_image_corners_at_true_projections(images):
    """OpenCV finds the corners of pose000 where the true (distorted) cameras put them.

    The reference pose also fixes the lab frame: the board's bottom-edge centre is the
    lab origin, board x is lab +x and board rows go down (lab −y).
    """
    board = board_yaml_dict()
    R, t = reference_pose(board)
    np.testing.assert_allclose(R @ np.array([0.01, 0.028, 0.0]) + t, 0.0, atol=1e-15)
    np.testing.assert_allclose(R @ [1.0, 0, 0], [1.0, 0, 0])
    np.testing.assert_allclose(R @ [0, 1.0, 0], [0, -1.0, 0])
    rig = default_rig()
    det = _detector(board)
    for cam in ("cam0", "cam1"):
        img = cv2.imread(str(images / cam / "pose000.png"), cv2.IMREAD_GRAYSCALE)
        corners, ids, _, _ = det.detectBoard(img)
        assert ids is not None and len(ids) >= 4, cam
        obj, uv = det.getBoard().matchImagePoints(corners, ids)
        truth = rig[cam].project(obj.reshape(-1, 3) @ R.T + t)
        err = np.linalg.norm(uv.reshape(-1, 2) - truth, axis=1)
        assert err.max() < 0.2, (cam, err)
        assert np.sqrt(np.mean(err**2)) < 0.1, (cam, err)


def test_poses_are_varied_and_seen():
    rig = default_rig()
    inputs = {n: c for n, c in rig.items() if c.role == "input"}
    poses = calibration_poses(inputs, board_yaml_dict(), seed=0, n_poses=14)
    assert len(poses) == 14
    normals = np.array([R[:, 2] for R, _ in poses])
    tilt = np.degrees(np.arccos(np.clip(-normals[1:] @ np.array([0.0, 0.0, 1.0]), -1, 1)))
    assert tilt.max() > 45 and np.ptp(normals[1:, 0]) > 0.5 and np.ptp(normals[1:, 1]) > 0.5
    for R, _ in poses:
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_render_is_deterministic_and_noisy():
    cam = default_rig(native=128)["cam0"]
    board = board_yaml_dict()
    R, t = reference_pose(board)
    rays = _camera_rays(cam, 3)
    a = render_board_view(cam, R, t, board, np.random.default_rng(5), rays=rays)
    b = render_board_view(cam, R, t, board, np.random.default_rng(5), rays=rays)
    c = render_board_view(cam, R, t, board, np.random.default_rng(6), rays=rays)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c) and np.abs(a.astype(int) - c.astype(int)).max() < 20
