"""Calibration stage: ChArUco detection, multi-camera solve in the lab frame, report."""

from surfphase.calib.board import BoardSpec, board_from_dict, load_board
from surfphase.calib.report import corners_picture, write_calibration
from surfphase.calib.solve import Calibration, calibrate_rig, calibrate_rig_detailed

__all__ = [
    "BoardSpec",
    "Calibration",
    "board_from_dict",
    "calibrate_rig",
    "calibrate_rig_detailed",
    "corners_picture",
    "load_board",
    "write_calibration",
]
