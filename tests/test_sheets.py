"""surfphase.sheets: the campaign sheets' conventions shared by the workflow and the package."""

from surfphase.sheets import camera_columns


def test_camera_columns_are_the_cam_n_columns_in_numeric_order():
    cols = ["session", "cam10", "rig", "cam2", "camera", "cam0", "cam1x", "gt", "cam1"]
    assert camera_columns(cols) == ["cam0", "cam1", "cam2", "cam10"]
