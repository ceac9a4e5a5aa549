"""Calibration stage: views (images or recordings), ChArUco detection, multi-camera solve
in the lab frame checked against each camera alone, report."""

from surfphase.calib.board import BoardSpec, board_from_dict, load_board
from surfphase.calib.report import corners_picture, write_calibration
from surfphase.calib.solve import (
    Calibration,
    CalibrationWarning,
    calibrate_rig,
    calibrate_rig_detailed,
)

__all__ = [
    "BoardSpec",
    "Calibration",
    "CalibrationWarning",
    "board_from_dict",
    "calibrate_rig",
    "calibrate_rig_detailed",
    "corners_picture",
    "load_board",
    "write_calibration",
]
