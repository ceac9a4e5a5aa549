"""Calibration inputs on the synthetic rig: recordings paired by timestamps, inverted
boards, the likely cause when the board is not found, lengths in the wrong unit, and
the workflow's rigs.tsv columns."""

from __future__ import annotations

import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
import yaml

from surfphase.calib import calibrate_rig_detailed
from surfphase.calib.solve import CalibrationWarning
from surfphase.synth.charuco import board_yaml_dict, write_calibration_images
from surfphase.synth.rig import default_rig

ROOT = Path(__file__).resolve().parents[1]
N_POSES = 16
LEAD = 2  # cam1's recording starts this many frames before cam0's


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """Folders of synthetic views, the same views as TIFF recordings (cam1's with
    ``LEAD`` blank frames first) and their timestamps; board files."""
    root = tmp_path_factory.mktemp("calib_inputs")
    write_calibration_images(default_rig(), root / "images", seed=3, n_poses=N_POSES)
    names = [f"pose{k:03d}.png" for k in range(N_POSES)]
    frames = {
        n: [cv2.imread(str(root / "images" / n / f), cv2.IMREAD_GRAYSCALE) for f in names]
        for n in ("cam0", "cam1")
    }
    blank = np.full_like(frames["cam1"][0], 165)
    tifffile.imwrite(root / "cam0.tif", np.stack(frames["cam0"]))
    tifffile.imwrite(root / "cam1.tif", np.stack([blank] * LEAD + frames["cam1"]))
    rows = ["sync_index,cam_id,frame_time"]
    for k in range(N_POSES):
        rows.append(f"{k},0,{100 + 0.1 * k:.4f}")
    for j in range(N_POSES + LEAD):  # 4 ms late, LEAD frames earlier
        rows.append(f"{j},1,{100 + 0.1 * (j - LEAD) + 0.004:.4f}")
    (root / "timestamps.csv").write_text("\n".join(rows) + "\n")
    board = board_yaml_dict()
    (root / "board.yaml").write_text(yaml.safe_dump(board))
    video_board = {k: v for k, v in board.items() if k != "reference_image"}
    (root / "board_video.yaml").write_text(yaml.safe_dump(video_board))
    return root


def _board(root: Path, name: str, **changes) -> Path:
    d = {**yaml.safe_load((root / "board.yaml").read_text()), **changes}
    path = root / f"{name}.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


@pytest.fixture(scope="module")
def from_folders(rig):
    return calibrate_rig_detailed(
        rig / "board.yaml", {n: rig / "images" / n for n in ("cam0", "cam1")}, rig="r"
    )


def test_recordings_paired_by_timestamps_match_the_folders(rig, from_folders):
    """The same views as recordings, cam1's two frames ahead: paired by time they give
    the folders' calibration; the frames without a partner are views of cam1 alone."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        cal = calibrate_rig_detailed(
            rig / "board_video.yaml",
            {"cam0": rig / "cam0.tif", "cam1": rig / "cam1.tif"},
            rig="r",
            timestamps=rig / "timestamps.csv",
        )
    sync = cal.report["sync"]
    assert sync["mode"] == "timestamps"
    assert sync["sync_tolerance_s"] == pytest.approx(0.025)
    assert sync["cameras"]["cam1"]["paired_with_cam0"] == N_POSES
    assert sync["cameras"]["cam1"]["alone"] == LEAD
    assert sync["cameras"]["cam1"]["max_pair_dt_s"] == pytest.approx(0.004, abs=1e-6)
    assert cal.sources["cam1"].frame_of["f000000"] == LEAD
    assert cal.report["reference_image"] == "f000000"
    assert cal.report["warnings"] == []
    for n in ("cam0", "cam1"):
        a, b = cal.cameras[n], from_folders.cameras[n]
        np.testing.assert_allclose(a.K, b.K, rtol=1e-6)
        np.testing.assert_allclose(a.R, b.R, atol=1e-7)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)


def test_recordings_paired_by_index_when_out_of_step_are_refused(rig):
    """Without the timestamps frame k is taken as one moment: every pair is two moments
    that do not fit one board pose, and the run asks whether they are synchronised
    (strict: it stops)."""
    with pytest.raises(ValueError) as e:
        calibrate_rig_detailed(
            rig / "board_video.yaml",
            {"cam0": rig / "cam0.tif", "cam1": rig / "cam1.tif"},
            strict=True,
        )
    msg = str(e.value)
    assert "different frame counts (cam0: 16, cam1: 18)" in msg
    assert "cam1: 4 of the 5 moments it shares with cam0 do not fit one board pose" in msg
    assert "cam0.tif and" in msg and "cam1.tif synchronised" in msg


def test_folders_raise_no_warning(from_folders):
    rep = from_folders.report
    assert rep["warnings"] == [] and rep["intrinsics_from"] == "joint solve"
    assert rep["polarity"]["views"]["cam0"]["inverted"] == 0
    true = default_rig()
    for n in ("cam0", "cam1"):
        assert abs(from_folders.cameras[n].K[0, 0] / true[n].K[0, 0] - 1) < 0.005


@pytest.fixture(scope="module")
def inverted(rig):
    """The first 12 views of each camera, printed inverted (255 − image)."""
    out = {}
    for n in ("cam0", "cam1"):
        out[n] = rig / "inverted" / n
        out[n].mkdir(parents=True)
        for k in range(12):
            img = cv2.imread(str(rig / "images" / n / f"pose{k:03d}.png"), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(out[n] / f"pose{k:03d}.png"), 255 - img)
    return out


def test_inverted_board_found_automatically_or_by_key(rig, inverted, from_folders):
    auto = calibrate_rig_detailed(rig / "board.yaml", inverted, min_images=4)
    assert auto.report["polarity"]["from"].startswith("found automatically")
    assert auto.report["polarity"]["views"]["cam0"]["normal"] == 0
    normal = [v for v in from_folders.detections["cam0"] if int(v[4:7]) < 12]
    assert auto.report["polarity"]["views"]["cam0"]["inverted"] == len(normal)
    keyed = calibrate_rig_detailed(_board(rig, "inv", inverted=True), inverted, min_images=4)
    assert keyed.report["polarity"]["from"] == "board key inverted: true"
    for cal in (auto, keyed):
        assert cal.report["warnings"] == []
        for n in ("cam0", "cam1"):
            K, ref = cal.cameras[n].K, from_folders.cameras[n].K
            assert abs(K[0, 0] / ref[0, 0] - 1) < 0.01


@pytest.mark.parametrize(
    ("changes", "cause"),
    [
        ({"inverted": False}, "likely cause: the board is printed inverted"),
        ({"squares_x": 7, "squares_y": 5}, "likely cause: squares_x and squares_y are swapped"),
        (
            {"dictionary": "DICT_5X5_50"},
            "likely cause: markers of another dictionary, DICT_4X4_1000",
        ),
        ({"squares_x": 4, "squares_y": 5}, "are not on a 4×5 board"),
    ],
)
def test_board_not_found_says_the_likely_cause(rig, inverted, changes, cause):
    board = _board(rig, "bad", **changes)
    with pytest.raises(ValueError) as e:
        calibrate_rig_detailed(board, inverted, rig="r9")
    msg = str(e.value)
    assert msg.startswith("rig r9: board found in only 0 of 12 images of cam0 (")
    assert str(inverted["cam0"]) in msg and cause in msg, msg


def test_board_in_millimetres_is_caught(rig):
    board = board_yaml_dict()
    mm = {k: board[k] * 1000 for k in ("square_length", "marker_length")}
    mm["lab_origin_in_board"] = [v * 1000 for v in board["lab_origin_in_board"]]
    with pytest.raises(ValueError) as e:
        calibrate_rig_detailed(
            _board(rig, "mm", **mm), {n: rig / "images" / n for n in ("cam0", "cam1")}
        )
    msg = str(e.value)
    assert "implausibly far from the board (cam0 43" in msg
    assert "if they are in millimetres they are 0.004 and 0.003 m (cameras 0.043 m away)" in msg


def test_workflow_passes_the_rigs_timestamps(rig, tmp_path):
    """A rigs.tsv row with recordings and a timestamps column, run by Snakemake."""
    shutil.copytree(ROOT / "config", tmp_path / "config")
    (tmp_path / "config" / "rigs.tsv").write_text(
        "rig\tboard\tcam0\tcam1\ttimestamps\n"
        f"rigv\t{rig / 'board_video.yaml'}\t{rig / 'cam0.tif'}\t{rig / 'cam1.tif'}\t"
        f"{rig / 'timestamps.csv'}\n"
    )
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(tmp_path)]
    r = subprocess.run(
        [*cmd, "--cores", "1", "results/calib/rigv/cameras.json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    import json

    report = json.loads((tmp_path / "results" / "calib" / "rigv" / "report.json").read_text())
    assert report["sync"]["mode"] == "timestamps"
    assert report["sync"]["cameras"]["cam1"]["alone"] == LEAD


def test_timestamps_errors_name_the_file_and_camera(rig, tmp_path):
    from surfphase.calib.sources import open_sources

    cams = {"cam0": rig / "cam0.tif", "cam1": rig / "cam1.tif"}
    bad = tmp_path / "ts.csv"
    bad.write_text("cam,time\n0,1.0\n")
    with pytest.raises(ValueError, match=f"{bad}: timestamps need the columns cam_id and"):
        open_sources(cams, timestamps=bad)
    lines = (rig / "timestamps.csv").read_text().splitlines()
    bad.write_text("\n".join(lines[:-1]) + "\n")  # cam1's last frame missing
    with pytest.raises(ValueError, match=f"{bad}: 17 timestamps for camera cam1, whose "):
        open_sources(cams, timestamps=bad)
    with pytest.raises(ValueError, match="timestamps .* are for recordings"):
        open_sources({n: rig / "images" / n for n in cams}, timestamps=rig / "timestamps.csv")
    with pytest.raises(ValueError, match="not a mix"):
        open_sources({"cam0": rig / "cam0.tif", "cam1": rig / "images" / "cam1"})
    # Sampling: at most max_frames, evenly spaced, the first frame included.
    src, sync = open_sources(cams, timestamps=rig / "timestamps.csv", max_frames=4)
    assert [src["cam0"].frame_of[v] for v in src["cam0"].names] == [0, 5, 10, 15]
    assert sorted(src["cam1"].frame_of[v] for v in src["cam1"].names if "-" not in v) == [
        LEAD + k for k in (0, 5, 10, 15)
    ]
