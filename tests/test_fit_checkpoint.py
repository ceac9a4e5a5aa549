"""A damaged fit checkpoint is reported, naming the file, discarded, and the fit resumes
from the last good one to the result of an uninterrupted run."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from test_fit_stage import SMALL
from test_fit_toy import make_toy_session

from surfphase.fit.outputs import load_surfels
from surfphase.fit.stage import run_fit

PARAMS = {**SMALL, "iters_first": 20, "iters_next": 6, "frames": 3, "densify_every": 5}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The toy session fitted once, uninterrupted, with its full checkpoint folder."""
    root = tmp_path_factory.mktemp("ckpt")
    ingest, masks = make_toy_session(root / "toy", frames=3, size=40)
    out, ckpt = root / "ref", root / "ref.ckpt"
    run_fit(ingest, masks, out, PARAMS, device="cpu", checkpoint_dir=ckpt)
    return ingest, masks, out, ckpt


def assert_same_fit(a_dir, b_dir):
    a, b = load_surfels(a_dir / "surfels.npz"), load_surfels(b_dir / "surfels.npz")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert (a_dir / "bubbles.csv").read_text() == (b_dir / "bubbles.csv").read_text()


@pytest.mark.parametrize(
    ("damaged", "recomputed"),
    [
        ("state.pt", [3]),  # the newest state: resume from the previous one
        ("frame_00002.pt", [3]),  # the newest frame record: the same
        ("frame_00000.pt", [1, 2, 3]),  # the first record: no state can resume
        ("state.prev.pt", []),  # unused: the newest state resumes, nothing is refitted
    ],
)
def test_damaged_checkpoint_is_reported_and_the_fit_resumes(
    reference, tmp_path, capsys, damaged, recomputed
):
    ingest, masks, ref, ref_ckpt = reference
    ckpt = tmp_path / "run.ckpt"
    shutil.copytree(ref_ckpt, ckpt)
    assert {"state.pt", "state.prev.pt"} <= {p.name for p in ckpt.iterdir()}
    (ckpt / damaged).write_bytes(b"\x80\x02garbage, not a torch file" * 3)
    capsys.readouterr()
    out = tmp_path / "run"
    run_fit(ingest, masks, out, PARAMS, device="cpu", checkpoint_dir=ckpt)
    log = capsys.readouterr().out
    if damaged != "state.prev.pt":
        assert f"checkpoint file {ckpt / damaged} is unreadable" in log, log
        assert "discarded" in log
    fitted = [int(ln.split("frame ")[1].split("/")[0]) for ln in log.splitlines() if "/3," in ln]
    assert fitted == recomputed, log
    assert_same_fit(ref, out)
    # Every file left in the checkpoint is readable again: a second rerun refits nothing.
    capsys.readouterr()
    run_fit(ingest, masks, tmp_path / "again", PARAMS, device="cpu", checkpoint_dir=ckpt)
    assert "/3," not in capsys.readouterr().out
    assert_same_fit(ref, tmp_path / "again")
