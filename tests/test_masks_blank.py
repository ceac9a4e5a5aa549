"""A blank (all-black, saturated) or bubble-less camera stops the mask stage, naming the
session, the camera and the files; a few blank frames are a warning."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from test_masks_scene import rising, write_ingest

from surfphase.cli import main
from surfphase.masks.stage import frame_spans, run_mask_stage

TRACKS = [rising(0.0, 0.005, 0.0, 0.001)]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """A healthy 4-frame ingest folder and one of the same rig with no bubble at all."""
    root = tmp_path_factory.mktemp("blank")
    write_ingest(root / "ok", TRACKS, 4, size=64)
    write_ingest(root / "empty", [lambda t: None], 4, size=64)
    return root


def with_cam1(scenes, tmp_path, cam1: np.ndarray, source: str | None = None):
    d = tmp_path / "ingest"
    shutil.copytree(scenes / "ok", d)
    np.save(d / "cam1.npy", cam1)
    if source:  # what ingest writes: per camera, the video it read
        meta = json.loads((d / "meta.json").read_text())
        meta["cameras"] = {c: {"source": f"/data/{c}.tif"} for c in meta["cameras"]}
        (d / "meta.json").write_text(json.dumps(meta))
    return d


def test_frame_spans_against_numpy(scenes):
    st = np.load(scenes / "ok" / "cam0.npy")
    want = np.percentile(st.reshape(len(st), -1), [0.1, 99.9], axis=1).T
    np.testing.assert_allclose(frame_spans(st), want, rtol=1e-6)
    st16 = np.round(st * 65535).astype(np.uint16)
    np.testing.assert_allclose(frame_spans(st16), want, atol=2e-5)


@pytest.mark.parametrize(
    ("kind", "frames"),
    [
        ("black", np.zeros((4, 64, 64), np.float32)),
        ("saturated", np.ones((4, 64, 64), np.float32)),
        ("saturated", np.full((4, 64, 64), 65535, np.uint16)),
        ("black", np.random.default_rng(0).integers(0, 2, (4, 64, 64)).astype(np.uint8)),
    ],
)
def test_blank_camera_stops_the_stage(scenes, tmp_path, capsys, kind, frames):
    d = with_cam1(scenes, tmp_path, frames, source="yes")
    out = tmp_path / "masks"
    assert main(["mask", "--ingest", str(d), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "session s01: camera cam1: every one of its 4 frames is blank" in err, err
    assert f"({kind}:" in err and "/data/cam1.tif" in err and str(d / "cam1.npy") in err
    assert not out.exists()


def test_camera_without_bubbles_stops_the_stage(scenes, tmp_path):
    d = with_cam1(scenes, tmp_path, np.load(scenes / "empty" / "cam1.npy"))
    assert (np.ptp(frame_spans(np.load(d / "cam1.npy")), axis=1) > 0.1).all()  # not blank
    with pytest.raises(ValueError, match=r"session s01: camera cam1: no bubble found in any"):
        run_mask_stage(d, tmp_path / "masks", {"overlay_frames": 0})
    assert not (tmp_path / "masks").exists()


def test_some_blank_frames_are_a_warning(scenes, tmp_path):
    cam1 = np.load(scenes / "ok" / "cam1.npy").copy()
    cam1[1:3] = 0.0
    d = with_cam1(scenes, tmp_path, cam1)
    with pytest.warns(UserWarning, match=r"camera cam1: 2 of 4 frames are blank.*frames 1, 2"):
        run_mask_stage(d, tmp_path / "masks", {"overlay_frames": 0})
    info = json.loads((tmp_path / "masks" / "masks.json").read_text())
    assert len(info["warnings"]) == 1 and "frames 1, 2" in info["warnings"][0]
    labels = np.load(tmp_path / "masks" / "cam1_labels.npy")
    assert (labels[1:3] == -1).all() and (labels[[0, 3]] >= 1).any()


def test_bubbles_the_views_never_agree_on_are_a_warning(scenes, tmp_path):
    # cam1 sees a bubble 1.6 times as large on the same track: paired, never consistent.
    write_ingest(tmp_path / "big", [rising(0.0, 0.005, 0.0, 0.0016)], 4, size=64)
    d = with_cam1(scenes, tmp_path, np.load(tmp_path / "big" / "cam1.npy"))
    with pytest.warns(
        UserWarning,
        match=r"session s01: bubble 1 is seen by cameras cam0 and "
        r"cam1 but in no frame do the two views agree.*no bubble will be reported",
    ):
        run_mask_stage(d, tmp_path / "masks", {"overlay_frames": 0})
    info = json.loads((tmp_path / "masks" / "masks.json").read_text())
    assert info["anchors"] == 0 and any("agree on their centre" in w for w in info["warnings"])
