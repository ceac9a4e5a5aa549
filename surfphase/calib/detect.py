"""ChArUco corner detection in calibration images."""

from __future__ import annotations

import functools
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


def detect_view(
    image: np.ndarray,
    board: BoardSpec,
    detector: cv2.aruco.CharucoDetector | None = None,
    min_corners: int = 4,
    order: tuple[bool, ...] = (False, True),
) -> tuple[Detection, bool]:
    """Corners of ``board`` in ``image`` (H, W) and whether they were found inverted.

    ``board.inverted`` True or False: that polarity only. None: the polarities of
    ``order`` (False: the image as it is; True: ``255 − image``, a board printed
    inverted, white markers on black) until one gives a usable view; if none does, the
    try with the most corners.
    """
    detector = detector or make_detector(board)
    tries = (bool(board.inverted),) if board.inverted is not None else order
    best: tuple[Detection, bool] | None = None
    for inverted in tries:
        det = detect_corners(255 - image if inverted else image, board, detector)
        if usable(det, min_corners) is None:
            return det, inverted
        if best is None or len(det) > len(best[0]):
            best = (det, inverted)
    return best


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


#: Ids of :func:`marker_corners`' points: ``MARKER_CORNER_ID0 + 4 · marker id + k``
#: (k: the marker's corner, clockwise from its top left), apart from ChArUco corner ids.
MARKER_CORNER_ID0 = 100_000


def marker_corners(
    image: np.ndarray,
    board: BoardSpec,
    detector: cv2.aruco.CharucoDetector | None = None,
    order: tuple[bool, ...] = (False, True),
) -> tuple[Detection, bool]:
    """The four corners of each of ``board``'s markers found whole in ``image`` (H, W),
    as points of the board (ids :data:`MARKER_CORNER_ID0` on), and whether they were
    found inverted (polarities as :func:`detect_view`; the try with the most markers).

    ChArUco corners are placed between two markers found in the image, so a board
    whose view holds only a few of its squares, each marker at the image's edge cut
    open, gives two or three of them; its whole markers still give four points each,
    less precise than chessboard corners (a marker's own corners, refined to sub-pixel).
    """
    detector = detector or make_detector(board)
    cb = detector.getBoard()
    all_ids = cb.getIds().ravel().astype(int)
    obj_all = cb.getObjPoints()
    tries = (bool(board.inverted),) if board.inverted is not None else order
    best = (Detection(np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros((0, 3))), tries[0])
    for inverted in tries:
        _, _, corners, ids = detector.detectBoard(255 - image if inverted else image)
        if ids is None:
            continue
        pts, obj, out_ids = [], [], []
        for c, i in zip(corners, ids.ravel().astype(int), strict=True):
            hit = np.flatnonzero(all_ids == i)
            if not hit.size:  # a marker of the dictionary, not of this board
                continue
            k = int(hit[0])
            pts.append(np.asarray(c, np.float64).reshape(4, 2))
            obj.append(np.asarray(obj_all[k], np.float64).reshape(4, 3))
            out_ids.append(MARKER_CORNER_ID0 + 4 * i + np.arange(4))
        if len(pts) <= len(best[0]) // 4:
            continue
        best = (
            Detection(
                ids=np.concatenate(out_ids).astype(np.int32),
                image_points=np.concatenate(pts),
                object_points=np.concatenate(obj),
            ),
            inverted,
        )
    return best


def usable(det: Detection, min_corners: int = 4) -> str | None:
    """Why a detection cannot be used for calibration, or None if it can.

    A view needs ``min_corners`` corners of which at least two lie off any one line:
    the board-to-image homography needs four points with no three on a line, and with
    all corners but one on a line it is undetermined (a one-parameter family of
    homographies fits them). ``cv2.calibrateCamera`` starts the intrinsics from every
    view's homography, and one such view can pull a camera's whole calibration away
    (its principal point outside the image).
    """
    if len(det) == 0:
        return "board not found"
    if len(det) < min_corners:
        return f"only {len(det)} corner(s) found (need {min_corners})"
    xy = det.object_points[:, :2] - det.object_points[:, :2].mean(axis=0)
    s = np.linalg.svd(xy, compute_uv=False)
    if s[1] < 1e-9 * max(s[0], 1e-12) or s[1] < 1e-6:
        return "corners all on one line"
    on_line = most_on_one_line(xy, 1e-6 * float(s[0]) / np.sqrt(len(xy)))
    if len(det) - on_line < 2:
        return f"{on_line} of its {len(det)} corners on one line (no homography of the board)"
    return None


def most_on_one_line(xy: np.ndarray, tol: float) -> int:
    """The largest number of the (N, 2) points ``xy`` that lie on one line (within
    ``tol``, in the points' units; exhaustive over the lines through two points)."""
    n = len(xy)
    best = min(n, 2)
    for i in range(n - 2):
        d = xy[i + 1 :] - xy[i]  # (M, 2): the lines through point i and a later one
        e = xy - xy[i]  # (N, 2)
        cross = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (M, N)
        on = np.abs(cross) <= tol * np.linalg.norm(d, axis=1)[:, None]
        best = max(best, int(on.sum(axis=1).max()))
    return best


#: Dictionaries tried when the board is not found (each contains the smaller ones of its
#: marker size: DICT_4X4_1000 finds the markers of DICT_4X4_50, 100 and 250).
COMMON_DICTIONARIES = (
    "DICT_4X4_1000",
    "DICT_5X5_1000",
    "DICT_6X6_1000",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
    "DICT_APRILTAG_36h11",
    "DICT_APRILTAG_25h9",
    "DICT_APRILTAG_16h5",
)


@functools.lru_cache(maxsize=16)
def _marker_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters())


def _markers(image: np.ndarray, dictionary: str) -> np.ndarray:
    """(M,) ids of the markers of ``dictionary`` found in ``image``."""
    _, ids, _ = _marker_detector(dictionary).detectMarkers(image)
    return np.zeros(0, dtype=int) if ids is None else ids.ravel().astype(int)


def _found(images: list[np.ndarray], board: BoardSpec, min_corners: int) -> int:
    """In how many of ``images`` the board (as given, polarity included) is usable."""
    det = make_detector(board)
    return sum(
        usable(detect_view(im, board, det, min_corners)[0], min_corners) is None for im in images
    )


def diagnose(
    images: list[np.ndarray], board: BoardSpec, min_corners: int = 4, found_elsewhere: int = 0
) -> list[str]:
    """Likely causes, best first, of the board not being found in ``images``.

    Tries, on each image: the board inverted (and not), ``squares_x`` and ``squares_y``
    swapped, the board's markers (their ids against the board's), and the markers of
    other common dictionaries (:data:`COMMON_DICTIONARIES`), both polarities. Each cause
    says what was seen, in how many of the ``len(images)`` images. ``found_elsewhere``:
    views of the same camera where the board was found as described (then markers
    without corners mean a board partly in view rather than a wrong description).
    """
    from dataclasses import replace

    n = len(images)
    causes: list[str] = []
    if board.inverted is not True:
        k = _found(images, replace(board, inverted=True), min_corners)
        if k:
            causes.append(
                f"the board is printed inverted (white markers on black): it is found in {k} "
                f"of {n} images once inverted; set 'inverted: true' in the board file"
                + (" (it says 'inverted: false')" if board.inverted is False else "")
            )
    if board.inverted is True:
        k = _found(images, replace(board, inverted=False), min_corners)
        if k:
            causes.append(
                f"the board is not printed inverted: it is found in {k} of {n} images as they "
                "are; remove 'inverted: true' from the board file"
            )
    board_ids = set(int(i) for i in board.charuco_board().getIds().ravel())
    own = [
        np.concatenate([_markers(im, board.dictionary), _markers(255 - im, board.dictionary)])
        for im in images
    ]
    with_own = sum(len(ids) >= 2 for ids in own)
    outside = sorted(set(np.concatenate(own).tolist()) - board_ids) if with_own else []
    if outside and not causes:
        causes.append(
            f"markers of {board.dictionary} are found in {with_own} of {n} images, but ids "
            f"{', '.join(map(str, outside[:8]))}{'...' if len(outside) > 8 else ''} are not "
            f"on a {board.squares_x}×{board.squares_y} board (ids {min(board_ids)}–"
            f"{max(board_ids)}): the printed board is larger, or of another dictionary; "
            "check squares_x, squares_y and the dictionary"
        )
    if not outside:
        # Rows and columns swapped: the same markers, another layout.
        swapped = replace(board, squares_x=board.squares_y, squares_y=board.squares_x)
        k = _found(images, replace(swapped, inverted=None), min_corners)
        if k and board.squares_x != board.squares_y:
            causes.append(
                f"squares_x and squares_y are swapped: with squares_x {swapped.squares_x}, "
                f"squares_y {swapped.squares_y} (columns × rows) the board is found in {k} "
                f"of {n} images"
            )
    if with_own and not causes and found_elsewhere:
        causes.append(
            f"the board as described is found in {found_elsewhere} other views of this "
            f"camera, and its markers are seen in {with_own} of these {n} images without "
            f"{min_corners} usable corners: the board is only partly in view, too oblique, "
            "too small or blurred there; record more views with the whole board in view"
        )
    if with_own and not causes:
        causes.append(
            f"markers of {board.dictionary} with the board's ids are found in {with_own} of "
            f"{n} images, but no ChArUco corner could be placed from them: check squares_x "
            "and squares_y (columns × rows), square_length and marker_length against the "
            "printed board"
        )
    # Four images, dictionaries in order until one is seen (the scan is slow: a
    # chessboard offers many candidate squares).
    few = [images[k] for k in np.unique(np.linspace(0, n - 1, min(4, n)).astype(int))]
    if not with_own:
        seen = {}
        for name in COMMON_DICTIONARIES:
            if name == board.dictionary:
                continue
            counts = [max(len(_markers(im, name)), len(_markers(255 - im, name))) for im in few]
            if sum(c >= 2 for c in counts):
                seen[name] = (sum(c >= 2 for c in counts), max(counts))
                break
        for name, (k, most) in sorted(seen.items(), key=lambda kv: -kv[1][0]):
            causes.append(
                f"markers of another dictionary, {name} (or a smaller one of its marker size), "
                f"are found in {k} of {len(few)} images tried (up to {most} per image), none of "
                f"{board.dictionary}: set 'dictionary' in the board file"
            )
    if not causes:
        causes.append(
            f"no ArUco markers of {board.dictionary} are found in {n} images, nor of another "
            f"common dictionary in {len(few)} of them, as they are or inverted: is the board "
            "in view, in focus and lit?"
        )
    return causes
