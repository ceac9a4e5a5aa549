"""Frame readers for a camera's recording: a video file, a folder of images, a TIFF stack.

:func:`open_video` picks the reader from the path:

* a folder: its images (PNG, TIFF, JPEG, BMP) sorted by file name, one frame each;
* ``.tif`` / ``.tiff``: a multi-page TIFF, one page per frame (``tifffile``);
* ``.cih`` / ``.cihx`` / ``.mraw`` (Photron) and ``.cine`` (Phantom): high-speed camera
  files, read by :mod:`surfphase.labformats` (8, 12 or 16 bit);
* anything else: a video file read with ``cv2.VideoCapture``.

Every reader yields 2D grayscale frames (colour is converted with OpenCV's luma
weights; the Bayer mosaic of a colour high-speed camera's MRAW or CINE file by
:func:`surfphase.labformats.bayer_to_grey`, (R + 2G + B)/4) as ``uint8`` or ``uint16`` arrays, (H, W) pixels, and reports ``bit_depth``
(8 or 16) so callers can normalise by the full scale ``2**bit_depth − 1``.

A recording cut short (as by an interrupted copy) is refused on opening with a
ValueError naming the file and saying "truncated": a multi-page TIFF whose pages or
next-page pointers lie past its end, or with fewer pages than its own metadata announces
(:func:`check_tiff_complete`); an MRAW or CINE file shorter than its header's frames.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np
import tifffile

from surfphase.labformats import LAB_SUFFIXES, open_lab_video

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
TIFF_SUFFIXES = (".tif", ".tiff")


def _to_gray(frame: np.ndarray, source: str, rgb: bool) -> np.ndarray:
    """(H, W[, C]) frame → (H, W) grayscale of the same dtype (uint8 or uint16)."""
    if frame.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{source}: unsupported pixel type {frame.dtype} (need 8- or 16-bit)")
    if frame.ndim == 2:
        return frame
    if frame.ndim == 3 and frame.shape[2] == 1:
        return frame[:, :, 0]
    if frame.ndim == 3 and frame.shape[2] in (3, 4):
        if frame.shape[2] == 4:
            code = cv2.COLOR_RGBA2GRAY if rgb else cv2.COLOR_BGRA2GRAY
        else:
            code = cv2.COLOR_RGB2GRAY if rgb else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(np.ascontiguousarray(frame), code)
    raise ValueError(f"{source}: unsupported frame shape {frame.shape}")


def _bit_depth(dtype: np.dtype) -> int:
    return 16 if np.dtype(dtype) == np.uint16 else 8


class VideoSource:
    """A camera's recording: ``count`` frames of ``shape`` (H, W) at ``bit_depth`` bits.

    Attributes:
        path: the source path.
        kind: ``"video"``, ``"folder"`` or ``"tiff"``.
        count: number of frames.
        shape: (H, W) in pixels.
        bit_depth: 8 or 16.
        fps: frame rate stored in the file (video files only), else None.
    """

    path: Path
    kind: str
    count: int
    shape: tuple[int, int]
    bit_depth: int
    fps: float | None = None

    def read(self, indices: Iterable[int]) -> Iterator[np.ndarray]:
        """Yield the (H, W) grayscale frames at ``indices`` (0-based), in the order given."""
        raise NotImplementedError

    def _check(self, indices: Sequence[int]) -> list[int]:
        idx = [int(i) for i in indices]
        bad = [i for i in idx if not 0 <= i < self.count]
        if bad:
            raise ValueError(
                f"{self.path}: frame {bad[0]} is outside the recording ({self.count} frames)"
            )
        return idx


class ImageFolder(VideoSource):
    """A folder of images, one frame per file, sorted by name."""

    kind = "folder"

    def __init__(self, path: Path):
        self.path = Path(path)
        self.files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise ValueError(f"{self.path}: no images (png/tif/jpg/bmp) in this folder")
        first = self._load(self.files[0])
        self.count = len(self.files)
        self.shape = first.shape
        self.bit_depth = _bit_depth(first.dtype)

    def _load(self, f: Path) -> np.ndarray:
        if f.suffix.lower() in TIFF_SUFFIXES:
            return _to_gray(tifffile.imread(f), str(f), rgb=True)
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{f}: not a readable image")
        return _to_gray(img, str(f), rgb=False)

    def read(self, indices: Iterable[int]) -> Iterator[np.ndarray]:
        for i in self._check(list(indices)):
            img = self._load(self.files[i])
            if img.shape != self.shape or _bit_depth(img.dtype) != self.bit_depth:
                raise ValueError(
                    f"{self.files[i]}: {img.shape[1]}×{img.shape[0]} {_bit_depth(img.dtype)}-bit "
                    f"differs from the folder's first image "
                    f"({self.shape[1]}×{self.shape[0]} {self.bit_depth}-bit)"
                )
            yield img


class _TiffLog(logging.Handler):
    """Collects tifffile's log messages (it logs, not raises, e.g. 'invalid page offset')."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _next_ifd_offset(tif: tifffile.TiffFile, page_offset: int) -> int | None:
    """The next-IFD pointer stored after the IFD at ``page_offset`` (0: last page), or
    None when the IFD itself does not fit in the file."""
    fh, t = tif.filehandle, tif.tiff
    fh.seek(page_offset)
    raw = fh.read(t.tagnosize)
    if len(raw) < t.tagnosize:
        return None
    ntags = struct.unpack(t.tagnoformat, raw)[0]
    fh.seek(page_offset + t.tagnosize + ntags * t.tagsize)
    raw = fh.read(t.offsetsize)
    if len(raw) < t.offsetsize:
        return None
    return int(struct.unpack(t.offsetformat, raw)[0])


def _announced_frames(tif: tifffile.TiffFile) -> int | None:
    """The frame count a TIFF's own metadata announces (ImageJ ``images``; tifffile's
    shaped ``shape`` over the first page's), or None when it announces none."""
    ij = tif.imagej_metadata or {}
    if ij.get("images"):
        return int(ij["images"])
    shaped = tif.shaped_metadata
    if shaped and len(shaped) == 1 and shaped[0].get("shape"):
        # The array written, in pages of the first page's shape (2D grey or RGB).
        total, per_page = np.prod(shaped[0]["shape"]), np.prod(tif.pages[0].shape)
        if per_page and total % per_page == 0:
            return int(total // per_page)
    return None


def check_tiff_complete(tif: tifffile.TiffFile, path: Path) -> int:
    """The page count of a multi-page TIFF after checking it is whole; raises ValueError
    naming ``path`` and saying "truncated" when it was cut short (an interrupted copy).

    Evidence, from the file's structure: a page's image data or the last IFD's next-page
    pointer lying past the end of the file (tifffile then logs 'invalid page offset' and
    reads fewer pages); from its metadata: fewer pages than ImageJ's or tifffile's own
    header announces.
    """
    size = tif.filehandle.size
    n = len(tif.pages)
    problems: list[str] = []
    tif.pages.useframes = True  # light TiffFrames: offsets and byte counts, no tag parsing
    for i in range(n):
        try:
            page = tif.pages[i]
        except (tifffile.TiffFileError, struct.error, ValueError, OSError):
            problems.append(f"page {i}'s directory (IFD) is cut")
            break
        ends = [int(o) + int(c) for o, c in zip(page.dataoffsets, page.databytecounts, strict=True)]
        if ends and max(ends) > size:
            problems.append(f"page {i}'s image data ends at byte {max(ends)}")
            break
    if n and not problems:
        nxt = _next_ifd_offset(tif, int(tif.pages[n - 1].offset))
        if nxt is None or nxt >= size:
            problems.append(f"page {n - 1} points to a next page at byte {nxt}")
    announced = _announced_frames(tif)
    if announced is not None and announced > n:
        problems.append(f"its metadata announces {announced} frames but {n} pages are readable")
    if problems:
        raise ValueError(
            f"{path}: truncated TIFF (cut short, e.g. by an interrupted copy): the file has "
            f"{size} bytes and {'; '.join(problems)}. Copy the recording again."
        )
    return n


class TiffStack(VideoSource):
    """A multi-page TIFF, one page per frame; a truncated file is refused
    (:func:`check_tiff_complete`)."""

    kind = "tiff"

    def __init__(self, path: Path):
        self.path = Path(path)
        log, logger = _TiffLog(), logging.getLogger("tifffile")
        logger.addHandler(log)
        try:
            with tifffile.TiffFile(self.path) as tif:
                self.count = check_tiff_complete(tif, self.path)
                first = tif.pages[0].asarray()
        except (tifffile.TiffFileError, IndexError) as e:
            hint = f"; tifffile: {'; '.join(log.messages)}" if log.messages else ""
            raise ValueError(f"{self.path}: not a readable TIFF ({e}{hint})") from e
        finally:
            logger.removeHandler(log)
        first = _to_gray(first, str(self.path), rgb=True)
        self.shape = first.shape
        self.bit_depth = _bit_depth(first.dtype)

    def read(self, indices: Iterable[int]) -> Iterator[np.ndarray]:
        idx = self._check(list(indices))
        with tifffile.TiffFile(self.path) as tif:
            for i in idx:
                yield _to_gray(tif.pages[i].asarray(), f"{self.path} page {i}", rgb=True)


class VideoFile(VideoSource):
    """A video file decoded by OpenCV (8-bit)."""

    kind = "video"

    def __init__(self, path: Path):
        self.path = Path(path)
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise ValueError(f"{self.path}: OpenCV cannot open this video")
            ok, frame = cap.read()
            if not ok:
                raise ValueError(f"{self.path}: the video has no readable frame")
            fps = cap.get(cv2.CAP_PROP_FPS)
            self.fps = float(fps) if fps and fps > 0 else None
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()
        if n <= 0:  # container without a frame count: decode to count
            n = self._count_by_decoding()
        self.count = n
        gray = _to_gray(frame, str(self.path), rgb=False)
        self.shape = gray.shape
        self.bit_depth = _bit_depth(gray.dtype)

    def _count_by_decoding(self) -> int:
        cap = cv2.VideoCapture(str(self.path))
        n = 0
        while cap.grab():
            n += 1
        cap.release()
        return n

    def read(self, indices: Iterable[int]) -> Iterator[np.ndarray]:
        idx = self._check(list(indices))
        if idx != sorted(idx):
            # Out of order: decode the set once, in order, then hand frames out as asked.
            frames = dict(zip(sorted(set(idx)), self._stream(sorted(set(idx))), strict=True))
            for i in idx:
                yield frames[i]
            return
        yield from self._stream(idx)

    def _stream(self, idx: list[int]) -> Iterator[np.ndarray]:
        """Frames at non-decreasing ``idx``, decoded sequentially (seeking in compressed
        streams is not frame-exact), holding one frame at a time."""
        cap = cv2.VideoCapture(str(self.path))
        try:
            pos, frame = -1, None
            for target in idx:
                while pos < target:
                    ok = cap.grab()
                    if not ok:
                        raise ValueError(f"{self.path}: video ends at frame {pos + 1}")
                    pos += 1
                    frame = None
                if frame is None:
                    ok, raw = cap.retrieve()
                    if not ok:
                        raise ValueError(f"{self.path}: cannot decode frame {target}")
                    frame = _to_gray(raw, str(self.path), rgb=False)
                yield frame
        finally:
            cap.release()


def open_video(path: str | Path) -> VideoSource:
    """Open a recording (video file, image folder or multi-page TIFF); see the module doc.

    Raises FileNotFoundError if ``path`` does not exist, ValueError if it cannot be read.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"video not found: {path}")
    if path.is_dir():
        return ImageFolder(path)
    if path.suffix.lower() in LAB_SUFFIXES:
        return open_lab_video(path)
    if path.suffix.lower() in TIFF_SUFFIXES:
        return TiffStack(path)
    return VideoFile(path)
