"""The stage folders' readers and writers (:mod:`surfphase.folders`): what a writer puts
down its reader gives back, and each bad folder is refused naming the session and file."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from skimage.util import img_as_float32

from surfphase.cameras import look_at
from surfphase.folders.frames import to_uint16, unit_float, unit_grey
from surfphase.folders.ingest import read_ingest, write_ingest
from surfphase.folders.masks import read_anchors, read_masks, read_merges, write_masks
from surfphase.folders.views import read_refined, read_views, write_refined, write_views

T, H, W = 4, 10, 12


def cameras():
    return {
        n: look_at(n, [0.03 * np.sin(a), 0.005, 0.03 * np.cos(a)], [0, 0, 0], fx=40.0,
                   width=W, height=H)
        for n, a in (("cam0", 0.0), ("cam1", 0.6))
    }  # fmt: skip


@pytest.fixture
def ingest(tmp_path):
    rng = np.random.default_rng(0)
    stacks = {n: rng.random((T, H, W), dtype=np.float32) for n in ("cam0", "cam1")}
    folder = tmp_path / "s07" / "ingest"
    write_ingest(folder, "s07", 500.0, cameras(), stacks, frame_indices=[10, 12, 14, 16])
    return folder, stacks


def test_unit_float_against_scikit_image():
    rng = np.random.default_rng(1)
    for dtype in (np.uint8, np.uint16):
        a = rng.integers(0, np.iinfo(dtype).max + 1, (5, 7), dtype=dtype)
        got = unit_float(a)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, img_as_float32(a), rtol=1e-6, atol=0)
    f = np.array([-0.5, 0.25, 1.5], np.float64)
    np.testing.assert_array_equal(unit_float(f), np.array([0.0, 0.25, 1.0], np.float32))
    # A 12-bit camera in 16-bit words: its declared depth, not the dtype's, is full scale.
    twelve = np.array([0, 2048, 4095], np.uint16)
    np.testing.assert_allclose(unit_float(twelve, bit_depth=12), [0.0, 2048 / 4095, 1.0])
    with pytest.raises(ValueError, match="bit depth 17"):
        unit_float(twelve, bit_depth=17)
    with pytest.raises(ValueError, match="int32"):
        unit_float(np.zeros(3, np.int32))
    # Dark 16-bit frames are not mistaken for 8-bit ones (no guessing from the values).
    dark = np.full((2, 2), 200, np.uint16)
    np.testing.assert_allclose(unit_float(dark), 200 / 65535)
    rgb = np.stack([np.full((2, 3), v, np.uint8) for v in (0, 51, 255)], axis=-1)
    np.testing.assert_allclose(unit_grey(rgb), (0 + 51 + 255) / 3 / 255, rtol=1e-6)
    back = unit_float(to_uint16(np.array([0.0, 0.5, 1.0])))
    np.testing.assert_allclose(back, [0.0, 32768 / 65535, 1.0])


def test_ingest_round_trip(ingest):
    folder, stacks = ingest
    got = read_ingest(folder, min_cameras=2)
    assert got.session == "s07" and got.fps == 500.0 and got.names == ["cam0", "cam1"]
    np.testing.assert_array_equal(got.frame_indices, [10, 12, 14, 16])
    assert got.n_frames == T and got.native() is None
    for n, st in stacks.items():
        np.testing.assert_array_equal(got.stacks[n], st)
        np.testing.assert_array_equal(got.frames(n, 2), st[2])
        assert got.cameras[n].to_dict() == cameras()[n].to_dict()
    assert [c.name for c in got.input_cameras()] == ["cam0", "cam1"]
    assert json.loads((folder / "meta.json").read_text())["dtype"] == "float32"
    # Without frames (the mesh stage): cameras and metadata only.
    light = read_ingest(folder, stacks=False)
    assert light.stacks == {} and light.session == "s07" and light.n_frames == 0


def test_ingest_missing_files_are_named(ingest, tmp_path):
    folder, _ = ingest
    (folder / "cam1.npy").unlink()
    with pytest.raises(FileNotFoundError, match=r"cam1\.npy: frame stack of camera cam1 "
                       r"\(session s07\) not found"):  # fmt: skip
        read_ingest(folder)
    (folder / "meta.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"ingest/meta\.json: not found in the ingest"):
        read_ingest(folder)
    with pytest.raises(FileNotFoundError, match=r"cameras\.json: not found in the ingest"):
        read_ingest(tmp_path / "nowhere")


def test_ingest_frame_counts_must_agree(ingest):
    folder, stacks = ingest
    np.save(folder / "cam1.npy", stacks["cam1"][:3])
    with pytest.raises(ValueError, match=r"cam1\.npy: 3 frames, camera cam0 has 4 \(session s07\)"):
        read_ingest(folder)


def test_ingest_dtype_is_checked(ingest):
    folder, stacks = ingest
    # meta.json declares float32: a uint16 stack is refused, naming file and session.
    np.save(folder / "cam1.npy", to_uint16(stacks["cam1"]))
    with pytest.raises(ValueError, match=r"cam1\.npy: frames stored as uint16, but meta\.json "
                       r"declares float32 \(session s07\)"):  # fmt: skip
        read_ingest(folder)
    # Without a declaration (a folder written by hand) uint16 frames are read by their dtype,
    np.testing.assert_allclose(
        unit_float(np.load(folder / "cam1.npy")), stacks["cam1"], atol=0.5 / 65535 + 1e-7
    )
    meta = json.loads((folder / "meta.json").read_text())
    del meta["dtype"]
    (folder / "meta.json").write_text(json.dumps(meta))
    got = read_ingest(folder)
    np.testing.assert_allclose(got.frames("cam1"), stacks["cam1"], atol=0.5 / 65535 + 1e-7)
    # but a dtype frames are never stored in is refused.
    np.save(folder / "cam1.npy", np.zeros((T, H, W), np.int32))
    with pytest.raises(ValueError, match=r"cam1\.npy \(session s07\): frames stored as int32"):
        read_ingest(folder)


def test_ingest_metadata_errors_name_the_file(ingest):
    folder, _ = ingest
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, "fps": -1}))
    with pytest.raises(ValueError, match=r"meta\.json: session s07: fps must be positive"):
        read_ingest(folder)
    (folder / "meta.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "fps"}))
    with pytest.raises(ValueError, match=r"meta\.json: session s07: fps must be positive"):
        read_ingest(folder).require_fps()
    (folder / "meta.json").write_text(json.dumps({**meta, "session": ""}))
    with pytest.raises(ValueError, match=r"meta\.json: no session name"):
        read_ingest(folder)
    (folder / "meta.json").write_text(json.dumps({**meta, "cameras": ["cam0", "cam9"]}))
    with pytest.raises(ValueError, match=r"cameras\.json: no camera 'cam9' \(session s07\)"):
        read_ingest(folder)
    np.save(folder / "cam0.npy", np.zeros((T, H + 1, W), np.float32))
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"cam0\.npy: frames are 12×11 pixels .* 12×10"):
        read_ingest(folder)


def _mask_tables():
    instances = pd.DataFrame(
        {"frame": [0, 1], "camera": ["cam0", "cam1"], "bubble": [1, 1], "area": [3, 4],
         "cx": [1.23456, 2.0], "cy": [0.5, 0.25], "x0": [0, 1], "y0": [0, 0], "x1": [2, 3],
         "y1": [1, 1], "score": [0.9, 0.8]}
    )  # fmt: skip
    events = pd.DataFrame(columns=["frame", "camera", "event", "parents", "children"])
    anchors = pd.DataFrame({"frame": [0], "bubble": [1], "x": [1e-3], "y": [2e-3], "z": [0.0]})
    return instances, events, anchors


def test_masks_round_trip_and_errors(tmp_path):
    cams = list(cameras().values())
    rng = np.random.default_rng(2)
    labels = {c.name: rng.integers(-1, 3, (T, H, W)).astype(np.int32) for c in cams}
    instances, events, anchors = _mask_tables()
    folder = tmp_path / "masks"
    overlay = np.zeros((H, 2 * W, 3), np.uint8)
    write_masks(folder, labels, instances, events, anchors, {"frame_00000.png": overlay},
                {"session": "s07", "cameras": list(labels)})  # fmt: skip
    got = read_masks(folder, cams, "s07", n_frames=T)
    assert got.n_frames == T and list(got.labels) == ["cam0", "cam1"]
    for c in cams:
        np.testing.assert_array_equal(got.labels[c.name], labels[c.name])
        np.testing.assert_array_equal(got.frame(c.name, 1), labels[c.name][1])
    back = pd.read_csv(folder / "instances.csv")
    assert back["cx"].tolist() == [1.235, 2.0]
    assert json.loads((folder / "masks.json").read_text())["session"] == "s07"
    assert (folder / "overlays" / "frame_00000.png").is_file()
    # Each bad folder is refused, naming the file and the session.
    with pytest.raises(ValueError, match=r"cam0_labels\.npy: session s07: masks of 4 frames, "
                       r"the frame stacks have 5"):  # fmt: skip
        read_masks(folder, cams, "s07", n_frames=5)
    with pytest.raises(ValueError, match=r"cam0_labels\.npy: session s07: masks of 4 frames, "
                       r"6 needed"):  # fmt: skip
        read_masks(folder, cams, "s07", min_frames=6)
    np.save(folder / "cam1_labels.npy", labels["cam1"][:2])
    with pytest.raises(ValueError, match=r"cam1_labels\.npy: session s07: 2 frames, the masks "
                       r"of cam0 have 4"):  # fmt: skip
        read_masks(folder, cams, "s07")
    np.save(folder / "cam1_labels.npy", labels["cam1"].astype(np.float32))
    with pytest.raises(ValueError, match=r"cam1_labels\.npy: session s07: labels stored as "
                       r"float32, expected integers"):  # fmt: skip
        read_masks(folder, cams, "s07")
    np.save(folder / "cam1_labels.npy", labels["cam1"][:, :, :5])
    with pytest.raises(ValueError, match=r"cam1_labels\.npy: session s07: labels of shape"):
        read_masks(folder, cams, "s07")
    (folder / "cam1_labels.npy").unlink()
    with pytest.raises(FileNotFoundError, match=r"cam1_labels\.npy: session s07: no masks"):
        read_masks(folder, cams, "s07")
    # A rewrite replaces the old overlays.
    write_masks(folder, labels, instances, events, anchors, {}, {"session": "s07"})
    assert not (folder / "overlays").exists()


def test_views_round_trip_and_errors(tmp_path):
    cams = list(cameras().values())
    rng = np.random.default_rng(3)
    frames = rng.random((2, T, H, W), dtype=np.float32)
    alphas = rng.random((2, T, H, W), dtype=np.float32)
    bg = np.full((H, W), 0.4, np.float32)
    folder = tmp_path / "views"
    meta = {"session": "s07", "fps": 500.0, "frame": [10, 12, 14, 16], "reference": "cam0"}
    write_views(folder, cams, frames, alphas, bg, meta)
    got = read_views(folder)
    assert (got.session, got.fps, got.meta["reference"]) == ("s07", 500.0, "cam0")
    np.testing.assert_array_equal(got.frame, [10, 12, 14, 16])
    assert list(got.cameras) == ["cam0", "cam1"]
    assert got.stored("cam1").dtype == np.uint16
    np.testing.assert_allclose(got.frames("cam1"), frames[1], atol=0.5 / 65535 + 1e-7)
    np.testing.assert_array_equal(np.load(folder / "background.npy"), bg)
    np.testing.assert_array_equal(got.background(), bg)
    assert got.alpha("cam0").dtype == np.float16
    np.testing.assert_array_equal(got.alpha("cam0"), alphas[0].astype(np.float16))
    with pytest.raises(FileNotFoundError, match=r"orbit09_alpha\.npy: no alpha of view orbit09 "
                       r"\(session s07\)"):  # fmt: skip
        got.alpha("orbit09")
    (folder / "background.npy").unlink()
    assert got.background() is None
    with pytest.raises(FileNotFoundError, match=r"orbit09\.npy: no such view in"):
        got.frames("orbit09")
    np.save(folder / "cam1.npy", frames[1])
    with pytest.raises(ValueError, match=r"cam1\.npy: expected a \(T, H, W\) uint16 stack, got "
                       r"float32"):  # fmt: skip
        got.frames("cam1")
    bad = json.loads((folder / "cameras.json").read_text())
    (folder / "cameras.json").write_text(json.dumps({**bad, "fps": 0}))
    with pytest.raises(ValueError, match=r"views/cameras\.json: session s07: fps must be positive"):
        read_views(folder)
    shutil.rmtree(folder)
    with pytest.raises(FileNotFoundError, match=r"cameras\.json: no cameras\.json in the views"):
        read_views(folder)
    # A refined view: json, mp4 and the uint16 frames, read back in [0, 1].
    refine, part = tmp_path / "refine", tmp_path / ".part"
    refine.mkdir()
    part.mkdir()
    write_refined(part, refine, "orbit01", frames[0], 500.0, {"strength": 0.3})
    np.testing.assert_allclose(read_refined(refine, "orbit01"), frames[0], atol=0.5 / 65535 + 1e-7)
    assert json.loads((refine / "orbit01.json").read_text()) == {"strength": 0.3}
    assert (refine / "orbit01.mp4").stat().st_size > 0


def test_merges_from_the_mask_events(tmp_path):
    p = tmp_path / "events.csv"
    p.write_text(
        "frame,camera,event,parents,children\n"
        "14,cam0,merge,1+2,5\n"
        "3,cam1,split,3,1+4\n"
        "14,cam1,merge,2+4,5\n"
        "19,cam1,merge,3+5,6\n"
    )
    assert read_merges(tmp_path, "s07") == {14: {5: {1, 2, 4}}, 19: {6: {3, 5}}}
    # A merge row without parents (older mask stages wrote them; seen on a synthetic
    # session with a split and two merges) is skipped, not a crash on "nan".
    p.write_text(
        "frame,camera,event,parents,children\n"
        "9,cam0,merge,,5\n12,cam0,merge,6+5,7\n18,cam1,detach,0,8\n"
    )
    assert read_merges(tmp_path, "s07") == {12: {7: {5, 6}}}
    assert read_merges(tmp_path / "missing", "s07") == {}
    p.write_text("frame,camera\n1,cam0\n")
    with pytest.raises(ValueError, match=r"events\.csv: session s07: not a merge/split event"):
        read_merges(tmp_path, "s07")


def test_anchors_table(tmp_path):
    assert read_anchors(tmp_path, "s07") is None  # masks written before anchors existed
    (tmp_path / "anchors.csv").write_text("frame,bubble,x,y,z,n_views\n12,3,0.001,0.002,0.5,2\n")
    tab = read_anchors(tmp_path, "s07")
    assert tab.to_dict("records") == [
        {"frame": 12, "bubble": 3, "x": 0.001, "y": 0.002, "z": 0.5, "n_views": 2}
    ]
    (tmp_path / "anchors.csv").write_text("frame,bubble,x\n12,3,0.001\n")
    with pytest.raises(ValueError, match=r"anchors\.csv: session s07: anchors lack columns "
                       r"\['y', 'z'\]"):  # fmt: skip
        read_anchors(tmp_path, "s07")
