"""The ingest folder (``results/<session>/ingest``): its one reader and its writer.

=======================  =========================  =======================================
file                     content                    meaning
=======================  =========================  =======================================
``<cam>.npy``            (T, H, W) float32 in       undistorted, cropped, downscaled frames
                         [0, 1] (hand-written       (readable memory-mapped)
                         folders: uint8 / uint16)
``cameras.json``         surfphase.cameras          the cameras of those frames (no
                                                    distortion), top level ``session``
``meta.json``            JSON, written last         ``session``, ``fps`` (frames/s),
                                                    ``frame_indices`` (the session frame of
                                                    each stack position), ``dtype``,
                                                    ``cameras`` (per camera its source, or
                                                    a list of names), ``native``
``native/``              the same three, uint16     the frames before downscaling
                         (value·65535)              (``meta["native"]`` names it)
=======================  =========================  =======================================

:func:`read_ingest` validates a folder once, for every stage that reads it (masks, fit,
views, mesh, evaluate); each error names the file and the session.
:func:`IngestFolder.frames` gives the frames as float32 in [0, 1]
(:func:`surfphase.folders.frames.unit_float`).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surfphase.cameras import Camera, load_cameras, save_cameras
from surfphase.folders.frames import check_frame_dtype, unit_float
from surfphase.io import atomic_path, atomic_write_json, load_stack, save_npy, stack_frame_indices

META = "meta.json"
CAMERAS = "cameras.json"
#: The dtype ingest stores frames in (``meta.json``'s ``dtype``), and the native frames'.
STACK_DTYPE = np.dtype(np.float32)
NATIVE_DTYPE = np.dtype(np.uint16)


def stack_path(folder: str | Path, camera: str) -> Path:
    """``folder/<camera>.npy``: a camera's frame stack."""
    return Path(folder) / f"{camera}.npy"


@dataclass(frozen=True)
class IngestFolder:
    """A validated ingest folder.

    Attributes:
        path: the folder.
        session: the session id (``meta.json``).
        fps: frame rate, frames/s, or None when ``meta.json`` has none.
        meta: ``meta.json`` as parsed.
        cameras: every camera of ``cameras.json``, file order.
        stacks: ``{camera: memory-mapped (T, H, W[, C]) frames}`` of the cameras with
            frames, in ``meta.json``'s camera order (else ``cameras.json``'s); empty when
            read with ``stacks=False``.
        frame_indices: (T,) int64 session frame of each stack position.
    """

    path: Path
    session: str
    fps: float | None
    meta: dict
    cameras: dict[str, Camera]
    stacks: dict[str, np.ndarray]
    frame_indices: np.ndarray

    @property
    def meta_path(self) -> Path:
        return self.path / META

    @property
    def cameras_path(self) -> Path:
        return self.path / CAMERAS

    @property
    def names(self) -> list[str]:
        """The cameras with frames, in stack order."""
        return list(self.stacks)

    @property
    def n_frames(self) -> int:
        """T, the frames of every stack (0 without stacks)."""
        return int(len(self.frame_indices)) if self.stacks else 0

    def require_fps(self) -> float:
        """The frame rate; ValueError naming the file and session when there is none."""
        if self.fps is None:
            raise ValueError(f"{self.meta_path}: session {self.session}: fps must be positive")
        return self.fps

    def input_cameras(self) -> list[Camera]:
        """The cameras with frames, undistorted, in stack order."""
        return [self.cameras[n].undistorted() for n in self.stacks]

    def frames(self, camera: str, t: int | slice = slice(None)) -> np.ndarray:
        """Frames ``t`` of ``camera`` as float32 grey levels in [0, 1]."""
        return unit_float(self.stacks[camera][t])

    def source(self, camera: str) -> str | None:
        """The recording ``camera``'s frames came from (``meta.json``), if recorded."""
        per = self.meta.get("cameras")
        entry = per.get(camera) if isinstance(per, dict) else None
        return entry.get("source") if isinstance(entry, dict) else None

    def native(self) -> IngestFolder | None:
        """The native-resolution folder ``meta["native"]`` names, read; None without."""
        sub = self.meta.get("native")
        return read_ingest(self.path / str(sub)) if sub else None


def _read_meta(meta_path: Path) -> tuple[dict, str, float | None]:
    """``meta.json`` → (meta, session, fps or None)."""
    try:
        meta = json.loads(meta_path.read_text())
    except ValueError as e:
        raise ValueError(f"{meta_path}: not valid JSON ({e})") from e
    if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object, not {type(meta).__name__}")
    if not meta.get("session"):
        raise ValueError(f"{meta_path}: no session name (key 'session')")
    session = str(meta["session"])
    fps = meta.get("fps")
    if fps is None:
        return meta, session, None
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not fps > 0:
        raise ValueError(f"{meta_path}: session {session}: fps must be positive, not {fps!r}")
    return meta, session, float(fps)


def _camera_names(meta: dict, cameras: Mapping[str, Camera], folder: Path) -> list[str]:
    """The cameras with frames: ``meta.json``'s list (or dict keys), else those of
    ``cameras.json`` with a stack file."""
    listed = meta.get("cameras")
    if listed:
        return [str(n) for n in listed]
    return [n for n in cameras if stack_path(folder, n).is_file()]


def _read_stack(path: Path, cam: Camera, declared: str | None, where: str) -> np.ndarray:
    """One camera's stack, memory-mapped, checked against its camera and dtype."""
    try:
        st = load_stack(path)
    except ValueError as e:
        raise ValueError(f"{path}: not a readable .npy frame stack ({e}) ({where})") from e
    if not (st.ndim == 3 or (st.ndim == 4 and st.shape[-1] in (1, 3))):
        raise ValueError(f"{path}: expected frames × H × W, got shape {st.shape} ({where})")
    check_frame_dtype(st.dtype, f"{path} ({where})")
    if declared is not None and st.dtype != np.dtype(declared):
        raise ValueError(
            f"{path}: frames stored as {st.dtype}, but meta.json declares {declared} ({where})"
        )
    if st.shape[1:3] != (cam.height, cam.width):
        raise ValueError(
            f"{path}: frames are {st.shape[2]}×{st.shape[1]} pixels but cameras.json says "
            f"{cam.name} is {cam.width}×{cam.height} ({where})"
        )
    return st


def read_ingest(folder: str | Path, stacks: bool = True, min_cameras: int = 1) -> IngestFolder:
    """Read and validate an ingest folder (see the module table).

    Args:
        folder: the ingest folder (or its ``native/`` folder).
        stacks: memory-map and check the frame stacks (False: cameras and metadata only,
            e.g. for the mesh stage, which reads no frames).
        min_cameras: the fewest cameras with frames the caller can work with.

    Raises:
        FileNotFoundError: a missing ``cameras.json``, ``meta.json`` or frame stack.
        ValueError: unreadable metadata, a listed camera not in ``cameras.json``, frames
            whose size is not their camera's, cameras with different frame counts,
            frames stored in a dtype other than the declared one (or one frames are not
            stored in), too few cameras. Every message names the file and the session.
    """
    folder = Path(folder)
    cam_path, meta_path = folder / CAMERAS, folder / META
    for p in (cam_path, meta_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: not found in the ingest folder (run ingest first)")
    meta, session, fps = _read_meta(meta_path)
    cameras = load_cameras(cam_path)
    names = _camera_names(meta, cameras, folder)
    for name in names:
        if name not in cameras:
            raise ValueError(f"{cam_path}: no camera {name!r} (session {session})")
    if len(names) < min_cameras:
        raise ValueError(
            f"{folder}: session {session}: need frame stacks of ≥ {min_cameras} cameras "
            f"listed in cameras.json, found {len(names)}"
        )
    if not stacks:
        idx = meta.get("frame_indices")
        n = len(idx) if isinstance(idx, list) else 0
        frames = stack_frame_indices(meta, n, meta_path)
        return IngestFolder(folder, session, fps, meta, cameras, {}, frames)
    declared = meta.get("dtype")  # ingest declares float32; hand-written folders may not
    out: dict[str, np.ndarray] = {}
    for name in names:
        path = stack_path(folder, name)
        where = f"session {session}"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: frame stack of camera {name} ({where}) not found")
        st = _read_stack(path, cameras[name], declared, where)
        first = next(iter(out.values()), None)
        if first is not None and st.shape[0] != first.shape[0]:
            raise ValueError(
                f"{path}: {st.shape[0]} frames, camera {names[0]} has {first.shape[0]} ({where})"
            )
        out[name] = st
    frames = stack_frame_indices(meta, next(iter(out.values())).shape[0], meta_path)
    return IngestFolder(folder, session, fps, meta, cameras, out, frames)


# -- writing -----------------------------------------------------------------------------
@contextlib.contextmanager
def stack_writer(
    folder: str | Path, camera: str, shape: tuple[int, int, int], dtype=STACK_DTYPE
) -> Iterator[np.ndarray]:
    """Yield a writable memory-mapped (T, H, W) stack for ``camera``; it is renamed to
    ``folder/<camera>.npy`` once the block ends without error (never half written)."""
    with atomic_path(stack_path(folder, camera)) as tmp:
        stack = np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=shape)
        yield stack
        stack.flush()
        del stack


def write_cameras(folder: str | Path, cameras: Mapping[str, Camera], session: str) -> None:
    """``folder/cameras.json`` of the stacks' cameras."""
    save_cameras(Path(folder) / CAMERAS, cameras, session=session)


def write_native_meta(
    folder: str | Path, session: str, fps: float, cameras: Sequence[str], frame_indices
) -> None:
    """``native/meta.json``: session, fps, camera names, frame indices."""
    meta = {"session": session, "fps": float(fps), "cameras": list(cameras)}
    meta["frame_indices"] = np.asarray(frame_indices).tolist()
    atomic_write_json(Path(folder) / META, meta)


def write_meta(
    folder: str | Path,
    session: str,
    fps: float,
    frame_indices,
    cameras: Mapping[str, dict],
    frames: str | None = None,
    scale: float = 1.0,
    crop: Sequence[int] | None = None,
    native: str | None = None,
) -> dict:
    """``folder/meta.json`` (written last: a folder with it is whole); returns it.

    ``cameras``: per camera what ingest records of it (source, bit depth, sizes…);
    ``frames``: the session's frame range spec; ``native``: the native folder's name.
    """
    meta = {
        "session": session,
        "fps": float(fps),
        "frames": frames or "",
        "frame_indices": np.asarray(frame_indices).tolist(),
        "scale": float(scale),
        "crop": list(crop) if crop is not None else None,
        "dtype": str(STACK_DTYPE),
        "value_range": [0.0, 1.0],
        "cameras": dict(cameras),
        "native": native,
    }
    atomic_write_json(Path(folder) / META, meta)
    return meta


def write_ingest(
    folder: str | Path,
    session: str,
    fps: float,
    cameras: Mapping[str, Camera],
    stacks: Mapping[str, np.ndarray],
    frame_indices=None,
) -> dict:
    """A whole ingest folder from in-memory float32 (T, H, W) stacks in [0, 1] (for
    folders made without recordings); ``frame_indices`` default ``0 … T − 1``."""
    folder = Path(folder)
    T = len(next(iter(stacks.values())))
    idx = np.arange(T) if frame_indices is None else np.asarray(frame_indices)
    for name, st in stacks.items():
        save_npy(stack_path(folder, name), np.asarray(st, STACK_DTYPE))
    write_cameras(folder, {n: cameras[n] for n in stacks}, session)
    per = {n: {"stack": stack_path(folder, n).name, "count": len(st)} for n, st in stacks.items()}
    return write_meta(folder, session, fps, idx, per)
