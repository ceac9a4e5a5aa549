"""Ingest: the same session from MP4, PNG folder and 16-bit TIFF; geometry; bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import tifffile

from surfphase.cameras import load_cameras, look_at, save_cameras
from surfphase.cli import main
from surfphase.folders.ingest import read_ingest
from surfphase.ingest import ingest_session, output_camera, parse_frames

W = H = 64


def _camera(name: str, size: int = W):
    """A wide, strongly distorted camera (~7 px of distortion in the corners at 64 px)."""
    f = 60.0 * size / 64
    return look_at(
        name,
        eye=(0.0, 0.0, 0.1),
        target=(0.0, 0.0, 0.0),
        fx=f,
        width=size,
        height=size,
        cx=(size - 1) / 2 + 1.3 * size / 64,
        cy=(size - 1) / 2 - 0.8 * size / 64,
        dist=np.array([-0.3, 0.1, 0.001, -0.001, 0.0]),
    )


def _sequence(n: int = 8, seed: int = 0) -> np.ndarray:
    """(n, H, W) uint8 frames of two smooth blobs moving across a textured background."""
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    rng = np.random.default_rng(seed)
    bg = cv2.GaussianBlur(rng.uniform(40, 90, (H, W)), (0, 0), 2.0)
    frames = []
    for k in range(n):
        f = bg.copy()
        for cx, cy, vx, vy in ((12, 20, 4, 1), (50, 44, -3, -2)):
            f += 140 * np.exp(-((xx - cx - vx * k) ** 2 + (yy - cy - vy * k) ** 2) / (2 * 5.0**2))
        frames.append(np.clip(np.round(f), 0, 255).astype(np.uint8))
    return np.stack(frames)


def _write_sources(root, name: str, frames: np.ndarray) -> dict:
    """The same frames as an MP4, a PNG folder and a 16-bit multi-page TIFF."""
    mp4 = root / f"{name}.mp4"
    vw = cv2.VideoWriter(str(mp4), cv2.VideoWriter_fourcc(*"mp4v"), 100.0, (W, H))
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    png = root / f"{name}_png"
    png.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(png / f"frame_{k:05d}.png"), f)
    tif = root / f"{name}.tif"
    tifffile.imwrite(tif, frames.astype(np.uint16) * 257)
    return {"mp4": mp4, "png": png, "tif": tif}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("session")
    cams = {"cam0": _camera("cam0"), "cam1": _camera("cam1")}
    src = {
        "cam0": _write_sources(root, "cam0", _sequence(seed=0)),
        "cam1": _write_sources(root, "cam1", _sequence(seed=1)),
    }
    return root, cams, src


def _ingest(root, cams, src, kind, **kw):
    out = root / f"out_{kind}_{kw.get('frames')}_{kw.get('scale', 1.0)}_{kw.get('crop')}"
    meta = ingest_session("s01", cams, {n: src[n][kind] for n in cams}, fps=100.0, out=out, **kw)
    return out, meta


def test_parse_frames():
    np.testing.assert_array_equal(parse_frames("1:7:2", 8), [1, 3, 5])
    np.testing.assert_array_equal(parse_frames(":3", 8), [0, 1, 2])
    np.testing.assert_array_equal(parse_frames("5:", 8), [5, 6, 7])
    np.testing.assert_array_equal(parse_frames(None, 3), [0, 1, 2])
    with pytest.raises(ValueError, match="beyond the video"):
        parse_frames("0:9", 8, source="x.mp4")
    for bad in ("3", "a:b", "4:2", "0:4:0", "-1:3"):
        with pytest.raises(ValueError):
            parse_frames(bad, 8)


def test_same_frames_from_mp4_png_and_tiff(session):
    root, cams, src = session
    kw = {"frames": "1:7:2", "scale": 0.5, "crop": (4, 6, 56, 52)}
    outs = {k: _ingest(root, cams, src, k, **kw) for k in ("mp4", "png", "tif")}
    for cam in cams:
        png = read_ingest(outs["png"][0]).stacks[cam]
        tif = read_ingest(outs["tif"][0]).stacks[cam]
        mp4 = read_ingest(outs["mp4"][0]).stacks[cam]
        assert isinstance(png, np.memmap) and png.dtype == np.float32
        assert png.shape == (3, 26, 28)
        # 8-bit PNG and 16-bit TIFF (×257) normalise to the very same floats.
        np.testing.assert_array_equal(png, tif)
        assert 0.0 <= png.min() and png.max() <= 1.0
        # MP4 differs only by codec loss.
        assert np.abs(mp4 - png).mean() < 0.02
        assert np.abs(mp4 - png).max() < 0.1
    meta = outs["tif"][1]
    assert meta["frame_indices"] == [1, 3, 5]
    assert meta["cameras"]["cam0"]["source_bit_depth"] == 16
    assert outs["png"][1]["cameras"]["cam0"]["source_bit_depth"] == 8
    assert meta["cameras"]["cam1"]["source_kind"] == "tiff"
    assert meta["cameras"]["cam1"]["size"] == [28, 26]
    assert meta["cameras"]["cam1"]["count"] == 3
    on_disk = json.loads((outs["tif"][0] / "meta.json").read_text())
    assert on_disk == json.loads(json.dumps(meta))
    # The written cameras are the calibrated ones undistorted, cropped, then scaled.
    got = load_cameras(outs["tif"][0] / "cameras.json")
    for cam in cams:
        expect = cams[cam].undistorted().cropped(4, 6, 56, 52).scaled(0.5)
        np.testing.assert_allclose(got[cam].K, expect.K, atol=1e-12)
        assert (got[cam].width, got[cam].height) == (28, 26)
        assert not np.any(got[cam].dist)
        np.testing.assert_allclose(got[cam].R, cams[cam].R)


def test_undistortion_puts_points_where_the_pinhole_sees_them(tmp_path):
    """Dots drawn at distorted projections land at the output camera's pinhole pixels."""
    size = 128
    cam = _camera("cam0", size)
    rng = np.random.default_rng(3)
    uv_ideal = rng.uniform(20, size - 20, (6, 2))
    X = cam.center + cam.pixel_rays(uv_ideal, distorted=False) * 0.1
    uv_raw = cam.project(X, distort=True)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    img = np.zeros((size, size))
    for u, v in uv_raw:
        img += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 2.0**2))
    frame = np.round(img / img.max() * 60000).astype(np.uint16)
    tifffile.imwrite(tmp_path / "dots.tif", np.stack([frame, frame]))
    crop = (10, 4, 108, 112)
    ingest_session(
        "dots",
        {"cam0": cam},
        {"cam0": tmp_path / "dots.tif"},
        50.0,
        None,
        0.5,
        crop,
        tmp_path / "o",
    )
    out_cam = load_cameras(tmp_path / "o" / "cameras.json")["cam0"]
    np.testing.assert_allclose(out_cam.K, cam.undistorted().cropped(*crop).scaled(0.5).K)
    np.testing.assert_allclose(out_cam.K, output_camera(cam, crop, (54, 56)).K)
    stack = read_ingest(tmp_path / "o").stacks["cam0"]
    expect = out_cam.project(X, distort=False)
    yy, xx = np.mgrid[0 : stack.shape[1], 0 : stack.shape[2]].astype(float)
    for u, v in expect:
        win = (np.abs(xx - u) < 4) & (np.abs(yy - v) < 4)
        w = stack[0] * win
        centroid = np.array([(w * xx).sum(), (w * yy).sum()]) / w.sum()
        assert np.linalg.norm(centroid - (u, v)) < 0.15


def test_missing_video_names_session_camera_and_path(session, tmp_path):
    _, cams, src = session
    missing = tmp_path / "gone.mp4"
    with pytest.raises(FileNotFoundError) as e:
        ingest_session(
            "s07", cams, {"cam0": src["cam0"]["png"], "cam1": missing}, 100.0, out=tmp_path / "o"
        )
    msg = str(e.value)
    assert "s07" in msg and "cam1" in msg and str(missing) in msg


def test_different_frame_counts(session, tmp_path):
    _, cams, src = session
    short = tmp_path / "short.tif"
    tifffile.imwrite(short, _sequence(5).astype(np.uint16) * 257)
    with pytest.raises(ValueError) as e:
        ingest_session(
            "s08", cams, {"cam0": src["cam0"]["png"], "cam1": short}, 100.0, out=tmp_path / "o"
        )
    msg = str(e.value)
    assert "s08" in msg and str(src["cam0"]["png"]) in msg and str(short) in msg
    assert "8 frames" in msg and "has 5" in msg
    assert not (tmp_path / "o" / "meta.json").exists()


def test_frame_range_beyond_video_and_bad_crop(session, tmp_path):
    _, cams, src = session
    videos = {n: src[n]["tif"] for n in cams}
    with pytest.raises(ValueError, match=r"session s09: .*beyond the video \(8 frames\)"):
        ingest_session("s09", cams, videos, 100.0, frames="2:12", out=tmp_path / "o")
    with pytest.raises(ValueError, match="session s09: cam0: crop"):
        ingest_session("s09", cams, videos, 100.0, crop=(40, 0, 40, 10), out=tmp_path / "o")
    wrong = {"cam0": cams["cam0"].scaled(2.0), "cam1": cams["cam1"]}
    with pytest.raises(ValueError, match="calibrated at 128×128"):
        ingest_session("s09", wrong, videos, 100.0, out=tmp_path / "o")


def test_cli(session, tmp_path):
    _, cams, src = session
    save_cameras(tmp_path / "cameras.json", cams)
    args = ["ingest", "--session", "s10", "--cameras", str(tmp_path / "cameras.json")]
    args += ["--cam", f"cam0={src['cam0']['png']}", "--cam", f"cam1={src['cam1']['mp4']}"]
    args += ["--fps", "100", "--frames", "0:8:4", "--scale", "0.25", "--out", str(tmp_path / "o")]
    assert main(args) == 0
    meta = json.loads((tmp_path / "o" / "meta.json").read_text())
    assert meta["frame_indices"] == [0, 4] and meta["fps"] == 100.0
    assert read_ingest(tmp_path / "o").stacks["cam1"].shape == (2, 16, 16)
    bad = args[:5] + ["--cam", "cam0=/nonexistent/x.mp4", "--cam", f"cam1={src['cam1']['mp4']}"]
    bad += ["--fps", "100", "--out", str(tmp_path / "o2")]
    assert main(bad) == 2


def test_cli_missing_calibration_names_session_and_rig(session, tmp_path, capsys):
    _, _, src = session
    sheet = tmp_path / "rigs.tsv"
    sheet.write_text("rig\tboard\tcam0\tcam1\nrig01\tboard.yaml\tc0\tc1\n")
    base = ["ingest", "--session", "s11", "--rigs-sheet", str(sheet)]
    base += ["--cameras", str(tmp_path / "calib" / "cameras.json")]
    base += ["--cam", f"cam0={src['cam0']['png']}", "--fps", "100", "--out", str(tmp_path / "o")]
    assert main(base + ["--rig", "rig09"]) == 2
    assert "session s11: rig rig09 is not a row of" in capsys.readouterr().err
    assert main(base + ["--rig", "rig01"]) == 2
    err = capsys.readouterr().err
    assert "session s11: calibration of rig rig01 not found" in err and "cameras.json" in err


def _cut(path, keep: float):
    """A copy of ``path`` holding only its first ``keep`` fraction of bytes (as an
    interrupted copy leaves it), beside it with the same suffix."""
    data = path.read_bytes()
    out = path.with_name(f"{path.stem}_cut{path.suffix}")
    out.write_bytes(data[: int(len(data) * keep)])
    return out


def test_lzw_16bit_multipage_tiff_ingests_like_uncompressed(session, tmp_path):
    _, cams, src = session
    lzw = {}
    for n in cams:
        frames16 = tifffile.imread(src[n]["tif"])
        lzw[n] = tmp_path / f"{n}_lzw.tif"
        tifffile.imwrite(lzw[n], frames16, compression="lzw")  # LZW needs imagecodecs
        with tifffile.TiffFile(lzw[n]) as tif:
            assert tif.pages[0].compression == tifffile.COMPRESSION.LZW
            assert len(tif.pages) == 8 and tif.pages[0].dtype == np.uint16
    kw = {"frames": "1:7:2", "scale": 0.5}
    ingest_session("s13", cams, lzw, 100.0, out=tmp_path / "lzw", **kw)
    ingest_session("s13", cams, {n: src[n]["tif"] for n in cams}, 100.0, out=tmp_path / "raw", **kw)
    for n in cams:
        np.testing.assert_array_equal(
            read_ingest(tmp_path / "lzw").stacks[n], read_ingest(tmp_path / "raw").stacks[n]
        )


@pytest.mark.parametrize("compression", [None, "lzw"])
@pytest.mark.parametrize("both", [True, False])
def test_truncated_tiff_is_a_clear_error(session, tmp_path, compression, both):
    """A multi-page TIFF cut short used to read as one frame (and the run went on)."""
    _, cams, src = session
    videos = {}
    for n in cams:
        full = tmp_path / f"{n}.tif"
        tifffile.imwrite(full, tifffile.imread(src[n]["tif"]), compression=compression)
        videos[n] = _cut(full, 0.6) if (both or n == "cam1") else full
    with pytest.raises(ValueError) as e:
        ingest_session("s14", cams, videos, 100.0, out=tmp_path / "o")
    msg = str(e.value)
    assert "session s14" in msg and "truncated" in msg
    assert "camera cam0" in msg if both else "camera cam1" in msg
    assert str(videos["cam0"] if both else videos["cam1"]) in msg
    assert not (tmp_path / "o" / "meta.json").exists()


def test_tiff_shorter_than_the_other_camera_says_it_may_be_truncated(session, tmp_path):
    """A file cut exactly at a page boundary looks whole: the count gives it away."""
    _, cams, src = session
    short = tmp_path / "short.tif"
    tifffile.imwrite(short, tifffile.imread(src["cam1"]["tif"])[:5], metadata=None)
    with pytest.raises(ValueError) as e:
        ingest_session(
            "s15", cams, {"cam0": src["cam0"]["tif"], "cam1": short}, 100.0, out=tmp_path / "o"
        )
    msg = str(e.value)
    assert "session s15" in msg and f"camera cam1 {short} may be truncated" in msg


@pytest.mark.parametrize("fmt", ["mraw12", "mraw16", "cine"])
def test_truncated_lab_recording_is_a_clear_error(session, tmp_path, fmt):
    from surfphase.labformats import write_cine, write_mraw

    _, cams, _ = session
    videos = {}
    for k, n in enumerate(cams):
        frames = _sequence(seed=k).astype(np.uint16) * 16  # 12 bits
        if fmt == "cine":
            videos[n] = write_cine(tmp_path / f"{n}.cine", frames, 12, 100)
        else:
            videos[n] = write_mraw(tmp_path / f"{n}.cih", frames, int(fmt[4:]), 100.0)
    data = videos["cam1"] if fmt == "cine" else videos["cam1"].with_suffix(".mraw")
    data.write_bytes(data.read_bytes()[: int(data.stat().st_size * 0.7)])
    with pytest.raises(ValueError) as e:
        ingest_session("s16", cams, videos, 100.0, out=tmp_path / "o")
    msg = str(e.value)
    assert "session s16" in msg and "camera cam1" in msg and str(data) in msg
    assert "truncated" in msg


def test_native_frames_are_the_unscaled_ingest(session, tmp_path):
    # ingest: native_masks keeps the frames before downscaling for the mask stage; they
    # must be what an ingest at scale 1 writes (to uint16 quantisation), with its cameras.
    root, cams, src = session
    kw = {"frames": "0:5", "crop": (4, 6, 56, 52)}
    full, _ = _ingest(root, cams, src, "tif", scale=1.0, **kw)
    out = tmp_path / "both"
    meta = ingest_session("s01", cams, {n: src[n]["tif"] for n in cams}, 100.0, scale=0.5,
                          out=out, native=True, **kw)  # fmt: skip
    assert meta["native"] == "native"
    got, ref = load_cameras(out / "native" / "cameras.json"), load_cameras(full / "cameras.json")
    for cam in cams:
        nat = np.load(out / "native" / f"{cam}.npy")
        assert nat.dtype == np.uint16 and nat.shape == (5, 52, 56)
        np.testing.assert_allclose(
            nat / 65535.0, read_ingest(full).stacks[cam], atol=0.5 / 65535 + 1e-7
        )
        np.testing.assert_allclose(got[cam].K, ref[cam].K, atol=1e-12)
        assert read_ingest(out).stacks[cam].shape == (5, 26, 28)
    native_meta = json.loads((out / "native" / "meta.json").read_text())
    assert native_meta["cameras"] == list(cams) and native_meta["frame_indices"] == list(range(5))
    # At scale 1 there is nothing to keep: no native folder, and a stale one goes.
    again = ingest_session("s01", cams, {n: src[n]["tif"] for n in cams}, 100.0, scale=1.0,
                           out=out, native=True, **kw)  # fmt: skip
    assert again["native"] is None and not (out / "native").exists()
