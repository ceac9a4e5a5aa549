"""The mask stage end to end, its command line, and its errors."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from test_masks_scene import rising, write_ingest

from surfphase.cli import main
from surfphase.masks.stage import DEFAULTS, merge_params, run_mask_stage

SPHERES = [
    lambda t: (np.array([-0.0025, 0.0006 + 0.00003 * t, 0.0]), 0.0006 + 0.00003 * t),
    rising(0.002, 0.003, 0.0, 0.0008),
    rising(-0.001, 0.008, 0.001, 0.001),
]


@pytest.fixture(scope="module")
def ingest(tmp_path_factory):
    d = tmp_path_factory.mktemp("ingest")
    truth = write_ingest(d, SPHERES, 6)
    return d, truth


def test_command_writes_every_output(ingest, tmp_path, capsys):
    d, truth = ingest
    out = tmp_path / "masks"
    cfg = tmp_path / "config.yaml"
    cfg.write_text("masks:\n  overlay_frames: 2\n  associate:\n    coast_frames: 4\n")
    assert main(["mask", "--ingest", str(d), "--out", str(out), "--config", str(cfg)]) == 0
    for c in truth:
        lab = np.load(out / f"{c}_labels.npy")
        assert lab.dtype == np.int32 and lab.shape == truth[c].shape
        # Background where the truth is background (allowing the 1-px rim).
        assert (lab[truth[c] < 0] >= 0).mean() < 0.01
        assert set(np.unique(lab)) == {-1, 0, 1, 2}
    inst = pd.read_csv(out / "instances.csv")
    assert list(inst.columns) == [
        "frame",
        "camera",
        "bubble",
        "area",
        "cx",
        "cy",
        "x0",
        "y0",
        "x1",
        "y1",
        "score",
    ]
    assert len(inst) == 6 * 2 * 3
    # The instance table agrees with the label stacks.
    lab0 = np.load(out / "cam0_labels.npy")
    for r in inst[inst.camera == "cam0"].itertuples():
        m = lab0[r.frame] == r.bubble
        ys, xs = np.nonzero(m)
        assert r.area == m.sum() and (r.x0, r.y0, r.x1, r.y1) == (
            xs.min(),
            ys.min(),
            xs.max(),
            ys.max(),
        )
        assert r.cx == pytest.approx(xs.mean(), abs=1e-3)
    assert list(pd.read_csv(out / "events.csv").columns) == [
        "frame",
        "camera",
        "event",
        "parents",
        "children",
    ]
    assert sorted(p.name for p in (out / "overlays").iterdir()) == [
        "frame_00000.png",
        "frame_00005.png",
    ]
    info = json.loads((out / "masks.json").read_text())
    assert info["session"] == "s01" and info["bubbles"] == 2
    assert info["params"]["associate"]["coast_frames"] == 4
    assert "masks written" in capsys.readouterr().out


def test_params_json_as_the_workflow_passes_them(ingest, tmp_path, capsys):
    d, _ = ingest
    out = tmp_path / "masks"
    settings = json.dumps({"backend": "classical", "overlay_frames": 1})
    assert main(["mask", "--ingest", str(d), "--out", str(out), "--params-json", settings]) == 0
    assert len(list((out / "overlays").iterdir())) == 1
    rc = main(["mask", "--ingest", str(d), "--out", str(out), "--params-json", "[1]"])
    assert rc == 2 and "expected a JSON object" in capsys.readouterr().err


def test_integer_frames_give_the_same_masks(ingest, tmp_path):
    d, _ = ingest
    run_mask_stage(d, tmp_path / "a", {"overlay_frames": 0})
    d16 = tmp_path / "in16"
    write_ingest(d16, SPHERES, 6, dtype=np.uint16)
    run_mask_stage(d16, tmp_path / "b", {"overlay_frames": 0})
    for c in ("cam0", "cam1"):
        a = np.load(tmp_path / "a" / f"{c}_labels.npy")
        b = np.load(tmp_path / "b" / f"{c}_labels.npy")
        assert (a == b).mean() > 0.999


def test_missing_stack_is_named(ingest, tmp_path, capsys):
    d, _ = ingest
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in ("cameras.json", "meta.json", "cam0.npy"):
        (broken / f).write_bytes((d / f).read_bytes())
    rc = main(["mask", "--ingest", str(broken), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "cam1.npy" in err and "s01" in err
    assert not (tmp_path / "o").exists()


def test_frames_of_the_wrong_size_are_refused(ingest, tmp_path):
    d, _ = ingest
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in ("cameras.json", "meta.json", "cam0.npy"):
        (bad / f).write_bytes((d / f).read_bytes())
    np.save(bad / "cam1.npy", np.zeros((6, 100, 128), np.float32))
    with pytest.raises(ValueError, match=r"cam1\.npy: frames are 128×100 pixels.*128×128"):
        run_mask_stage(bad, tmp_path / "o", {})


def test_config_errors_name_the_key():
    with pytest.raises(ValueError, match="masks.classical.treshold_low"):
        merge_params({"classical": {"treshold_low": 0.1}})
    with pytest.raises(ValueError, match="backend"):
        merge_params({"backend": "magic"})
    assert merge_params(None) == DEFAULTS


def test_nucleation_pieces_grow_to_their_outline_and_keep_their_rows():
    """After the association the nucleation region's pieces (id 0) grow to their outline
    in front of the plate (:func:`classical.outline_in_front`) and their rows of the
    instance table are remade from the grown pixels; a free bubble's pixels and row are
    left as they were."""
    import cv2
    from test_masks_classical import shadowgraph

    from surfphase.masks import classical
    from surfphase.masks.stage import grown_nucleation

    frames = []
    for t in range(8):
        sites = [(40.0, 73.5, 5.0), (70.0, 30.0, 6.0)] if t % 2 == 0 else []
        img, _ = shadowgraph(96, 96, sites, seed=t, plate_row=64, noise=0.005)
        frames.append(cv2.GaussianBlur(img, (0, 0), 1.0))
    stack = np.stack(frames)
    bg = classical.static_background(classical.session_reference(stack))
    lab = np.full(stack.shape, -1, np.int32)
    rows = []
    for t in range(0, 8, 2):
        seg, _ = classical.segment_frame(stack[t], None, bg)
        for k in range(seg.max() + 1):
            ys, xs = np.nonzero(seg == k)
            b = 0 if ys.mean() > 64 else 1  # the one sitting on the plate
            lab[t][seg == k] = b
            rows.append((t, "cam0", b, ys.size, xs.mean(), ys.mean(), xs.min(), ys.min(),
                         xs.max(), ys.max(), 0.5))  # fmt: skip
    cols = ["frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1", "score"]
    inst = pd.DataFrame(rows, columns=cols)
    before = lab.copy()
    p = merge_params({})
    out = grown_nucleation({"cam0": lab}, inst, {"cam0": stack}, {"cam0": bg}, p)
    noise = classical.contrast_noise(stack, p["classical"], bg)
    for t in range(0, 8, 2):
        signed = classical.relative_contrast(stack[t], p["classical"], bg, signed=True)
        want = classical.outline_in_front(
            before[t] == 0, before[t] < 0, signed, bg[1], p["classical"], noise
        )
        assert (want.sum() > (before[t] == 0).sum()) and ((lab[t] == 0) == want).all()
        assert ((lab[t] == 1) == (before[t] == 1)).all()
        row = out[(out.frame == t) & (out.bubble == 0)].iloc[0]
        ys, xs = np.nonzero(want)
        assert row.area == ys.size and np.isclose(row.cx, xs.mean()) and row.y1 == ys.max()
        free = out[(out.frame == t) & (out.bubble == 1)].reset_index(drop=True)
        pd.testing.assert_frame_equal(
            free, inst[(inst.frame == t) & (inst.bubble == 1)].reset_index(drop=True)
        )


def test_grown_nucleation_pieces_stay_apart_downscaled():
    """Two attached bubbles side by side, their dark rims overlapping, each a bright core:
    grown with a 3-px gap (2 s − 1 at a downscale of s = 2) they stay two pieces in the
    downscaled labels too, which a 1-px gap does not keep apart."""
    from surfphase.masks.anchors import downsample_labels
    from surfphase.masks.stage import grown_nucleation

    h = w = 48
    yy, xx = np.mgrid[0:h, 0:w]
    bright = np.full((h, w), 0.3, np.float32)  # the plate, lit
    rhos = [np.hypot(yy - 16, xx - cx) for cx in (16, 24)]
    for rho in rhos:
        bright[rho <= 6] = 0.3 * 0.8  # the rim, 0.2 darker than the plate
    stack = np.stack([bright, bright])
    bg = (np.full((h, w), 0.3, np.float32), np.ones((h, w), bool))
    counts = {}
    for gap in (1, 3):
        lab = np.full((1, h, w), -1, np.int32)
        for rho in rhos:
            stack[:, rho <= 3] = 0.9  # the core
            lab[0][rho <= 3] = 0
        inst = pd.DataFrame(
            [(0, "cam0", 0, 29, float(cx), 16.0, cx - 3, 13, cx + 3, 19, 0.5) for cx in (16, 24)],
            columns=["frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1",
                     "score"],
        )  # fmt: skip
        out = grown_nucleation({"cam0": lab}, inst, {"cam0": stack}, {"cam0": bg},
                               merge_params({}), gap)  # fmt: skip
        comp, n = ndi_label(lab[0] == 0)
        assert n == 2 and (lab[0] == 0).sum() > 2 * 29
        assert sorted(out.area) == sorted(np.bincount(comp.ravel())[1:])
        counts[gap] = ndi_label(downsample_labels(lab[0], (w // 2, h // 2)) == 0)[1]
    assert counts == {1: 1, 3: 2}


def ndi_label(mask):
    from scipy import ndimage as ndi

    return ndi.label(mask, np.ones((3, 3), bool))
