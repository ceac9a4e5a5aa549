"""The calibration board: ``board.yaml`` → ChArUco board and the lab-frame definition.

``board.yaml`` keys (metres):

* ``squares_x``, ``squares_y``: squares along the board's x (columns) and y (rows);
* ``square_length``, ``marker_length``: chessboard square and ArUco marker sides;
* ``dictionary``: an OpenCV predefined dictionary name, e.g. ``DICT_4X4_50``;
* ``reference_image`` (optional): the calibration view that defines the lab frame: an
  image's file name, or for recordings a view name ``fNNNNNN`` (camera 0's frame
  index); by default the first view (by name) in which camera 0 sees the board;
* ``lab_origin_in_board`` (optional, default the centre of the grid's bottom edge):
  ``[x, y]`` or ``[x, y, z]``, the lab origin in board coordinates (metres);
* ``inverted`` (optional): ``true`` for a board printed inverted (white markers on
  black), ``false`` for a normal one; without the key each image is tried normal first,
  then inverted (``255 − image``), and the report says which was found.

Board frame (OpenCV's): origin at the grid's top-left corner, x along the columns,
y along the rows (down the printed board), z = x × y (into the board). In the
reference image the board stands upright on the heated plate facing camera 0, so
board x is lab +x, board y is lab −y and board z is lab −z:
``x_lab = diag(1, −1, −1) · (x_board − lab_origin_in_board)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

#: Board axes → lab axes in the reference image (x → +x, y → −y, z → −z).
BOARD_TO_LAB_AXES = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board, sizes in metres, and where the lab origin sits on it."""

    squares_x: int
    squares_y: int
    square_length: float
    marker_length: float
    dictionary: str = "DICT_4X4_50"
    reference_image: str | None = None
    lab_origin_in_board: tuple[float, float, float] | None = None
    inverted: bool | None = None

    @property
    def lab_origin(self) -> np.ndarray:
        """(3,) lab origin in board coordinates, metres (default: bottom-edge centre)."""
        if self.lab_origin_in_board is None:
            return np.array(
                [self.squares_x * self.square_length / 2, self.squares_y * self.square_length, 0.0]
            )
        return np.asarray(self.lab_origin_in_board, dtype=np.float64)

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (object points in metres)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )

    def board_to_lab(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` with ``x_lab = R @ x_board + t`` in the reference image (metres)."""
        R = BOARD_TO_LAB_AXES.copy()
        return R, -R @ self.lab_origin


def board_from_dict(d: dict, source: str = "board") -> BoardSpec:
    """Validate a board description (``board.yaml`` contents); errors name ``source``."""
    required = ("squares_x", "squares_y", "square_length", "marker_length")
    missing = [k for k in required if k not in d]
    if missing:
        raise ValueError(f"{source}: missing board key(s) {', '.join(missing)}")
    dictionary = str(d.get("dictionary", "DICT_4X4_50"))
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"{source}: unknown ArUco dictionary {dictionary!r}")
    sx, sy = int(d["squares_x"]), int(d["squares_y"])
    sq, mk = float(d["square_length"]), float(d["marker_length"])
    if sx < 2 or sy < 2:
        raise ValueError(f"{source}: the board needs at least 2×2 squares, not {sx}×{sy}")
    if not 0 < mk < sq:
        raise ValueError(
            f"{source}: marker_length ({mk} m) must be positive and below square_length ({sq} m)"
        )
    origin = d.get("lab_origin_in_board")
    if origin is not None:
        origin = [float(v) for v in origin]
        if len(origin) == 2:
            origin.append(0.0)
        if len(origin) != 3:
            raise ValueError(f"{source}: lab_origin_in_board must be [x, y] or [x, y, z] metres")
        origin = tuple(origin)
    ref = d.get("reference_image")
    inverted = d.get("inverted")
    if inverted is not None and not isinstance(inverted, bool):
        raise ValueError(f"{source}: inverted must be true or false, not {inverted!r}")
    return BoardSpec(
        squares_x=sx,
        squares_y=sy,
        square_length=sq,
        marker_length=mk,
        dictionary=dictionary,
        reference_image=None if ref is None else str(ref),
        lab_origin_in_board=origin,
        inverted=inverted,
    )


def load_board(path: str | Path) -> BoardSpec:
    """Read ``board.yaml``; raises FileNotFoundError / ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"board file not found: {path}")
    try:
        d = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected a mapping of board keys")
    return board_from_dict(d, source=str(path))
