"""The views folder (``results/<session>/views``, the ``render_views`` stage) and the
refine folder (``results/<session>/refine``): readers and writers.

Views folder, written into a temporary folder and renamed (it appears whole or not at
all):

==================  =====================  ===============================================
file                shape / dtype          meaning
==================  =====================  ===============================================
``cameras.json``    surfphase.cameras      the orbit cameras ``orbit01`` … at the fit's
                                           resolution; top level: ``session``, ``fps``,
                                           ``frame`` (session frame indices),
                                           ``scene_center`` (m), ``reference`` (camera)
``<v>.npy``         (T, H, W) uint16       grey render of view ``v`` composited over
                                           ``background.npy``, lossless (value·65535)
``<v>_alpha.npy``   (T, H, W) float16      the render's accumulated alpha
``<v>.mp4``         H.264, T frames        the same frames for people, at the session's fps
``background.npy``  (H, W) float32         the mean of the input views' fit backgrounds
==================  =====================  ===============================================

Refine folder: per view ``<v>.npy`` ((T, H, W) uint16, value·65535), ``<v>.mp4`` and
``<v>.json`` (the refinement's settings), the ``.npy`` written last.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surfphase.cameras import Camera, load_cameras, save_cameras
from surfphase.folders.frames import to_uint16, unit_float
from surfphase.io import atomic_dir, atomic_path, save_npy

CAMERAS, BACKGROUND = "cameras.json", "background.npy"
#: The dtype view frames are stored in (grey level × 65535).
VIEW_DTYPE = np.dtype(np.uint16)


def write_mp4(path: str | os.PathLike, frames: np.ndarray, fps: float) -> None:
    """Write (T, H, W) grey frames in [0, 1] as an H.264 MP4 (yuv420p), whole or not at all.

    H and W are padded to even sizes (H.264 with 4:2:0 chroma needs them) by repeating
    the last row/column.
    """
    import imageio.v2 as imageio

    v = np.round(np.clip(np.asarray(frames, np.float32), 0, 1) * 255).astype(np.uint8)
    ph, pw = v.shape[1] % 2, v.shape[2] % 2
    if ph or pw:
        v = np.pad(v, ((0, 0), (0, ph), (0, pw)), mode="edge")
    with atomic_path(path) as tmp:
        w = imageio.get_writer(
            str(tmp), format="FFMPEG", mode="I", fps=float(fps), codec="libx264",
            pixelformat="yuv420p", macro_block_size=1, ffmpeg_log_level="error",
            output_params=["-crf", "18"],
        )  # fmt: skip
        try:
            for frame in v:
                w.append_data(np.repeat(frame[..., None], 3, axis=2))
        finally:
            w.close()


def read_mp4(path: str | os.PathLike) -> np.ndarray:
    """(T, H, W) uint8 grey frames of an MP4 (first colour channel)."""
    import imageio.v2 as imageio

    r = imageio.get_reader(str(path), format="FFMPEG")
    try:
        return np.stack([np.asarray(f)[..., 0] for f in r])
    finally:
        r.close()


def read_view_stack(path: Path, where: str) -> np.ndarray:
    """A (T, H, W) uint16 view stack (a rendered or refined view), as stored."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such view in {where}")
    stack = np.load(path)
    if stack.dtype != VIEW_DTYPE or stack.ndim != 3:
        raise ValueError(f"{path}: expected a (T, H, W) uint16 stack, got {stack.dtype} "
                         f"{stack.shape}")  # fmt: skip
    return stack


@dataclass(frozen=True)
class ViewsFolder:
    """A views folder's ``cameras.json`` (the orbit cameras and their metadata).

    Attributes:
        path: the folder.
        session, fps: the session id and its frame rate (frames/s).
        frame: (T,) int64 session frame index of each stack position.
        cameras: ``{view: Camera}``, file order.
        meta: the top level of ``cameras.json`` (``scene_center``, ``reference``…).
    """

    path: Path
    session: str
    fps: float
    frame: np.ndarray
    cameras: dict[str, Camera]
    meta: dict

    def stored(self, view: str) -> np.ndarray:
        """(T, H, W) uint16 frames of ``view`` as stored."""
        return read_view_stack(self.path / f"{view}.npy", str(self.path))

    def frames(self, view: str) -> np.ndarray:
        """(T, H, W) float32 [0, 1] frames of ``view``."""
        return unit_float(self.stored(view))

    def alpha(self, view: str) -> np.ndarray:
        """(T, H, W) accumulated alpha of ``view`` as stored (float16)."""
        path = self.path / f"{view}_alpha.npy"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no alpha of view {view} (session {self.session})")
        alpha = np.load(path)
        if alpha.ndim != 3:
            raise ValueError(
                f"{path}: expected a (T, H, W) alpha stack, got {alpha.shape} "
                f"(session {self.session})"
            )
        return alpha

    def background(self) -> np.ndarray | None:
        """The (H, W) float32 ``background.npy``, or None when the folder has none."""
        path = self.path / BACKGROUND
        return np.load(path) if path.is_file() else None


def read_views(folder: str | os.PathLike) -> ViewsFolder:
    """Read a views folder's ``cameras.json``.

    Raises:
        FileNotFoundError: no ``cameras.json``.
        ValueError: an unreadable one, or one without a positive ``fps``, naming the file
            and the session.
    """
    folder = Path(folder)
    path = folder / CAMERAS
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no cameras.json in the views folder")
    try:
        meta = json.loads(path.read_text())
    except ValueError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from e
    session = str(meta.get("session", ""))
    try:
        fps = float(meta["fps"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: no readable fps ({e}) (session {session})") from e
    if not fps > 0:
        raise ValueError(f"{path}: session {session}: fps must be positive")
    frame = np.asarray(meta.get("frame", []), dtype=np.int64)
    top = {k: v for k, v in meta.items() if k != "cameras"}
    return ViewsFolder(folder, session, fps, frame, load_cameras(path), top)


def write_views(
    folder: str | os.PathLike,
    cameras: Sequence[Camera],
    frames: np.ndarray,
    alphas: np.ndarray,
    background: np.ndarray,
    meta: Mapping,
) -> None:
    """Write a views folder whole.

    Args:
        cameras: the V orbit cameras.
        frames: (V, T, H, W) float grey renders in [0, 1].
        alphas: (V, T, H, W) their alpha (stored as float16).
        background: (H, W) float32.
        meta: the top level of ``cameras.json``: ``session``, ``fps``, ``frame`` and the
            orbit's settings.
    """
    with atomic_dir(Path(folder)) as tmp:
        save_npy(tmp / BACKGROUND, background)
        for k, cam in enumerate(cameras):
            save_npy(tmp / f"{cam.name}.npy", to_uint16(frames[k]))
            save_npy(tmp / f"{cam.name}_alpha.npy", alphas[k].astype(np.float16))
            write_mp4(tmp / f"{cam.name}.mp4", frames[k], meta["fps"])
        save_cameras(tmp / CAMERAS, cameras, **meta)


def read_refined(folder: str | os.PathLike, view: str) -> np.ndarray:
    """(T, H, W) float32 [0, 1] refined frames of ``view`` (``folder/<view>.npy``)."""
    return unit_float(read_view_stack(Path(folder) / f"{view}.npy", str(folder)))


def write_refined(
    part: Path, folder: Path, view: str, refined: np.ndarray, fps: float, info: Mapping
) -> None:
    """Write refined view ``view`` into ``part`` (a private temporary folder), then
    rename ``<view>.json``, ``.mp4`` and ``.npy`` (last) into ``folder``.

    ``refined``: (T, H, W) float frames in [0, 1]; stored as uint16 (value·65535).
    """
    from surfphase.io import atomic_write_json

    atomic_write_json(part / f"{view}.json", dict(info))
    write_mp4(part / f"{view}.mp4", refined, fps)
    save_npy(part / f"{view}.npy", to_uint16(refined))
    for name in (f"{view}.json", f"{view}.mp4", f"{view}.npy"):  # the .npy last
        os.replace(part / name, Path(folder) / name)
