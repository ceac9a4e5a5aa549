"""A lab's first day: its own LZW-compressed TIFF recordings and calibration images →
`surfphase new-campaign` → one board edit → `surfphase run`, which must finish.

The recordings are the tiny synthetic campaign's frames rewritten as the 16-bit,
LZW-compressed multi-page TIFFs that ImageJ/Fiji and camera tools write, under names the
lab chose (``<session>_<camera>.tif``); nothing here is tuned to the project's demo.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml
from PIL import Image

from surfphase.cli import main
from surfphase.ingest import auto_scale
from surfphase.synth.campaign import write_campaign


def _lzw_stack(folder: Path, out: Path) -> tuple[int, int]:
    """Write the PNG frames of ``folder`` as one 16-bit LZW multi-page TIFF; → (w, h)."""
    frames = [np.asarray(Image.open(p)) for p in sorted(folder.glob("*.png"))]
    stack = np.stack(frames)
    if stack.dtype == np.uint8:
        stack = stack.astype(np.uint16) * 257
    tifffile.imwrite(out, stack, compression="lzw", photometric="minisblack")
    return stack.shape[2], stack.shape[1]


@pytest.fixture(scope="module")
def lab_folder(tmp_path_factory) -> tuple[Path, Path]:
    """(videos folder as a lab has it, the rig's board file)."""
    root = tmp_path_factory.mktemp("firstday")
    synth = root / "synth"
    write_campaign(synth, preset="tiny", seed=5, sessions=1, frames=2, native=160)
    videos = root / "recordings"
    (videos / "calib").mkdir(parents=True)
    for cam, label in (("cam0", "left"), ("cam1", "right")):
        _lzw_stack(synth / "session01" / cam, videos / f"boil01_{label}.tif")
        shutil.copytree(synth / "rig01" / "calib" / cam, videos / "calib" / label)
    return videos, synth / "board.yaml"


def test_new_campaign_then_run_on_lzw_tiffs(lab_folder, tmp_path, capsys):
    videos, board = lab_folder
    with tifffile.TiffFile(videos / "boil01_left.tif") as tif:
        assert tif.pages[0].compression == tifffile.COMPRESSION.LZW
    camp = tmp_path / "campaign"
    assert main(["new-campaign", "--videos", str(videos), "--out", str(camp), "--fps", "1500"]) == 0
    assert "refinement: off (no --clips)" in capsys.readouterr().out

    text = (camp / "config" / "config.yaml").read_text()
    cfg = yaml.safe_load(text)
    assert cfg["refine"]["enabled"] is False and cfg["prior"]["clips"] is None
    assert cfg["ingest"]["scale"] == "auto"
    # The config says why: each session's native size and what it is fitted at.
    k = auto_scale(160, 160, cfg["ingest"]["fit_size"])
    assert f"boil01: native 160x160 -> fitted {round(160 * k)}x{round(160 * k)}" in text

    # The one edit: the rig's board (the template is the reference rig's).
    shutil.copy(board, camp / "config" / "board.yaml")
    rc = main(["run", "--campaign", str(camp), "--cores", "2"])
    out = capsys.readouterr().out
    assert rc == 0, out
    res = camp / "results"
    assert (res / "campaign" / "metrics.csv").is_file()
    meta = yaml.safe_load((res / "boil01" / "ingest" / "meta.json").read_text())
    assert meta["scale"] == pytest.approx(k)
    bubbles = (res / "boil01" / "fit" / "bubbles.csv").read_text().splitlines()
    assert len(bubbles) > 1


def test_clips_turn_refinement_on_and_are_checked(lab_folder, tmp_path):
    videos, _ = lab_folder
    empty = tmp_path / "no_clips"
    empty.mkdir()
    rc = main(["new-campaign", "--videos", str(videos), "--out", str(tmp_path / "a"), "--fps",
               "1500", "--clips", str(empty)])  # fmt: skip
    assert rc == 2 and not (tmp_path / "a" / "config" / "config.yaml").exists()
    clips = tmp_path / "clips" / "clip000"
    clips.mkdir(parents=True)
    for i in range(3):
        Image.fromarray(np.full((8, 8), 40 * i, np.uint8)).save(clips / f"{i:06d}.png")
    camp = tmp_path / "b"
    rc = main(["new-campaign", "--videos", str(videos), "--out", str(camp), "--fps", "1500",
               "--clips", str(clips.parent)])  # fmt: skip
    assert rc == 0
    cfg = yaml.safe_load((camp / "config" / "config.yaml").read_text())
    assert cfg["refine"]["enabled"] is True
    assert Path(cfg["prior"]["clips"]).resolve() == clips.parent.resolve()
