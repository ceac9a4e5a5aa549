"""Photron MRAW/CIH/CIHX and Phantom CINE readers against files written here.

The references are the arrays the files were written from. 8/16-bit MRAW files are
written with pyMRAW's own ``save_mraw``; 12-bit packed MRAW, CIHX headers and CINE
files are written by the helpers below, byte by byte from the format descriptions
(not with the reader's code). Where pycine is importable (it is not a dependency), its
header parser and 16-bit reader cross-check the CINE files.
"""

from __future__ import annotations

import importlib.util
import struct
from pathlib import Path

import numpy as np
import pytest

from surfphase.labformats import LAB_SUFFIXES, open_lab_video, write_mraw
from surfphase.labformats import write_cine as lab_write_cine

RNG = np.random.default_rng(0)


def frames(n: int, h: int, w: int, bits: int) -> np.ndarray:
    return RNG.integers(0, 2**bits, size=(n, h, w), dtype=np.uint16 if bits > 8 else np.uint8)


# --- writers for what pyMRAW cannot write -----------------------------------------------


def write_cih(
    path: Path,
    n: int,
    h: int,
    w: int,
    color_bit: int,
    effective: int,
    side: str,
    fps,
    color_type: str = "Mono",
    camera: str = "FASTCAM TEST",
):
    lines = [
        f"Camera Type : {camera}",
        "#Camera Information Header",
        f"Record Rate(fps) : {fps}",
        "Shutter Speed(s) : 1/10000",
        f"Total Frame : {n}",
        f"Original Total Frame : {n}",
        "Start Frame : 0",
        f"Image Width : {w}",
        f"Image Height : {h}",
        f"Color Type : {color_type}",
        f"Color Bit : {color_bit}",
        "File Format : MRaw",
        f"EffectiveBit Depth : {effective}",
        f"EffectiveBit Side : {side}",
        "",
        "END",
    ]
    path.write_text("\n".join(lines) + "\n")


def pack12(images: np.ndarray) -> bytes:
    """Photron 12-bit packing: pixels p0, p1 -> bytes p0[11:4], p0[3:0]p1[11:8], p1[7:0]."""
    flat = images.astype(np.uint16).ravel()
    p0, p1 = flat[0::2], flat[1::2]
    out = np.empty((p0.size, 3), dtype=np.uint8)
    out[:, 0] = p0 >> 4
    out[:, 1] = ((p0 & 0xF) << 4) | (p1 >> 8)
    out[:, 2] = p1 & 0xFF
    return out.tobytes()


def write_cihx(
    path: Path,
    n: int,
    h: int,
    w: int,
    bits: int,
    fps: float,
    color_type: str = "Mono",
    device: str = "FASTCAM TEST",
):
    xml = f"""<?xml version="1.0" encoding="UTF-8" ?>
<cih>
<fileInfo><date>2026/11/22</date></fileInfo>
<basicInfo><comment>bubble test</comment></basicInfo>
<deviceInfo><deviceName>{device}</deviceName></deviceInfo>
<recordInfo><recordRate>{fps}</recordRate><shutterSpeed>0.0001</shutterSpeed></recordInfo>
<frameInfo><totalFrame>{n}</totalFrame><recordedFrame>{n}</recordedFrame></frameInfo>
<imageDataInfo>
<resolution><width>{w}</width><height>{h}</height></resolution>
<effectiveBit><depth>{bits}</depth><side>Lower</side></effectiveBit>
<colorInfo><type>{color_type}</type><bit>{bits}</bit></colorInfo>
</imageDataInfo>
<imageFileInfo><fileFormat>MRaw</fileFormat></imageFileInfo>
</cih>
"""
    # Real CIHX files start with a binary block before the XML.
    path.write_bytes(b"\x00\x01\x02\x03" + xml.encode())


SETUP_SIZE = 12432  # size of the SETUP structure in current CINE files


def write_cine(
    path: Path,
    images: np.ndarray,
    bit_count: int,
    real_bpp: int,
    fps: int,
    compression: int = 0,
    cfa: int = 0,
):
    """A minimal uncompressed CINE file: headers, SETUP, offset table, bottom-up images.

    ``images``: (n, H, W) mono or (n, H, W, 3) BGR. Rows are padded to 4 bytes.
    ``compression`` 2 with ``cfa`` 1-4: an uninterpolated colour (Bayer) recording.
    """
    n, h, w = images.shape[:3]
    ch = 3 if images.ndim == 4 else 1
    item = 2 if bit_count in (16, 48) else 1
    stride = (w * ch * item + 3) // 4 * 4
    image_bytes = stride * h
    off_bitmap, off_setup = 44, 44 + 40
    off_offsets = off_setup + SETUP_SIZE
    annotation = 8  # AnnotationSize + ImageSize fields, no annotation text
    first = off_offsets + 8 * n
    offsets = [first + i * (annotation + image_bytes) for i in range(n)]
    head = struct.pack(
        "<2sHHHiIiIIIIII",
        b"CI",
        44,
        compression,  # 0: grey or interpolated colour, 2: uninterpolated (Bayer)
        1,  # version
        0,
        n,
        -n // 2,  # FirstImageNo: recordings often start before the trigger
        n,
        off_bitmap,
        off_setup,
        off_offsets,
        0,
        0,
    )
    bmp = struct.pack("<IiiHHIIiiII", 40, w, h, 1, bit_count, 0, image_bytes, 0, 0, 0, 0)
    setup = bytearray(SETUP_SIZE)
    struct.pack_into("<H", setup, 0, min(fps, 65535))  # FrameRate16
    struct.pack_into("<H", setup, 142, SETUP_SIZE & 0xFFFF)  # Length
    struct.pack_into("<I", setup, 768, fps)  # FrameRate
    struct.pack_into("<I", setup, 808, cfa)  # CFA: 0 grey sensor, 1-4 Bayer patterns
    struct.pack_into("<I", setup, 896, real_bpp)  # RealBPP
    struct.pack_into("<I", setup, 5732, 0)  # BlackLevel
    struct.pack_into("<I", setup, 5736, 2**real_bpp - 1)  # WhiteLevel
    with open(path, "wb") as f:
        f.write(head + bmp + bytes(setup))
        f.write(struct.pack(f"<{n}q", *offsets))
        for img in images:
            dt = "<u2" if item == 2 else "u1"
            rows = img[::-1].astype(dt).reshape(h, w * ch).view(np.uint8)  # bottom-up
            padded = np.zeros((h, stride), dtype=np.uint8)
            padded[:, : rows.shape[1]] = rows
            f.write(struct.pack("<II", annotation, image_bytes))  # AnnotationSize, ImageSize
            f.write(padded.tobytes())


# --- MRAW -------------------------------------------------------------------------------


@pytest.mark.parametrize("bits", [8, 16])
def test_mraw_written_by_pymraw(tmp_path, bits):
    pymraw = pytest.importorskip("pyMRAW")
    data = frames(5, 6, 10, 12 if bits == 16 else 8)
    _, cih = pymraw.save_mraw(
        data, str(tmp_path / "s01_cam0.cih"), bit_depth=bits, info_dict={"Record Rate(fps)": 5000}
    )
    for given in (cih, tmp_path / "s01_cam0.mraw"):
        v = open_lab_video(given)
        assert (v.count, v.shape, v.fps) == (5, (6, 10), 5000.0)
        assert v.bit_depth == (12 if bits == 16 else 8)  # save_mraw declares 12 effective bits
        got = np.stack(list(v.read()))
        assert got.dtype == (np.uint16 if bits == 16 else np.uint8)
        np.testing.assert_array_equal(got, data)
        np.testing.assert_array_equal(np.stack(list(v.read([4, 0]))), data[[4, 0]])


def test_mraw_12bit_packed(tmp_path):
    data = frames(4, 8, 6, 12)
    pymraw = pytest.importorskip("pyMRAW")  # its unpacker agrees with the packing used here
    theirs = pymraw.nb_read_uint12(np.frombuffer(pack12(data), dtype=np.uint8))
    np.testing.assert_array_equal(theirs.reshape(data.shape), data)
    (tmp_path / "rec.mraw").write_bytes(pack12(data))
    write_cih(tmp_path / "rec.cih", 4, 8, 6, 12, 12, "Lower", 20000)
    v = open_lab_video(tmp_path / "rec.cih")
    assert (v.count, v.shape, v.bit_depth, v.fps) == (4, (8, 6), 12, 20000.0)
    np.testing.assert_array_equal(np.stack(list(v.read([2, 3, 0]))), data[[2, 3, 0]])


def test_mraw_16bit_high_side_is_shifted_down(tmp_path):
    data = frames(2, 4, 4, 12)
    (tmp_path / "hi.mraw").write_bytes((data.astype("<u2") << 4).tobytes())
    write_cih(tmp_path / "hi.cih", 2, 4, 4, 16, 12, "Higher", 1000)
    v = open_lab_video(tmp_path / "hi.mraw")
    assert v.bit_depth == 12
    np.testing.assert_array_equal(np.stack(list(v.read())), data)


def test_cihx_header(tmp_path):
    data = frames(3, 5, 4, 8)
    (tmp_path / "x.mraw").write_bytes(data.tobytes())
    write_cihx(tmp_path / "x.cihx", 3, 5, 4, 8, 7500.0)
    v = open_lab_video(tmp_path / "x.cihx")
    assert (v.count, v.shape, v.bit_depth, v.fps) == (3, (5, 4), 8, 7500.0)
    np.testing.assert_array_equal(np.stack(list(v.read())), data)


def test_mraw_errors_name_the_file(tmp_path):
    write_cih(tmp_path / "a.cih", 4, 8, 8, 8, 8, "Lower", 100)
    with pytest.raises(FileNotFoundError, match="a.mraw"):
        open_lab_video(tmp_path / "a.cih")
    (tmp_path / "a.mraw").write_bytes(b"\0" * 100)  # 4 frames of 64 bytes announced
    with pytest.raises(ValueError, match="a.mraw.*4 frames"):
        open_lab_video(tmp_path / "a.cih")
    with pytest.raises(FileNotFoundError, match="b.mraw"):
        open_lab_video(tmp_path / "b.mraw")
    (tmp_path / "a.mraw").write_bytes(b"\0" * 256)
    with pytest.raises(ValueError, match="frame 4 out of range"):
        list(open_lab_video(tmp_path / "a.cih").read([4]))


# --- CINE -------------------------------------------------------------------------------


@pytest.mark.parametrize(("bit_count", "real_bpp", "w"), [(8, 8, 6), (16, 12, 5), (16, 16, 4)])
def test_cine_mono(tmp_path, bit_count, real_bpp, w):
    data = frames(4, 3, w, real_bpp)
    write_cine(tmp_path / "s.cine", data, bit_count, real_bpp, fps=24000)
    v = open_lab_video(tmp_path / "s.cine")
    assert (v.count, v.shape, v.bit_depth, v.fps) == (4, (3, w), real_bpp, 24000.0)
    got = np.stack(list(v.read()))
    assert got.dtype == (np.uint8 if bit_count == 8 else np.uint16)
    np.testing.assert_array_equal(got, data)
    np.testing.assert_array_equal(np.stack(list(v.read([3, 1]))), data[[3, 1]])


def test_cine_colour_to_grey(tmp_path):
    bgr = frames(2, 4, 3 * 3, 8).reshape(2, 4, 3, 3)
    write_cine(tmp_path / "c.cine", bgr, 24, 8, fps=1000)
    got = np.stack(list(open_lab_video(tmp_path / "c.cine").read()))
    ref = np.rint(0.114 * bgr[..., 0] + 0.587 * bgr[..., 1] + 0.299 * bgr[..., 2])
    np.testing.assert_array_equal(got, ref.astype(np.uint8))


def test_cine_cross_checked_with_pycine(tmp_path):
    """pycine (when installed) reads the same header fields and 16-bit frames."""
    pytest.importorskip("pycine.raw")
    from pycine.file import read_header
    from pycine.raw import read_frames

    data = frames(3, 4, 6, 12)
    write_cine(tmp_path / "p.cine", data, 16, 12, fps=3000)
    head = read_header(str(tmp_path / "p.cine"))
    assert head["setup"].FrameRate == 3000 and head["setup"].RealBPP == 12
    assert (head["bitmapinfoheader"].biWidth, head["bitmapinfoheader"].biHeight) == (6, 4)
    gen, _, bpp = read_frames(str(tmp_path / "p.cine"))
    theirs = np.stack(list(gen))
    ours = np.stack(list(open_lab_video(tmp_path / "p.cine").read()))
    assert bpp == 12
    np.testing.assert_array_equal(theirs, data)
    np.testing.assert_array_equal(ours, theirs)


def test_cine_errors(tmp_path):
    (tmp_path / "bad.cine").write_bytes(b"XX" + b"\0" * 100)
    with pytest.raises(ValueError, match="bad.cine.*not a CINE"):
        open_lab_video(tmp_path / "bad.cine")
    with pytest.raises(FileNotFoundError, match="none.cine"):
        open_lab_video(tmp_path / "none.cine")
    data = frames(2, 3, 4, 8)
    write_cine(tmp_path / "t.cine", data, 8, 8, fps=10)
    blob = (tmp_path / "t.cine").read_bytes()
    (tmp_path / "t.cine").write_bytes(blob[:-5])
    with pytest.raises(ValueError, match="t.cine: truncated recording.* image 1 of the 2"):
        open_lab_video(tmp_path / "t.cine")  # found on opening, not at the last frame
    with pytest.raises(ValueError, match="not a lab format"):
        open_lab_video(tmp_path / "x.avi")


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_write_mraw_read_by_pymraw(tmp_path, bits):
    pymraw = pytest.importorskip("pyMRAW")
    data = frames(3, 4, 6, bits)
    cih = write_mraw(tmp_path / "w.cih", data, bits, fps=12500)
    images, info = pymraw.load_video(str(cih))
    np.testing.assert_array_equal(np.asarray(images), data)
    assert info["Record Rate(fps)"] == 12500 and info["Color Bit"] == bits
    v = open_lab_video(cih)
    assert (v.bit_depth, v.fps) == (bits, 12500.0)
    np.testing.assert_array_equal(np.stack(list(v.read())), data)


@pytest.mark.parametrize(("bits", "w"), [(8, 5), (12, 6)])
def test_write_cine(tmp_path, bits, w):
    data = frames(3, 4, w, bits)
    path = lab_write_cine(tmp_path / "w.cine", data, bits, fps=9000)
    v = open_lab_video(path)
    assert (v.count, v.shape, v.bit_depth, v.fps) == (3, (4, w), bits, 9000.0)
    np.testing.assert_array_equal(np.stack(list(v.read())), data)
    if bits > 8 and importlib.util.find_spec("pycine"):
        from pycine.raw import read_frames

        gen, setup, bpp = read_frames(str(path))
        assert (bpp, setup.FrameRate) == (bits, 9000)
        np.testing.assert_array_equal(np.stack(list(gen)), data)


def test_suffixes():
    assert LAB_SUFFIXES == {".cih", ".cihx", ".mraw", ".cine"}


# --- colour (Bayer) sensors ---------------------------------------------------------------

PHASES = {"RGGB": "COLOR_BayerRGGB2RGB", "BGGR": "COLOR_BayerBGGR2RGB"}
PHASES |= {"GRBG": "COLOR_BayerGRBG2RGB", "GBRG": "COLOR_BayerGBRG2RGB"}


def colour_scene(n: int = 2, h: int = 24, w: int = 32) -> np.ndarray:
    """(n, h, w, 3) RGB, 12-bit: flat 8×8 patches of distinct colours, changing per frame."""
    rng = np.random.default_rng(5)
    patches = rng.integers(0, 4096, size=(n, h // 8, w // 8, 3))
    return np.repeat(np.repeat(patches, 8, axis=1), 8, axis=2).astype(np.uint16)


def mosaic(rgb: np.ndarray, phase: str) -> np.ndarray:
    """(..., H, W, 3) RGB → (..., H, W) Bayer mosaic whose 2×2 cell reads ``phase``
    (row-major, as OpenCV's ``COLOR_Bayer<phase>2RGB`` names it)."""
    out = np.empty(rgb.shape[:-1], rgb.dtype)
    for k, letter in enumerate(phase):
        dy, dx = divmod(k, 2)
        out[..., dy::2, dx::2] = rgb[..., dy::2, dx::2, "RGB".index(letter)]
    return out


def patch_interior(h: int, w: int) -> np.ndarray:
    """(h, w) bool: pixels whose 3×3 neighbourhood lies in their own 8×8 patch."""
    y, x = np.mgrid[0:h, 0:w]
    return (y % 8 >= 1) & (y % 8 <= 6) & (x % 8 >= 1) & (x % 8 <= 6)


def check_grey_of_bayer(got: np.ndarray, rgb: np.ndarray, mos: np.ndarray, phase: str):
    """Flat colours come out (R + 2G + B)/4, and agree with OpenCV's own demosaic."""
    import cv2

    inside = patch_interior(*got.shape[1:])
    truth = (rgb[..., 0] + 2.0 * rgb[..., 1] + rgb[..., 2]) / 4
    assert np.abs(got - truth)[:, inside].max() <= 0.5
    for g, m in zip(got, mos, strict=True):
        demosaiced = cv2.cvtColor(m, getattr(cv2, PHASES[phase])).astype(float)
        cv_grey = (demosaiced[..., 0] + 2 * demosaiced[..., 1] + demosaiced[..., 2]) / 4
        assert np.abs(g - cv_grey)[inside].max() <= 1.0
    # Read as grey without conversion, the mosaic is a checkerboard, far from this.
    assert np.abs(mos.astype(float) - truth)[:, inside].max() > 500


@pytest.mark.parametrize("phase", sorted(PHASES))
def test_cine_bayer_is_converted_to_grey(tmp_path, phase):
    rgb = colour_scene()
    mos = mosaic(rgb, phase)
    write_cine(tmp_path / "c.cine", mos, 16, 12, fps=5000, compression=2, cfa=3)
    v = open_lab_video(tmp_path / "c.cine")
    assert (v.shape, v.bit_depth) == ((24, 32), 12) and v.header["colour"].startswith("bayer")
    got = np.stack(list(v.read()))
    assert got.dtype == np.uint16
    check_grey_of_bayer(got, rgb, mos, phase)


@pytest.mark.parametrize(
    ("header", "colour", "device"),
    [
        ("cih", "Color", "FASTCAM TEST"),
        ("cihx", "Raw", "FASTCAM Mini AX200 type 900K-C-16GB"),
    ],
)
@pytest.mark.parametrize("phase", ["RGGB", "GBRG"])
def test_mraw_bayer_is_converted_to_grey(tmp_path, header, colour, device, phase):
    rgb = colour_scene()
    mos = mosaic(rgb, phase)
    (tmp_path / "c.mraw").write_bytes(pack12(mos))
    if header == "cih":
        write_cih(tmp_path / "c.cih", 2, 24, 32, 12, 12, "Lower", 5000, colour, device)
    else:
        write_cihx(tmp_path / "c.cihx", 2, 24, 32, 12, 5000.0, colour, device)
    v = open_lab_video(tmp_path / f"c.{header}")
    assert v.header["colour"].startswith("bayer")
    check_grey_of_bayer(np.stack(list(v.read())), rgb, mos, phase)


def test_mono_raw_is_not_converted_and_unknown_sensor_warns(tmp_path):
    import warnings

    data = frames(2, 8, 8, 12)
    (tmp_path / "m.mraw").write_bytes(pack12(data))
    # Photron's "Raw" from a monochrome model (as in real files): read as is, no warning.
    write_cihx(tmp_path / "m.cihx", 2, 8, 8, 12, 100.0, "Raw", "FASTCAM Nova S16 type 1100K-M-64GB")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        v = open_lab_video(tmp_path / "m.cihx")
    np.testing.assert_array_equal(np.stack(list(v.read())), data)
    (tmp_path / "m.cihx").unlink()
    write_cih(tmp_path / "m.cih", 2, 8, 8, 12, 12, "Lower", 100, "Raw", "FASTCAM ?")
    with pytest.warns(UserWarning, match=r"m\.cih: .*monochrome or colour"):
        v = open_lab_video(tmp_path / "m.cih")
    np.testing.assert_array_equal(np.stack(list(v.read())), data)
    # A colour CFA with 1-channel images said to be interpolated: grey, with a warning.
    write_cine(tmp_path / "c.cine", data, 16, 12, fps=100, compression=0, cfa=2)
    with pytest.warns(UserWarning, match=r"c\.cine: .*colour sensor"):
        v = open_lab_video(tmp_path / "c.cine")
    np.testing.assert_array_equal(np.stack(list(v.read())), data)
