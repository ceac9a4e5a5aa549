"""Calibration of two real webcams (``../shared/realdata/charuco_2cam``), all frames.

The references are independent of the calibration code: each camera's intrinsics from
a plain OpenCV pipeline (``CharucoDetector`` on ``255 − frame``, the board being
printed inverted, then ``cv2.calibrateCamera``), and the baseline from caliscope's own
calibration of the same recordings (``camera_array.toml``).

Skipped with a message when ``../shared/realdata`` is absent, unless
``SURFPHASE_REQUIRE_REALDATA=1`` (CI), which turns the skip into a failure.
"""

from __future__ import annotations

import os
import tomllib
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from surfphase.calib import calibrate_rig_detailed
from surfphase.calib.board import board_from_dict
from surfphase.calib.solve import CalibrationWarning
from surfphase.cli import main

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / "charuco_2cam"


@pytest.fixture(scope="module")
def data() -> Path:
    if not (DATA / "cam_0.mp4").is_file():
        msg = f"real data not found: {DATA.resolve()} (the project's ../shared/realdata)"
        if os.environ.get("SURFPHASE_REQUIRE_REALDATA") == "1":
            pytest.fail(msg + "; SURFPHASE_REQUIRE_REALDATA=1 requires it")
        pytest.skip(msg)
    return DATA


def _board_dict(data: Path) -> dict:
    """charuco.toml (caliscope's board description) as board.yaml keys, metres."""
    b = tomllib.loads((data / "charuco.toml").read_text())
    square = b["square_size_override_cm"] / 100.0
    return {
        "squares_x": b["columns"],
        "squares_y": b["rows"],
        "square_length": square,
        "marker_length": square * b["aruco_scale"],
        "dictionary": b["dictionary"],
    }


def _opencv_single_camera(video: Path, board: dict) -> np.ndarray:
    """(3, 3) intrinsics of a plain OpenCV calibration on every frame (inverted)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board["dictionary"]))
    cb = cv2.aruco.CharucoBoard(
        (board["squares_x"], board["squares_y"]),
        board["square_length"],
        board["marker_length"],
        dictionary,
    )
    detector = cv2.aruco.CharucoDetector(cb)
    obj, img = [], []
    cap = cv2.VideoCapture(str(video))
    size = None
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        gray = 255 - cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        size = gray.shape[::-1]
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is not None and len(ids) >= 6:
            o, i = cb.matchImagePoints(corners, ids)
            obj.append(o.astype(np.float32))
            img.append(i.astype(np.float32))
    cap.release()
    _, K, _, _, _ = cv2.calibrateCamera(obj, img, size, None, None)
    return K


def _caliscope_baseline(data: Path) -> float:
    cams = tomllib.loads((data / "camera_array.toml").read_text())["cameras"]
    centres = [
        -np.asarray(c["rotation"]).T @ np.asarray(c["translation"]) for c in (cams["0"], cams["1"])
    ]
    return float(np.linalg.norm(centres[1] - centres[0]))


@pytest.fixture(scope="module")
def calibration(data):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CalibrationWarning)
        cal = calibrate_rig_detailed(
            board_from_dict(_board_dict(data)),
            {"cam0": data / "cam_0.mp4", "cam1": data / "cam_1.mp4"},
            rig="charuco_2cam",
            timestamps=data / "timestamps.csv",
        )
    return cal, [str(w.message) for w in caught if w.category is CalibrationWarning]


def test_intrinsics_and_baseline_agree_or_warn(data, calibration):
    """fx within 3 % and the principal point within 25 px of OpenCV's single-camera
    calibration, the baseline within 3 % of caliscope's; any camera whose joint solve
    disagreed is named in a warning."""
    cal, caught = calibration
    board = _board_dict(data)
    rep = cal.report
    assert rep["sync"]["mode"] == "timestamps"
    assert rep["sync"]["cameras"]["cam1"]["paired_with_cam0"] == 111
    assert all(len(cal.sources[n].names) == 111 for n in ("cam0", "cam1"))  # every frame
    for n, video in (("cam0", "cam_0.mp4"), ("cam1", "cam_1.mp4")):
        ref = _opencv_single_camera(data / video, board)
        K = cal.cameras[n].K
        assert abs(K[0, 0] / ref[0, 0] - 1) < 0.03, (n, K[0, 0], ref[0, 0])
        assert np.hypot(K[0, 2] - ref[0, 2], K[1, 2] - ref[1, 2]) < 25, (n, K, ref)
        joint = rep["checks"][n]
        if abs(joint["joint_fx_rel_diff"]) > 0.03 or joint["joint_pp_diff_px"] > 25:
            assert any(f"{n}: the joint solve's" in w for w in rep["warnings"]), n
    assert rep["baselines_m"]["cam1"] == pytest.approx(_caliscope_baseline(data), rel=0.03)
    # Every warning of the report was also issued, and names a camera.
    assert sorted(caught) == sorted(rep["warnings"])
    assert all("cam0" in w or "cam1" in w for w in rep["warnings"])
    # The stated baseline uncertainty is a real number, not zero.
    assert 0 < rep["baselines_sd_m"]["cam1"] < 0.05


def test_inverted_board_found_automatically(calibration):
    cal, _ = calibration
    pol = cal.report["polarity"]
    assert pol["from"].startswith("found automatically")
    assert pol["views"]["cam0"] == {"normal": 0, "inverted": 46}
    assert pol["views"]["cam1"]["normal"] == 0 and pol["views"]["cam1"]["inverted"] >= 28


def test_not_inverted_says_so(data, tmp_path, capsys):
    """With 'inverted: false' the board is not found, and the error says why."""
    board = tmp_path / "board.yaml"
    board.write_text(yaml.safe_dump({**_board_dict(data), "inverted": False}))
    args = ["calibrate", "--rig", "c2", "--board", str(board), "--out", str(tmp_path / "o")]
    args += ["--cam", f"cam0={data / 'cam_0.mp4'}", "--cam", f"cam1={data / 'cam_1.mp4'}"]
    assert main([*args, "--max-frames", "20"]) == 2
    msg = capsys.readouterr().err
    assert "rig c2: board found in only 0 of 20 sampled frames of cam0 (" in msg
    assert "cam_0.mp4" in msg and "likely cause: the board is printed inverted" in msg
    assert "set 'inverted: true'" in msg
    assert not (tmp_path / "o" / "cameras.json").exists()
