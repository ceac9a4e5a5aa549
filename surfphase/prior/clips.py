"""Read monocular clips (training data of the prior) and view videos (refinement input).

A clip or video is a folder of grayscale image frames sorted by name (8- or 16-bit
PNG/TIFF…) or an ``.npy`` stack (T, H, W). Values become float32 in [0, 1]: integer
images are divided by their type's maximum; float stacks are taken as they are and
must lie in [0, 1].
"""

from __future__ import annotations

import glob
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")


def _frame_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _to_unit(a: np.ndarray, name: str) -> np.ndarray:
    if np.issubdtype(a.dtype, np.integer):
        return (a.astype(np.float32) / np.iinfo(a.dtype).max).astype(np.float32)
    a = a.astype(np.float32)
    if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
        raise ValueError(f"{name}: float frames must be finite and within [0, 1]")
    return a


def read_video(path: str | Path) -> np.ndarray:
    """Read a (T, H, W) float32 video in [0, 1] from a frame folder or an ``.npy`` stack.

    Colour frames are converted to grey. Raises FileNotFoundError for a missing path or
    an empty folder and ValueError for frames of different sizes or a bad stack.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"video {path} not found")
    if path.is_file():
        if path.suffix.lower() != ".npy":
            raise ValueError(f"{path}: expected a folder of frames or an .npy stack (T, H, W)")
        a = np.load(path)
        if a.ndim == 4 and a.shape[-1] in (1, 3):
            a = a.mean(-1) if a.shape[-1] == 3 else a[..., 0]
        if a.ndim != 3:
            raise ValueError(f"{path}: expected a (T, H, W) stack, got shape {a.shape}")
        return _to_unit(np.asarray(a), str(path))
    files = _frame_files(path)
    if not files:
        raise FileNotFoundError(f"{path}: no image frames ({', '.join(IMAGE_SUFFIXES)})")
    frames = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{f}: not a readable image")
        if img.ndim == 3:
            img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
        if frames and img.shape != frames[0].shape:
            raise ValueError(
                f"{f}: size {img.shape} differs from {files[0].name} {frames[0].shape}"
            )
        frames.append(img)
    return _to_unit(np.stack(frames), str(path))


def find_clips(spec: str | Path) -> list[Path]:
    """The clips named by ``spec``, sorted: a folder of clip folders (or ``.npy`` stacks),
    a single clip folder, or a glob pattern of clip folders / ``.npy`` files.
    """
    s = str(spec)
    if any(ch in s for ch in "*?["):
        hits = [Path(p) for p in sorted(glob.glob(s))]
        hits = [p for p in hits if p.is_dir() or p.suffix.lower() == ".npy"]
        if not hits:
            raise FileNotFoundError(f"prior clips: nothing matches {s!r}")
        return hits
    root = Path(s)
    if not root.is_dir():
        raise FileNotFoundError(f"prior clips: folder {root} not found")
    if _frame_files(root):  # the folder is itself one clip
        return [root]
    hits = sorted(
        p for p in root.iterdir() if (p.is_dir() and _frame_files(p)) or p.suffix.lower() == ".npy"
    )
    if not hits:
        raise FileNotFoundError(f"prior clips: {root} holds no clip folders or .npy stacks")
    return hits


def read_clips(spec: str | Path) -> tuple[list[str], list[np.ndarray]]:
    """Names and (T, H, W) float32 [0, 1] videos of the clips named by ``spec``."""
    paths = find_clips(spec)
    return [p.stem if p.is_file() else p.name for p in paths], [read_video(p) for p in paths]


def write_video(out: str | Path, video: np.ndarray, bit_depth: int = 8) -> None:
    """Write (T, H, W) [0, 1] ``video`` as ``out.npy`` (float32) and PNG frames ``out/``.

    ``out`` may be given with or without the ``.npy`` suffix; the PNG folder is the
    same path without it. Each file is written whole or not at all, and the ``.npy``
    comes last, so a workflow can take it as the sign that the video is complete.
    """
    from surfphase.io import atomic_path, save_npy

    out = Path(out)
    base = out.with_suffix("") if out.suffix == ".npy" else out
    v = np.clip(np.asarray(video, np.float32), 0.0, 1.0)
    base.mkdir(parents=True, exist_ok=True)
    scale, dtype = (255, np.uint8) if bit_depth == 8 else (65535, np.uint16)
    for k, frame in enumerate(v):
        with atomic_path(base / f"{k:06d}.png") as tmp:
            if not cv2.imwrite(str(tmp), np.round(frame * scale).astype(dtype)):
                raise OSError(f"could not write {base / f'{k:06d}.png'}")
    save_npy(base.with_suffix(".npy"), v)  # last: its presence means the frames are complete
