"""Readers for high-speed camera formats: Photron MRAW (+ CIH/CIHX) and Phantom CINE.

:func:`open_lab_video` returns a reader with the same interface as
``surfphase.video.open_video``: ``.count`` (frames), ``.shape`` (H, W) in pixels,
``.bit_depth`` (significant bits per pixel: 8, 10, 12, 14 or 16), ``.fps`` (frames per
second from the header, or ``None``) and ``read(indices)``, an iterator of 2D arrays
(``uint8`` when ``bit_depth <= 8``, else ``uint16`` holding values in
``[0, 2**bit_depth)``), one per index, in the order asked. Frames are read one at a
time from a memory map, so a long recording is never loaded whole.

Photron: a recording is a ``.cih`` (text) or ``.cihx`` (XML) header plus a ``.mraw`` of
the same name holding the frames back to back, row-major, top row first, 8-bit,
16-bit, or 12-bit packed (two pixels in three bytes, big-endian bit order). The header
is parsed with pyMRAW; frames are unpacked here, one at a time. Any of the three paths
may be given.

Phantom: a ``.cine`` file is a CINEFILEHEADER (44 bytes), a BITMAPINFOHEADER (40 bytes),
a SETUP block (frame rate, real bit depth), a table of 64-bit image offsets, and per
image an annotation block followed by the pixels, bottom row first (a DIB), rows padded
to 4 bytes. Uncompressed monochrome (8 or 16 bit), interpolated colour (24/48 bit,
converted to grey) and uninterpolated colour (a Bayer mosaic, 8 or 16 bit: header
``Compression`` 2 with a SETUP ``CFA`` code) files are read; packed and compressed files
raise ``ValueError`` (save them from the camera software as 16-bit).

Colour sensors: a Bayer mosaic is converted to grey by :func:`bayer_to_grey`, the same
for any of the four 2×2 phases, so the phase need not be known: grey = (R + 2G + B)/4.
Photron headers say ``Color Type`` (``.cih``) or ``colorInfo/type`` (``.cihx``):
``Mono``; ``Color`` (a colour sensor's mosaic); ``Raw`` (raw sensor data, colour or not:
told apart by the camera model, ``...K-C`` colour, ``...K-M`` monochrome). A header that
does not say is read as monochrome with a warning naming the file. Phantom: SETUP ``CFA``
(0 grey sensor, 1-4 a Bayer pattern) with the file header's ``Compression``. pycine is not used: it reads 16-bit files only and
its package requires ``opencv-python``, which clashes with the project's
``opencv-contrib-python-headless``. The layout follows Vision Research's file format
description.
"""

from __future__ import annotations

import re
import shutil
import struct
import tempfile
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

LAB_SUFFIXES = {".cih", ".cihx", ".mraw", ".cine"}

# CINE layout (byte offsets, little-endian).
_CINE_HEADER = struct.Struct("<2sHHHiIiIIII8s")  # CINEFILEHEADER, 44 bytes
_BITMAP_HEADER = struct.Struct("<IiiHHIIiiII")  # BITMAPINFOHEADER, 40 bytes
_SETUP_FRAMERATE16 = 0  # WORD: frame rate, older files
_SETUP_LENGTH = 142  # WORD: size of the SETUP block in this file
_SETUP_FRAMERATE = 768  # UINT: frame rate, fps
_SETUP_CFA = 808  # UINT: colour filter array, low byte 0 grey, 1-4 a Bayer pattern
_SETUP_REALBPP = 896  # UINT: significant bits per pixel (8..16)
_SETUP_WHITELEVEL = 5736  # UINT: the value of full white
_SETUP_SIZE = 12432  # size of the SETUP block in current files


@dataclass
class LabVideo:
    """A high-speed recording opened by :func:`open_lab_video` (frames not yet read).

    ``shape`` is (height, width) in pixels; ``fps`` in frames per second (``None`` when
    the header has none); ``bit_depth`` the significant bits per pixel.
    """

    path: Path
    count: int
    shape: tuple[int, int]
    bit_depth: int
    fps: float | None
    kind: str  # "mraw" or "cine" (as VideoSource.kind)
    header: dict = field(default_factory=dict, repr=False)
    _frame: object = field(default=None, repr=False)

    def read(self, indices: Iterable[int] | None = None) -> Iterator[np.ndarray]:
        """Yield the frames at ``indices`` (all when ``None``) as 2D arrays (H, W)."""
        idx = range(self.count) if indices is None else indices
        for i in idx:
            i = int(i)
            if not 0 <= i < self.count:
                raise ValueError(f"{self.path}: frame {i} out of range (0..{self.count - 1})")
            yield self._frame(i)


def open_lab_video(path: str | Path) -> LabVideo:
    """Open a Photron (``.cih``, ``.cihx``, ``.mraw``) or Phantom (``.cine``) recording.

    Raises FileNotFoundError when the file (or the MRAW's header/data partner) is
    missing and ValueError, naming the file, when it is not a readable recording.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LAB_SUFFIXES:
        raise ValueError(f"{path}: not a lab format ({', '.join(sorted(LAB_SUFFIXES))})")
    if suffix == ".cine":
        return _open_cine(path)
    return _open_mraw(path)


def lab_frame_rate(path: str | Path) -> float | None:
    """The frame rate (fps) written in a lab recording's header, or ``None``."""
    return open_lab_video(path).fps


# --- Photron MRAW -----------------------------------------------------------------------


def _mraw_pair(path: Path) -> tuple[Path, Path]:
    """(header, data) paths of a Photron recording given any one of them."""
    if path.suffix.lower() == ".mraw":
        for sfx in (".cihx", ".cih", ".CIHX", ".CIH"):
            head = path.with_suffix(sfx)
            if head.is_file():
                return head, path
        if not path.is_file():
            raise FileNotFoundError(f"{path}: file not found")
        raise FileNotFoundError(f"{path}: no .cih or .cihx header beside it")
    data = path.with_suffix(".mraw")
    if not data.is_file() and path.with_suffix(".MRAW").is_file():
        data = path.with_suffix(".MRAW")
    return path, data


def _read_cih(head: Path) -> dict:
    import pyMRAW  # imported here: it compiles its 12-bit unpacker (numba) on import

    try:
        if head.suffix in (".cih", ".cihx"):
            return pyMRAW.get_cih(str(head))
        # pyMRAW dispatches on the exact, lower-case suffix: read an upper-case one via a copy.
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / ("header" + head.suffix.lower())
            shutil.copyfile(head, copy)
            return pyMRAW.get_cih(str(copy))
    except Exception as e:  # a malformed header fails in many ways (KeyError, ExpatError...)
        raise ValueError(f"{head}: not a readable Photron header ({e!r})") from e


def unpack_uint12(packed: np.ndarray) -> np.ndarray:
    """Photron 12-bit packing → uint16: bytes (a, b, c) hold pixels ``a<<4 | b>>4`` and
    ``(b & 15)<<8 | c``. ``packed``: 1D uint8 of length 3k; returns 2k pixels.

    (numpy rather than pyMRAW's numba kernel: 2-3x faster per frame on 2 shared cores.)
    """
    t = packed.reshape(-1, 3).astype(np.uint16)
    out = np.empty((t.shape[0], 2), dtype=np.uint16)
    out[:, 0] = (t[:, 0] << 4) | (t[:, 1] >> 4)
    out[:, 1] = ((t[:, 1] & 0xF) << 8) | t[:, 2]
    return out.reshape(-1)


def bayer_to_grey(mosaic: np.ndarray) -> np.ndarray:
    """(H, W) Bayer mosaic (uint8/uint16, any of the RGGB/BGGR/GRBG/GBRG phases) →
    (H, W) grey of the same dtype and range.

    The 3×3 binomial filter ``[1 2 1]ᵀ[1 2 1] / 16`` (edges mirrored, which keeps the
    mosaic's parity): at every pixel it weighs the pixel's own colour ×4, its 4
    diagonal neighbours (the same colour, or the opposite of red/blue) ×1 and its 4 side
    neighbours ×2, which for every phase sums to (R + 2G + B)/4 of the 2×2 cell. A flat
    colour comes out exactly (R + 2G + B)/4; detail is blurred by [1 2 1]/4 per axis,
    the resolution a demosaic recovers.
    """
    import cv2

    if mosaic.ndim != 2 or min(mosaic.shape) < 2:
        raise ValueError(f"Bayer mosaic must be 2D, at least 2×2, not {mosaic.shape}")
    k = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0]).astype(np.float32) / 16
    grey = cv2.filter2D(mosaic.astype(np.float32), -1, k, borderType=cv2.BORDER_REFLECT_101)
    return np.rint(grey).astype(mosaic.dtype)


def _cihx_fields(head: Path) -> dict[str, str | None]:
    """``colorInfo/type`` and ``deviceInfo/deviceName`` of a CIHX header (pyMRAW's
    header parse keeps neither)."""
    text = head.read_bytes().decode("utf-8", errors="ignore")
    a, b = text.find("<cih>"), text.rfind("</cih>")
    out: dict[str, str | None] = {"type": None, "device": None}
    if a < 0 or b < 0:
        return out
    try:
        root = ET.fromstring(text[a : b + len("</cih>")])
    except ET.ParseError:
        return out
    out["type"] = root.findtext("imageDataInfo/colorInfo/type")
    out["device"] = root.findtext("deviceInfo/deviceName")
    return out


def photron_colour(head: Path, cih: dict) -> tuple[str, str]:
    """(``"mono"``, ``"bayer"`` or ``"unknown"``, the header's words for it) of a Photron
    recording; see the module docstring for the rules."""
    if head.suffix.lower() == ".cihx":
        f = _cihx_fields(head)
        ctype, device = f["type"], f["device"]
    else:
        ctype, device = cih.get("Color Type"), cih.get("Camera Type")
    words = f"colour type {ctype!r}, camera {device!r}"
    kind = str(ctype or "").strip().lower()
    if kind == "mono":
        return "mono", words
    if kind in ("color", "colour", "bayer"):
        return "bayer", words
    if kind == "raw":
        model = re.search(r"\dK-([CM])\b", str(device or ""), re.IGNORECASE)
        if model:
            return ("bayer" if model.group(1).upper() == "C" else "mono"), words
    return "unknown", words


def _open_mraw(path: Path) -> LabVideo:
    head, data = _mraw_pair(path)
    for p in (head, data):
        if not p.is_file():
            raise FileNotFoundError(
                f"{p}: file not found (Photron recordings need .cih/.cihx and .mraw)"
            )
    cih = _read_cih(head)

    def need(key):
        if key not in cih:
            raise ValueError(f"{head}: Photron header has no '{key}'")
        return cih[key]

    count = int(need("Total Frame"))
    h, w = int(need("Image Height")), int(need("Image Width"))
    bits = int(need("Color Bit"))
    fmt = str(cih.get("File Format", "MRaw")).lower()
    if fmt != "mraw":
        raise ValueError(f"{head}: file format '{fmt}' is not MRAW")
    if bits not in (8, 12, 16):
        raise ValueError(f"{head}: {bits}-bit MRAW is not supported (8, 12 or 16)")
    effective = int(cih.get("EffectiveBit Depth", bits) or bits)
    effective = min(effective, bits)
    side = str(cih.get("EffectiveBit Side", "Lower")).lower()
    frame_bytes = h * w * bits // 8
    size = data.stat().st_size
    if count < 1 or h < 1 or w < 1:
        raise ValueError(f"{head}: empty recording ({count} frames of {w}x{h})")
    if size < count * frame_bytes:
        raise ValueError(
            f"{data}: truncated recording (cut short, e.g. by an interrupted copy): "
            f"{size} bytes, but {head.name} announces {count} frames of {w}x{h} "
            f"at {bits} bit ({count * frame_bytes} bytes; {size // frame_bytes} whole "
            "frames present). Copy the recording again."
        )
    colour, words = photron_colour(head, cih)
    if colour == "unknown":
        warnings.warn(
            f"{head}: the header ({words}) does not say whether the sensor is monochrome "
            "or colour; read as monochrome (a colour sensor's Bayer mosaic would stay in "
            "the frames as a fine checkerboard)",
            stacklevel=3,
        )
    bayer = colour == "bayer"
    # 16-bit words with the significant bits at the top are shifted down.
    shift = 16 - effective if bits == 16 and side == "higher" else 0
    if bits == 8:
        raw = np.memmap(data, dtype=np.uint8, mode="r", shape=(count, h, w))
    elif bits == 16:
        raw = np.memmap(data, dtype="<u2", mode="r", shape=(count, h, w))
    else:
        raw = np.memmap(data, dtype=np.uint8, mode="r", shape=(count, frame_bytes))

    def frame(i: int) -> np.ndarray:
        if bits == 12:
            img = unpack_uint12(np.asarray(raw[i])).reshape(h, w)
        else:
            img = np.array(raw[i])
        if bits == 16:
            img = img.astype(np.uint16, copy=False)
            if shift:
                img >>= shift
        return bayer_to_grey(img) if bayer else img

    fps = cih.get("Record Rate(fps)")
    return LabVideo(
        path=head,
        count=count,
        shape=(h, w),
        bit_depth=effective if bits > 8 else 8,
        fps=float(fps) if fps not in (None, "") else None,
        kind="mraw",
        header={**cih, "colour": "bayer → grey (R+2G+B)/4" if bayer else "mono"},
        _frame=frame,
    )


# --- Phantom CINE -----------------------------------------------------------------------


@dataclass
class _CineLayout:
    """What a CINE file's headers say (the fields :func:`_open_cine` uses)."""

    header_size: int
    compression: int
    first_image_no: int
    count: int
    width: int
    height: int  # > 0: rows stored bottom-up
    bit_count: int
    bi_compression: int
    bi_size_image: int
    setup: bytes
    setup_len: int
    offsets: np.ndarray  # (count,) int64 byte offset of each image's annotation
    last: int  # the image stored last
    image_end: int | None  # the byte after it, when it could be read

    def setup_uint(self, offset: int, fmt: str) -> int | None:
        """An unsigned field of the SETUP block, None beyond its length."""
        n = struct.calcsize(fmt)
        if offset + n > self.setup_len:
            return None
        return struct.unpack_from("<" + fmt, self.setup, offset)[0]


def _read_cine_layout(path: Path, size: int) -> _CineLayout:
    """The CINE header, BITMAPINFOHEADER, SETUP and image offset table of ``path``."""
    with open(path, "rb") as f:
        head = f.read(_CINE_HEADER.size + _BITMAP_HEADER.size)
        if len(head) < _CINE_HEADER.size + _BITMAP_HEADER.size:
            raise ValueError(f"{path}: too short for a CINE file")
        (magic, header_size, compression, _version, _first_movie_image, _total_count,
         first_image_no, count, off_bitmap, off_setup, off_offsets, _trigger,
         ) = _CINE_HEADER.unpack_from(head, 0)  # fmt: skip
        if magic != b"CI":
            raise ValueError(f"{path}: not a CINE file (starts with {magic!r}, not b'CI')")
        f.seek(off_bitmap)
        bmp = f.read(_BITMAP_HEADER.size)
        if len(bmp) < _BITMAP_HEADER.size:
            raise ValueError(f"{path}: truncated BITMAPINFOHEADER")
        (_bi_size, width, height, _planes, bit_count, bi_compression, bi_size_image, *_rest) = (
            _BITMAP_HEADER.unpack(bmp)
        )
        f.seek(off_setup)
        setup = f.read(_SETUP_REALBPP + 4)
        setup_len = struct.unpack_from("<H", setup, _SETUP_LENGTH)[0] if len(setup) > 144 else 0
        setup_len = min(setup_len or len(setup), len(setup))
        f.seek(off_offsets)
        table = f.read(8 * count)
        if len(table) < 8 * count:
            raise ValueError(
                f"{path}: truncated recording (cut short, e.g. by an interrupted copy): "
                f"{size} bytes end inside the image offset table of the {count} images "
                "its header announces. Copy the recording again."
            )
        offsets = np.frombuffer(table, dtype="<i8").copy()
        # The images must all lie in the file: the one stored last (the largest offset)
        # is read up to its end; a file cut short ends before it.
        last = int(np.argmax(offsets)) if count > 0 else 0
        image_end = None
        if count > 0 and 0 <= offsets[last] <= size - 8:
            f.seek(int(offsets[last]))
            annotation = struct.unpack("<I", f.read(4))[0]
            if annotation >= 8 and offsets[last] + annotation <= size:
                f.seek(int(offsets[last]) + annotation - 4)
                image_end = int(offsets[last]) + annotation + struct.unpack("<I", f.read(4))[0]
    return _CineLayout(
        header_size, compression, first_image_no, count, width, height, bit_count,
        bi_compression, bi_size_image, setup, setup_len, offsets, last, image_end,
    )  # fmt: skip


def _check_cine(path: Path, size: int, c: _CineLayout) -> tuple[int, int, int]:
    """Refuse what is not read (compression, pixel formats, empty or truncated files).

    Returns (channels, bytes per sample, DIB row stride in bytes)."""
    if c.compression not in (0, 2) or c.bi_compression != 0:
        raise ValueError(
            f"{path}: compressed or packed CINE (compression {c.compression}, "
            f"biCompression {c.bi_compression}) is not supported; save it as 16-bit"
        )
    if c.bit_count not in (8, 16, 24, 48):
        raise ValueError(f"{path}: {c.bit_count} bits per pixel is not supported (8, 16, 24, 48)")
    if c.count < 1 or c.width < 1 or c.height == 0:
        raise ValueError(f"{path}: empty recording ({c.count} images of {c.width}x{c.height})")
    channels = 3 if c.bit_count in (24, 48) else 1
    itemsize = 2 if c.bit_count in (16, 48) else 1
    h, w = abs(c.height), c.width
    stride = (w * channels * itemsize + 3) // 4 * 4  # DIB rows are padded to 4 bytes
    if c.image_end is None or c.image_end > size:
        whole = int(np.sum(c.offsets + 8 + stride * h <= size))
        ends = f"ends at byte {c.image_end}" if c.image_end is not None else "is cut"
        raise ValueError(
            f"{path}: truncated recording (cut short, e.g. by an interrupted copy): the "
            f"file has {size} bytes, but image {c.last} of the {c.count} its header announces "
            f"starts at byte {int(c.offsets[c.last])} and {ends} (about {whole} whole images "
            "present). Copy the recording again."
        )
    return channels, itemsize, stride


def _cine_bayer(path: Path, c: _CineLayout, channels: int) -> tuple[bool, int | None]:
    """Whether the images are a colour sensor's raw mosaic, and the SETUP's CFA word."""
    cfa = c.setup_uint(_SETUP_CFA, "I")
    pattern = (cfa or 0) & 0xFF
    bayer = pattern != 0 and channels == 1
    if bayer and c.compression != 2:
        warnings.warn(
            f"{path}: the SETUP names a colour sensor (CFA {cfa:#x}) but the header says "
            f"the {c.bit_count}-bit images are interpolated (compression {c.compression}); "
            "read as grey",
            stacklevel=4,
        )
        bayer = False
    return bayer, cfa


def _cine_frames(path: Path, size: int, c: _CineLayout, channels: int, itemsize: int,
                 stride: int, bayer: bool):  # fmt: skip
    """The reader of image ``i`` (H, W) of a CINE file, grey, in the file's sample type."""
    mm = np.memmap(path, dtype=np.uint8, mode="r")
    dtype = np.dtype("<u2") if itemsize == 2 else np.dtype(np.uint8)
    h, w, bottom_up, offsets = abs(c.height), c.width, c.height > 0, c.offsets

    def frame(i: int) -> np.ndarray:
        off = int(offsets[i])
        if off < 0 or off + 8 > size:
            raise ValueError(f"{path}: image {i} offset {off} outside the file")
        annotation = int(mm[off : off + 4].view("<u4")[0])
        if annotation < 8:
            raise ValueError(f"{path}: image {i} has a bad annotation size {annotation}")
        n_bytes = int(mm[off + annotation - 4 : off + annotation].view("<u4")[0])
        start = off + annotation
        if n_bytes < stride * h or start + stride * h > size:
            raise ValueError(f"{path}: image {i} truncated ({n_bytes} bytes, need {stride * h})")
        rows = np.asarray(mm[start : start + stride * h]).reshape(h, stride)
        img = rows[:, : w * channels * itemsize].copy().view(dtype).reshape(h, w, channels)
        if bottom_up:
            img = img[::-1]
        if channels == 3:  # BGR -> grey (ITU-R 601 luma), kept in the input's range
            grey = img[..., 2] * 0.299 + img[..., 1] * 0.587 + img[..., 0] * 0.114
            return np.ascontiguousarray(np.rint(grey).astype(img.dtype))
        grey = np.ascontiguousarray(img[..., 0]).astype(
            np.uint16 if itemsize == 2 else np.uint8, copy=False
        )
        return bayer_to_grey(grey) if bayer else grey

    return frame


def _open_cine(path: Path) -> LabVideo:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    size = path.stat().st_size
    c = _read_cine_layout(path, size)
    channels, itemsize, stride = _check_cine(path, size, c)
    real_bpp = c.setup_uint(_SETUP_REALBPP, "I")
    bayer, cfa = _cine_bayer(path, c, channels)
    bit_depth = 8 * itemsize
    if itemsize == 2 and real_bpp and 8 < real_bpp <= 16:
        bit_depth = int(real_bpp)
    fps = c.setup_uint(_SETUP_FRAMERATE, "I") or c.setup_uint(_SETUP_FRAMERATE16, "H")
    return LabVideo(
        path=path,
        count=int(c.count),
        shape=(abs(c.height), c.width),
        bit_depth=bit_depth,
        fps=float(fps) if fps else None,
        kind="cine",
        header={
            "first_image_no": c.first_image_no,
            "bit_count": c.bit_count,
            "real_bpp": real_bpp,
            "bi_size_image": c.bi_size_image,
            "header_size": c.header_size,
            "compression": c.compression,
            "cfa": cfa,
            "colour": (
                "bayer → grey (R+2G+B)/4" if bayer else ("bgr → grey" if channels == 3 else "mono")
            ),
        },
        _frame=_cine_frames(path, size, c, channels, itemsize, stride, bayer),
    )


# --- writers (tests, benchmarks, converting recordings) ----------------------------------


def pack_uint12(pixels: np.ndarray) -> bytes:
    """Inverse of :func:`unpack_uint12`: values < 4096, an even number of them."""
    flat = np.asarray(pixels, dtype=np.uint16).ravel()
    if flat.size % 2 or (flat.size and int(flat.max()) > 0xFFF):
        raise ValueError("12-bit packing needs an even number of values below 4096")
    out = np.empty((flat.size // 2, 3), dtype=np.uint8)
    out[:, 0] = flat[0::2] >> 4
    out[:, 1] = ((flat[0::2] & 0xF) << 4) | (flat[1::2] >> 8)
    out[:, 2] = flat[1::2] & 0xFF
    return out.tobytes()


def write_mraw(path: str | Path, frames: np.ndarray, bit_depth: int, fps: float) -> Path:
    """Write (n, H, W) frames as a Photron recording ``path`` (.cih) + its ``.mraw``.

    ``bit_depth`` 8 (uint8 data), 12 (packed) or 16 (little-endian words); values must
    fit. Returns the .cih path. (pyMRAW's ``save_mraw`` writes 8 and 16 bit only.)
    """
    head = Path(path).with_suffix(".cih")
    frames = np.asarray(frames)
    n, h, w = frames.shape
    if bit_depth not in (8, 12, 16) or int(frames.max(initial=0)) >= 2**bit_depth:
        raise ValueError(f"{head}: frames do not fit {bit_depth} bits (8, 12 or 16)")
    if bit_depth == 12:
        data = pack_uint12(frames)
    else:
        data = frames.astype(np.uint8 if bit_depth == 8 else "<u2").tobytes()
    fields = {
        "Record Rate(fps)": f"{fps:g}",
        "Shutter Speed(s)": f"{1 / fps:.6f}",
        "Total Frame": n,
        "Original Total Frame": n,
        "Start Frame": 0,
        "Image Width": w,
        "Image Height": h,
        "Color Type": "Mono",
        "Color Bit": bit_depth,
        "File Format": "MRaw",
        "EffectiveBit Depth": bit_depth,
        "EffectiveBit Side": "Lower",
    }
    text = "#Camera Information Header\n" + "".join(f"{k} : {v}\n" for k, v in fields.items())
    head.parent.mkdir(parents=True, exist_ok=True)
    head.with_suffix(".mraw").write_bytes(data)
    head.write_text(text + "\nEND\n")
    return head


def write_cine(path: str | Path, frames: np.ndarray, bit_depth: int, fps: int) -> Path:
    """Write (n, H, W) mono frames as an uncompressed Phantom CINE file.

    ``bit_depth`` 8 (8-bit pixels) or 9..16 (16-bit pixels, RealBPP = bit_depth).
    Images are stored bottom-up with rows padded to 4 bytes, without annotations.
    """
    path = Path(path)
    frames = np.asarray(frames)
    n, h, w = frames.shape
    if not 8 <= bit_depth <= 16 or int(frames.max(initial=0)) >= 2**bit_depth:
        raise ValueError(f"{path}: frames do not fit {bit_depth} bits (8..16)")
    item = 1 if bit_depth == 8 else 2
    stride = (w * item + 3) // 4 * 4
    setup = bytearray(_SETUP_SIZE)
    struct.pack_into("<H", setup, _SETUP_FRAMERATE16, min(int(fps), 0xFFFF))
    struct.pack_into("<H", setup, _SETUP_LENGTH, _SETUP_SIZE & 0xFFFF)
    struct.pack_into("<I", setup, _SETUP_FRAMERATE, int(fps))
    struct.pack_into("<I", setup, _SETUP_REALBPP, bit_depth)
    struct.pack_into("<I", setup, _SETUP_WHITELEVEL, 2**bit_depth - 1)
    off_setup = _CINE_HEADER.size + _BITMAP_HEADER.size
    off_offsets = off_setup + _SETUP_SIZE
    first = off_offsets + 8 * n
    offsets = [first + i * (8 + stride * h) for i in range(n)]
    head = _CINE_HEADER.pack(
        b"CI", 44, 0, 1, 0, n, 0, n, _CINE_HEADER.size, off_setup, off_offsets, bytes(8)
    )
    bmp = _BITMAP_HEADER.pack(40, w, h, 1, 8 * item, 0, stride * h, 0, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(head + bmp + bytes(setup) + struct.pack(f"<{n}q", *offsets))
        rows = np.zeros((h, stride), dtype=np.uint8)
        for img in frames:
            pix = img[::-1].astype(np.uint8 if item == 1 else "<u2")
            rows[:, : w * item] = pix.view(np.uint8).reshape(h, w * item)
            f.write(struct.pack("<II", 8, stride * h) + rows.tobytes())
    return path
