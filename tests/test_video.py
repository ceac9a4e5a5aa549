"""Frame readers: image folders, multi-page TIFF and video files, 8 and 16 bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from surfphase.video import open_video


def _frames(n: int = 6, h: int = 32, w: int = 48) -> np.ndarray:
    """(n, h, w) uint8 frames with a bright square moving right, all distinct."""
    rng = np.random.default_rng(0)
    f = rng.integers(20, 60, size=(n, h, w)).astype(np.uint8)
    for k in range(n):
        f[k, 8:20, 4 + 4 * k : 16 + 4 * k] = 200 + k
    return f


def test_folder_8bit_png_sorted_by_name(tmp_path):
    frames = _frames()
    for k, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"img_{k:04d}.png"), f)
    src = open_video(tmp_path)
    assert (src.kind, src.count, src.shape, src.bit_depth) == ("folder", 6, (32, 48), 8)
    got = list(src.read([5, 0, 2]))
    np.testing.assert_array_equal(np.stack(got), frames[[5, 0, 2]])


def test_folder_16bit_and_colour_to_gray(tmp_path):
    frames16 = _frames().astype(np.uint16) * 257
    for k, f in enumerate(frames16):
        cv2.imwrite(str(tmp_path / f"{k:03d}.png"), cv2.merge([f, f, f]))
    src = open_video(tmp_path)
    assert src.bit_depth == 16
    got = np.stack(list(src.read(range(src.count))))
    assert got.dtype == np.uint16
    # Equal channels: OpenCV's luma weights sum to one, so grey equals the channel.
    assert np.abs(got.astype(int) - frames16.astype(int)).max() <= 1


def test_multipage_tiff_16bit_and_rgb(tmp_path):
    frames16 = _frames().astype(np.uint16) * 257
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, frames16)
    src = open_video(path)
    assert (src.kind, src.count, src.shape, src.bit_depth) == ("tiff", 6, (32, 48), 16)
    np.testing.assert_array_equal(np.stack(list(src.read(range(6)))), frames16)

    rgb = np.zeros((3, 32, 48, 3), np.uint8)
    rgb[..., 0] = 255  # pure red: luma 0.299
    tifffile.imwrite(tmp_path / "rgb.tif", rgb, photometric="rgb")
    red = next(open_video(tmp_path / "rgb.tif").read([1]))
    assert red.shape == (32, 48) and abs(int(red[0, 0]) - 76) <= 1


def test_video_file_mp4(tmp_path):
    frames = _frames(8, 64, 64)
    path = tmp_path / "clip.mp4"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (64, 64))
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    src = open_video(path)
    assert (src.kind, src.count, src.shape, src.bit_depth) == ("video", 8, (64, 64), 8)
    assert src.fps == pytest.approx(25.0)
    seq = np.stack(list(src.read([1, 3, 3, 7]))).astype(float)
    unordered = np.stack(list(src.read([7, 1]))).astype(float)
    np.testing.assert_array_equal(unordered, seq[[3, 0]])
    # Lossy codec: close to the originals, and each frame closest to its own original.
    assert np.abs(seq - frames[[1, 3, 3, 7]]).mean() < 4.0
    err = np.abs(seq[:, None] - frames[None].astype(float)).mean(axis=(2, 3))
    assert list(err.argmin(axis=1)) == [1, 3, 3, 7]


def test_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.mp4"):
        open_video(tmp_path / "nothere.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no images"):
        open_video(tmp_path / "empty")
    tifffile.imwrite(tmp_path / "s.tif", np.zeros((2, 4, 4), np.uint8))
    src = open_video(tmp_path / "s.tif")
    with pytest.raises(ValueError, match="frame 2 is outside"):
        list(src.read([0, 2]))
    (tmp_path / "bad.mp4").write_bytes(b"not a video")
    with pytest.raises(ValueError, match="bad.mp4"):
        open_video(tmp_path / "bad.mp4")


def test_lzw_multipage_tiff_16bit_equals_tifffile(tmp_path):
    rng = np.random.default_rng(1)
    frames16 = rng.integers(0, 65536, size=(7, 30, 41), dtype=np.uint16)
    path = tmp_path / "lzw.tif"
    tifffile.imwrite(path, frames16, compression="lzw", predictor=True)
    ref = tifffile.imread(path)  # tifffile's own decoder (imagecodecs)
    np.testing.assert_array_equal(ref, frames16)
    src = open_video(path)
    assert (src.kind, src.count, src.shape, src.bit_depth) == ("tiff", 7, (30, 41), 16)
    np.testing.assert_array_equal(np.stack(list(src.read([6, 0, 3]))), ref[[6, 0, 3]])


@pytest.mark.parametrize("kw", [{}, {"compression": "lzw"}, {"imagej": True}, {"metadata": None}])
@pytest.mark.parametrize("keep", [0.3, 0.6, 0.97])
def test_truncated_multipage_tiff_is_refused(tmp_path, kw, keep):
    frames16 = _frames(10).astype(np.uint16) * 257
    full = tmp_path / "full.tif"
    tifffile.imwrite(full, frames16, **kw)
    assert open_video(full).count == 10
    cut = tmp_path / "cut.tif"
    cut.write_bytes(full.read_bytes()[: int(full.stat().st_size * keep)])
    with pytest.raises(ValueError, match=r"cut\.tif: truncated TIFF"):
        open_video(cut)
