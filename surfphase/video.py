"""Frame readers for a camera's recording: a video file, a folder of images, a TIFF stack.

:func:`open_video` picks the reader from the path:

* a folder: its images (PNG, TIFF, JPEG, BMP) sorted by file name, one frame each;
* ``.tif`` / ``.tiff``: a multi-page TIFF, one page per frame (``tifffile``);
* ``.cih`` / ``.cihx`` / ``.mraw`` (Photron) and ``.cine`` (Phantom): high-speed camera
  files, read by :mod:`surfphase.labformats` (8, 12 or 16 bit);
* anything else: a video file read with ``cv2.VideoCapture``.

Every reader yields 2D grayscale frames (colour is converted with OpenCV's luma
weights) as ``uint8`` or ``uint16`` arrays, (H, W) pixels, and reports ``bit_depth``
(8 or 16) so callers can normalise by the full scale ``2**bit_depth − 1``.
"""

from __future__ import annotations

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


class TiffStack(VideoSource):
    """A multi-page TIFF, one page per frame."""

    kind = "tiff"

    def __init__(self, path: Path):
        self.path = Path(path)
        try:
            with tifffile.TiffFile(self.path) as tif:
                self.count = len(tif.pages)
                first = tif.pages[0].asarray()
        except (tifffile.TiffFileError, ValueError, IndexError) as e:
            raise ValueError(f"{self.path}: not a readable TIFF ({e})") from e
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
