"""Ingest stage: a session's raw recordings → undistorted frame stacks on disk.

Per camera: read the frames of the session's frame range (:mod:`surfphase.video`),
undistort them with the rig's calibration keeping the same intrinsics
(``cv2.initUndistortRectifyMap`` with ``newCameraMatrix = K``, bilinear), crop, then
downscale with ``cv2.INTER_AREA``. Outputs in ``out``:

* ``<cam>.npy``: float32 (frames, H, W), grey levels in [0, 1] (the source divided by
  its full scale, 255 or 65535), readable memory-mapped with
  :func:`surfphase.folders.ingest.read_ingest`;
* ``cameras.json``: the cameras the stacks are seen by (no distortion, cropped and
  scaled intrinsics, same extrinsics);
* ``native/``, only when the frames are downscaled and ``native`` is on: the same
  frames undistorted and cropped but not downscaled (``<cam>.npy`` uint16, grey level ×
  65535), their ``cameras.json`` and a ``meta.json``. The mask stage segments these, so
  bubble outlines and centroids keep the recording's resolution
  ([docs/method.md §4](../docs/method.md#4-masks));
* ``meta.json``: session, fps, frame indices in the source, crop/scale, and per camera
  the source path, kind, bit depth, size and count (written last).

Frames are processed one at a time, so a long recording never sits in memory. The
folder's layout, reader and writer: :mod:`surfphase.folders.ingest`.
"""

from __future__ import annotations

import shutil
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from surfphase.cameras import Camera
from surfphase.folders.frames import to_uint16, unit_float
from surfphase.folders.ingest import (
    NATIVE_DTYPE,
    stack_writer,
    write_cameras,
    write_meta,
    write_native_meta,
)
from surfphase.video import open_video

NATIVE_DIR = "native"


def parse_frames(spec: str | None, count: int, source: str = "") -> np.ndarray:
    """Frame indices of ``start:stop[:step]`` (stop exclusive, Python-style) in ``count``.

    Empty ``start`` is 0, empty ``stop`` is ``count``; None or ``""`` is every frame.
    Raises ValueError (naming ``source``) for a malformed range or one beyond the video.
    """
    where = f"{source}: " if source else ""
    if spec is None or str(spec).strip() == "":
        return np.arange(count)
    parts = str(spec).strip().split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"{where}frame range {spec!r} is not start:stop[:step]")
    try:
        start = int(parts[0]) if parts[0] else 0
        stop = int(parts[1]) if parts[1] else count
        step = int(parts[2]) if len(parts) == 3 and parts[2] else 1
    except ValueError as e:
        raise ValueError(f"{where}frame range {spec!r} is not start:stop[:step]") from e
    if start < 0 or stop < 0 or step <= 0:
        raise ValueError(f"{where}frame range {spec!r}: need start, stop >= 0 and step > 0")
    if stop > count:
        raise ValueError(f"{where}frame range {spec!r} goes beyond the video ({count} frames)")
    if start >= stop:
        raise ValueError(f"{where}frame range {spec!r} is empty")
    return np.arange(start, stop, step)


def output_camera(cam: Camera, crop: tuple[int, int, int, int] | None, size: tuple[int, int]):
    """The camera that sees the undistorted, cropped, resized frames of ``size`` (W, H).

    Resizing uses the pixel-centre convention per axis: ``u' = (u + 0.5)·W'/W − 0.5``.
    """
    out = cam.undistorted()
    if crop is not None:
        out = out.cropped(*crop)
    sx, sy = size[0] / out.width, size[1] / out.height
    K = out.K.copy()
    K[0, :] *= sx
    K[1, :] *= sy
    K[0, 2] += 0.5 * sx - 0.5
    K[1, 2] += 0.5 * sy - 0.5
    return replace(out, K=K, width=int(size[0]), height=int(size[1]))


def _check_crop(crop, width: int, height: int, where: str) -> tuple[int, int, int, int] | None:
    if crop is None:
        return None
    if len(crop) != 4:
        raise ValueError(f"{where}crop must be x0,y0,w,h pixels, not {crop!r}")
    x0, y0, w, h = (int(v) for v in crop)
    if x0 < 0 or y0 < 0 or w <= 0 or h <= 0 or x0 + w > width or y0 + h > height:
        raise ValueError(
            f"{where}crop {x0},{y0},{w},{h} does not fit in the {width}×{height} image"
        )
    return x0, y0, w, h


def auto_scale(width: int, height: int, fit_size: int) -> float:
    """Ingest scale that makes the fitted frame's longer side ``fit_size`` pixels.

    ``width``, ``height``: the native (cropped) frame, pixels. Never upsamples (≤ 1).
    """
    if fit_size <= 0:
        raise ValueError(f"fit_size must be a positive number of pixels, not {fit_size!r}")
    return min(1.0, float(fit_size) / float(max(width, height)))


def _resolve_scale(session, cameras, videos, scale, crop, fit_size) -> float:
    """The ingest scale: ``scale`` checked, or :func:`auto_scale` of the first camera."""
    where = f"session {session}: "
    if scale == "auto":
        if not fit_size:
            raise ValueError(f"{where}scale: auto needs fit_size (pixels)")
        first = cameras.get(next(iter(videos)))
        if first is None:
            raise ValueError(f"{where}camera {next(iter(videos))} is not in the calibration")
        c0 = _check_crop(crop, first.width, first.height, where)
        scale = auto_scale(*((c0[2], c0[3]) if c0 else (first.width, first.height)), fit_size)
    if not isinstance(scale, int | float) or not 0 < scale <= 1:
        raise ValueError(f"{where}scale must be in (0, 1] or auto, not {scale!r}")
    return scale


def _open_sources(session: str, cameras: dict[str, Camera], videos: dict[str, Path]) -> dict:
    """``{camera: opened recording}``, checked: calibrated, present, same frame counts,
    calibrated size."""
    where = f"session {session}: "
    sources = {}
    for name, path in videos.items():
        if name not in cameras:
            raise ValueError(
                f"{where}camera {name} ({path}) is not in the calibration "
                f"(cameras: {', '.join(cameras)})"
            )
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{where}recording of {name} not found: {path}")
        try:
            sources[name] = open_video(path)
        except ValueError as e:
            raise ValueError(f"{where}camera {name}: {e}") from e
    names = list(sources)
    counts = {name: sources[name].count for name in names}
    if len(set(counts.values())) > 1:
        # Synchronised cameras record the same number of frames: the shorter recording
        # was most likely cut short (an interrupted copy) even if its file looks whole.
        short = min(counts, key=counts.get)
        listing = ", ".join(f"{n} {sources[n].path} has {counts[n]} frames" for n in names)
        raise ValueError(
            f"{where}cameras have different frame counts ({listing}): camera {short} "
            f"{sources[short].path} may be truncated (cut short, e.g. by an interrupted "
            "copy); copy it again, or give both recordings the same frames"
        )
    for name in names:
        src, cam = sources[name], cameras[name]
        if src.shape != (cam.height, cam.width):
            raise ValueError(
                f"{where}{name} {src.path} is {src.shape[1]}×{src.shape[0]} pixels but was "
                f"calibrated at {cam.width}×{cam.height}"
            )
    return sources


def _ingest_camera(src, cam: Camera, name: str, indices, crop, scale, out: Path, native: bool,
                   where: str) -> tuple[Camera, Camera | None, dict]:  # fmt: skip
    """Undistort, crop and downscale one camera's frames into ``out/<name>.npy`` (and
    ``out/native/<name>.npy`` when ``native`` and downscaled).

    Returns the output camera, the native camera (or None) and its ``meta.json`` entry.
    """
    c = _check_crop(crop, cam.width, cam.height, f"{where}{name}: ")
    cw, ch = (c[2], c[3]) if c else (cam.width, cam.height)
    size = (max(1, int(round(cw * scale))), max(1, int(round(ch * scale))))
    map1, map2 = cv2.initUndistortRectifyMap(
        cam.K, cam.dist, None, cam.K, (cam.width, cam.height), cv2.CV_32FC1
    )
    keep_native = native and size != (cw, ch)
    native_out = (
        stack_writer(out / NATIVE_DIR, name, (len(indices), ch, cw), NATIVE_DTYPE)
        if keep_native
        else nullcontext()
    )
    with stack_writer(out, name, (len(indices), size[1], size[0])) as stack, native_out as full:
        for k, frame in enumerate(src.read(indices)):
            img = cv2.remap(
                unit_float(frame, src.bit_depth), map1, map2,
                interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE,
            )  # fmt: skip
            if c:
                img = img[c[1] : c[1] + c[3], c[0] : c[0] + c[2]]
            if full is not None:
                full[k] = to_uint16(img)
            if size != (img.shape[1], img.shape[0]):
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            stack[k] = img
    entry = {
        "source": str(src.path),
        "source_kind": src.kind,
        "source_bit_depth": src.bit_depth,
        "source_size": [src.shape[1], src.shape[0]],
        "source_count": src.count,
        "source_fps": src.fps,
        "size": list(size),
        "count": len(indices),
        "stack": f"{name}.npy",
    }
    native_cam = output_camera(cam, c, (cw, ch)) if keep_native else None
    return output_camera(cam, c, size), native_cam, entry


def ingest_session(
    session: str,
    cameras: dict[str, Camera],
    videos: dict[str, Path],
    fps: float,
    frames: str | None = None,
    scale: float | str = 1.0,
    crop: tuple[int, int, int, int] | None = None,
    out: Path = Path("."),
    fit_size: int | None = None,
    native: bool = False,
) -> dict:
    """Undistort, crop and downscale a session's recordings into frame stacks in ``out``.

    Args:
        session: session id (named in every error).
        cameras: the rig's calibrated cameras (raw-image intrinsics and distortion).
        videos: ``{camera name: recording path}`` (video file, image folder, TIFF stack).
        fps: the session's frame rate, frames per second.
        frames: ``start:stop[:step]`` in source frames, or None for all.
        scale: output size factor after cropping (e.g. 0.25), in (0, 1]; or ``"auto"``:
            :func:`auto_scale` of the first camera's (cropped) native frame and ``fit_size``.
        crop: ``(x0, y0, w, h)`` pixels of the undistorted full-size image, or None.
        out: output folder.
        fit_size: with ``scale="auto"``, the fitted frame's longer side, pixels.
        native: also write ``out/native/`` (the frames before downscaling) when they
            are downscaled (config ``ingest: native_masks``).

    Returns:
        The metadata written to ``out/meta.json``.
    """
    where = f"session {session}: "
    if not videos:
        raise ValueError(f"{where}no camera recordings given")
    if not fps or fps <= 0:
        raise ValueError(f"{where}fps must be positive, not {fps!r}")
    scale = _resolve_scale(session, cameras, videos, scale, crop, fit_size)
    sources = _open_sources(session, cameras, videos)
    ref = sources[next(iter(sources))]
    indices = parse_frames(frames, ref.count, source=f"{where}{ref.path}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    out_cams: dict[str, Camera] = {}
    native_cams: dict[str, Camera] = {}
    per_cam = {}
    for name, src in sources.items():
        out_cams[name], nat, per_cam[name] = _ingest_camera(
            src, cameras[name], name, indices, crop, scale, out, native, where
        )
        if nat is not None:
            native_cams[name] = nat
    write_cameras(out, out_cams, session)
    if native_cams:
        write_cameras(out / NATIVE_DIR, native_cams, session)
        write_native_meta(out / NATIVE_DIR, session, fps, list(native_cams), indices)
    elif (out / NATIVE_DIR).exists():
        shutil.rmtree(out / NATIVE_DIR)
    return write_meta(
        out, session, fps, indices, per_cam, frames=frames, scale=scale, crop=crop,
        native=NATIVE_DIR if native_cams else None,
    )  # fmt: skip
