"""ChArUco corner detection in calibration images."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from surfphase.calib.board import BoardSpec

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")


@dataclass
class Detection:
    """Corners of the board found in one image.

    Attributes:
        ids: (N,) ChArUco corner ids.
        image_points: (N, 2) corner pixels of the raw (distorted) image.
        object_points: (N, 3) the same corners in board coordinates, metres.
    """

    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.size)


def list_images(folder: Path) -> list[Path]:
    """Calibration images of ``folder``, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def read_gray(path: Path) -> np.ndarray:
    """Read an image as 8-bit grayscale (16-bit input is rescaled)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        top = 65535.0 if img.max() > 255 else 255.0
        img = np.clip(np.round(img / top * 255.0), 0, 255).astype(np.uint8)
    return img


def make_detector(board: BoardSpec) -> cv2.aruco.CharucoDetector:
    """A ChArUco detector for ``board`` with sub-pixel marker corners."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(board.charuco_board(), detectorParams=params)


def detect_corners(
    image: np.ndarray, board: BoardSpec, detector: cv2.aruco.CharucoDetector | None = None
) -> Detection:
    """ChArUco corners of ``board`` in a grayscale ``image`` (H, W); may find none."""
    detector = detector or make_detector(board)
    corners, ids, _, _ = detector.detectBoard(image)
    if ids is None or len(ids) == 0:
        empty = np.zeros((0,), dtype=np.int32)
        return Detection(empty, np.zeros((0, 2)), np.zeros((0, 3)))
    obj, img = detector.getBoard().matchImagePoints(corners, ids)
    return Detection(
        ids=ids.ravel().astype(np.int32),
        image_points=img.reshape(-1, 2).astype(np.float64),
        object_points=obj.reshape(-1, 3).astype(np.float64),
    )


def usable(det: Detection, min_corners: int = 4) -> str | None:
    """Why a detection cannot be used for calibration, or None if it can.

    A view needs ``min_corners`` corners that are not all on one line (a homography
    from collinear points is undetermined).
    """
    if len(det) == 0:
        return "board not found"
    if len(det) < min_corners:
        return f"only {len(det)} corner(s) found (need {min_corners})"
    xy = det.object_points[:, :2] - det.object_points[:, :2].mean(axis=0)
    s = np.linalg.svd(xy, compute_uv=False)
    if s[1] < 1e-9 * max(s[0], 1e-12) or s[1] < 1e-6:
        return "corners all on one line"
    return None
