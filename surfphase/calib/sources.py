"""Where a camera's calibration views come from: a folder of images, or a recording.

A rig gives each camera either

* a **folder of images**: one view per file; the same file name in two folders is the
  same moment; or
* a **recording** (any file :func:`surfphase.video.open_video` reads: a video, a
  multi-page TIFF, a Photron or Phantom file): its frames are sampled (at most
  ``max_frames``, evenly spaced). Without timestamps, frame *k* of every camera's
  recording is the same moment. With a timestamps file (below) a camera's frame is
  paired with camera 0's nearest frame in time, and only when they are at most
  ``sync_tolerance`` apart; its other frames are views of that camera alone (they
  pin its intrinsics, not the extrinsics).

Timestamps file (``rigs.tsv`` column ``timestamps``; CSV, comma, tab or whitespace
separated, with a header): one row per frame and camera, with the columns

* ``cam_id``: the camera, as its name in ``rigs.tsv`` (``cam0``) or its number (``0``);
* ``frame_time``: the frame's capture time in seconds (any common origin);
* ``frame_index`` (optional): the frame's 0-based index in the camera's recording;
  without it a camera's rows, sorted by ``frame_time``, are its frames in order.

Other columns (e.g. caliscope's ``sync_index``) are ignored. Each camera's rows must
number its recording's frames.

Views are named ``fNNNNNN`` (camera 0's frame index, or the common index without
timestamps) when they are a moment shared by the cameras, and ``<camera>-fNNNNNN``
when they are one camera's alone.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.video import IMAGE_SUFFIXES, open_video

#: Most frames sampled from a calibration recording (evenly spaced).
MAX_FRAMES = 200
#: Frames of two cameras are paired when this fraction of the slower camera's median
#: frame interval apart, at most.
SYNC_TOLERANCE_FRAMES = 0.25


@dataclass
class FrameSource:
    """One camera's calibration views.

    Attributes:
        camera: camera name (``cam0``...).
        path: the folder or recording.
        kind: ``"folder"`` or ``"recording"``.
        names: view names, sorted (the moment each view shows; see the module doc).
        frame_of: for a recording, ``{view name: frame index}``; for a folder,
            ``{view name: index of the file in the sorted folder}``.
        times: ``{view name: capture time (s)}`` when timestamps were given.
    """

    camera: str
    path: Path
    kind: str
    names: list[str]
    frame_of: dict[str, int]
    times: dict[str, float] = field(default_factory=dict)
    frame_count: int = 0

    @property
    def label(self) -> str:
        """How messages name this source: ``cam1 (path)``."""
        return f"{self.camera} ({self.path})"

    def iter_views(self, names: list[str] | None = None):
        """Yield ``(name, image)``: (H, W) uint8 grayscale views (all, or ``names``).

        Frames are decoded once, in recording order; 16-bit input is scaled to 8 bits.
        """
        names = self.names if names is None else list(names)
        names = sorted(names, key=lambda n: self.frame_of[n])
        video = open_video(self.path)
        top = float(2 ** int(getattr(video, "bit_depth", 8)) - 1)
        frames = video.read([self.frame_of[n] for n in names])
        for name, img in zip(names, frames, strict=True):
            if img.dtype != np.uint8:
                img = np.clip(np.round(img.astype(np.float64) / top * 255.0), 0, 255)
                img = img.astype(np.uint8)
            yield name, img

    def read(self, name: str) -> np.ndarray:
        """The (H, W) uint8 grayscale view ``name``."""
        return next(self.iter_views([name]))[1]


def read_timestamps(path: str | Path) -> pd.DataFrame:
    """Rows ``cam_id`` (str), ``frame_time`` (s) and optionally ``frame_index`` (int)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"timestamps file not found: {path}")
    try:
        df = pd.read_csv(path, sep=None, engine="python", dtype=str, skipinitialspace=True)
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as e:
        raise ValueError(f"{path}: not a readable timestamps table ({e})") from e
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in ("cam_id", "frame_time") if c not in df.columns]
    if missing:
        raise ValueError(
            f"{path}: timestamps need the columns cam_id and frame_time (seconds); "
            f"missing {', '.join(missing)} (found {', '.join(df.columns)})"
        )
    out = pd.DataFrame({"cam_id": df["cam_id"].str.strip()})
    try:
        out["frame_time"] = pd.to_numeric(df["frame_time"])
        if "frame_index" in df.columns:
            out["frame_index"] = pd.to_numeric(df["frame_index"]).astype(int)
    except ValueError as e:
        raise ValueError(f"{path}: frame_time and frame_index must be numbers ({e})") from e
    return out


def _camera_times(table: pd.DataFrame, camera: str, count: int, path: Path) -> np.ndarray:
    """(count,) capture time (s) of each frame of ``camera``'s recording."""
    number = re.fullmatch(r"[A-Za-z_]*?(\d+)", camera)
    keys = {camera} | ({number.group(1), str(int(number.group(1)))} if number else set())
    rows = table[table["cam_id"].isin(keys)]
    if rows.empty:
        ids = ", ".join(sorted(table["cam_id"].unique()))
        raise ValueError(f"{path}: no timestamps for camera {camera} (cam_id values: {ids})")
    if "frame_index" in rows.columns:
        rows = rows.sort_values("frame_index")
        idx = rows["frame_index"].to_numpy()
        if not np.array_equal(idx, np.arange(len(idx))):
            raise ValueError(
                f"{path}: camera {camera}'s frame_index must run 0..{len(idx) - 1} once each"
            )
    else:
        rows = rows.sort_values("frame_time", kind="stable")
    if len(rows) != count:
        raise ValueError(
            f"{path}: {len(rows)} timestamps for camera {camera}, whose recording has "
            f"{count} frames"
        )
    return rows["frame_time"].to_numpy(dtype=np.float64)


def _sample(n: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` indices of ``range(n)``, evenly spaced, first one included."""
    if n <= max_frames:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, max_frames)).astype(int))


def _source_kinds(paths: dict[str, Path], where: str) -> dict[str, str]:
    """``{camera: "folder" | "recording"}``; every camera must be of one kind."""
    kinds = {}
    for n, p in paths.items():
        p = Path(p)
        if not p.exists():
            raise FileNotFoundError(f"{where}calibration folder or recording of {n} not found: {p}")
        kinds[n] = "folder" if p.is_dir() else "recording"
    if len(set(kinds.values())) > 1:
        raise ValueError(
            f"{where}give every camera a folder of images or every camera a recording, "
            f"not a mix ({', '.join(f'{n}: {kinds[n]}' for n in paths)})"
        )
    return kinds


def _folder_sources(paths: dict[str, Path], timestamps, where: str) -> dict[str, FrameSource]:
    """Folders of images, paired by file name."""
    if timestamps:
        raise ValueError(
            f"{where}timestamps ({timestamps}) are for recordings; folders of images "
            "are paired by file name"
        )
    sources = {}
    for n in paths:
        files = sorted(
            p.name for p in Path(paths[n]).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not files:
            raise ValueError(f"{where}no calibration images (png/tif/jpg/bmp) in {paths[n]} ({n})")
        sources[n] = FrameSource(
            n, Path(paths[n]), "folder", files, {f: k for k, f in enumerate(files)}
        )
        sources[n].frame_count = len(files)
    return sources


def _frame_index_sources(
    paths: dict[str, Path], counts: dict[str, int], max_frames: int
) -> tuple[dict[str, FrameSource], dict]:
    """Recordings without timestamps: frame k of every camera is one moment."""
    idx = _sample(max(counts.values()), max_frames)
    sources = {}
    for n in paths:
        mine = [int(i) for i in idx if i < counts[n]]
        views = {f"f{i:06d}": i for i in mine}
        sources[n] = FrameSource(n, Path(paths[n]), "recording", sorted(views), views)
        sources[n].frame_count = counts[n]
    report = {"mode": "frame index", "frames": counts, "sampled": len(idx)}
    if len(set(counts.values())) > 1:
        report["warning"] = (
            "the recordings have different frame counts "
            f"({', '.join(f'{n}: {c}' for n, c in counts.items())}); without a "
            "timestamps file frame k of every camera is taken as the same moment"
        )
    return sources, report


def _pair_by_time(
    t0: np.ndarray, idx0: np.ndarray, t: np.ndarray, name: str, sync_tolerance: float,
    max_frames: int,
) -> tuple[dict[str, int], dict[int, int], list[int], np.ndarray]:  # fmt: skip
    """One camera's frames (times ``t``) against camera 0's (``t0``, sampled ``idx0``).

    Returns ``(views, taken, alone, dt)``: view name → frame, camera 0 frame → this
    camera's partner (closest pairs first, one partner each), the frames with no
    partner within ``sync_tolerance``, and each frame's time to its nearest partner.
    """
    order = np.argsort(t0, kind="stable")
    # Camera 0's frame nearest in time to each of this camera's frames.
    pos = np.clip(np.searchsorted(t0[order], t), 1, len(t0) - 1) if len(t0) > 1 else None
    if pos is None:
        near = np.zeros(len(t), dtype=int)
    else:
        left, right = order[pos - 1], order[pos]
        near = np.where(np.abs(t0[left] - t) <= np.abs(t0[right] - t), left, right)
    dt = np.abs(t0[near] - t)
    paired = dt <= sync_tolerance
    views: dict[str, int] = {}
    sampled0 = set(int(i) for i in idx0)
    taken: dict[int, int] = {}
    for j in np.argsort(dt, kind="stable"):  # closest pairs first: one partner each
        i = int(near[j])
        if paired[j] and i in sampled0 and i not in taken:
            taken[i] = int(j)
    for i, j in taken.items():
        views[f"f{i:06d}"] = j
    alone = [j for j in range(len(t)) if not paired[j]]
    for j in _sample(len(alone), max_frames) if alone else []:
        views[f"{name}-f{alone[j]:06d}"] = int(alone[j])
    return views, taken, alone, dt


def _timestamp_sources(
    paths: dict[str, Path],
    counts: dict[str, int],
    timestamps: str | Path,
    max_frames: int,
    sync_tolerance: float | None,
    where: str,
) -> tuple[dict[str, FrameSource], dict]:
    """Recordings paired by the timestamps file, each camera against camera 0."""
    names = list(paths)
    table = read_timestamps(timestamps)
    times = {n: _camera_times(table, n, counts[n], Path(timestamps)) for n in names}
    intervals = [np.median(np.diff(t)) for t in times.values() if len(t) > 1]
    if sync_tolerance is None:
        if not intervals:
            raise ValueError(f"{where}{timestamps}: one frame per camera; give sync_tolerance")
        sync_tolerance = SYNC_TOLERANCE_FRAMES * float(max(intervals))
    t0 = times[names[0]]
    idx0 = _sample(len(t0), max_frames)
    sources = {
        names[0]: FrameSource(
            names[0],
            Path(paths[names[0]]),
            "recording",
            sorted(f"f{i:06d}" for i in idx0),
            {f"f{i:06d}": int(i) for i in idx0},
            {f"f{i:06d}": float(t0[i]) for i in idx0},
            counts[names[0]],
        )
    }
    per_cam = {names[0]: {"frames": int(counts[names[0]]), "sampled": len(idx0)}}
    for n in names[1:]:
        t = times[n]
        views, taken, alone, dt = _pair_by_time(t0, idx0, t, n, sync_tolerance, max_frames)
        frame_times = {v: float(t[j]) for v, j in views.items()}
        sources[n] = FrameSource(
            n, Path(paths[n]), "recording", sorted(views), views, frame_times, counts[n]
        )
        pair_dt = [float(dt[j]) for j in taken.values()]
        per_cam[n] = {
            "frames": int(counts[n]),
            "paired_with_" + names[0]: len(taken),
            "alone": len(alone),
            "max_pair_dt_s": max(pair_dt) if pair_dt else None,
        }
    report = {
        "mode": "timestamps",
        "timestamps": str(timestamps),
        "sync_tolerance_s": float(sync_tolerance),
        "cameras": per_cam,
    }
    return sources, report


def open_sources(
    paths: dict[str, Path],
    timestamps: str | Path | None = None,
    max_frames: int = MAX_FRAMES,
    sync_tolerance: float | None = None,
    where: str = "",
) -> tuple[dict[str, FrameSource], dict]:
    """Open every camera's calibration views; returns ``(sources, sync report)``.

    Args:
        paths: ``{camera: folder or recording}``; the first camera is camera 0.
        timestamps: the timestamps file (recordings only; see the module doc).
        max_frames: most frames sampled from a recording.
        sync_tolerance: most time (s) between two frames of a pair; by default
            ``SYNC_TOLERANCE_FRAMES`` of the slower camera's median frame interval.
        where: prefix of error messages (``"rig r1: "``).

    The sync report says how the views were paired: ``{"mode": "file names" |
    "frame index" | "timestamps", ...}`` with, for timestamps, the tolerance used and
    per camera the frames paired and alone.
    """
    kinds = _source_kinds(paths, where)
    if kinds[next(iter(paths))] == "folder":
        return _folder_sources(paths, timestamps, where), {"mode": "file names"}
    videos = {}
    for n in paths:
        try:
            videos[n] = open_video(paths[n])
        except ValueError as e:
            raise ValueError(f"{where}{n}: {e}") from e
    counts = {n: v.count for n, v in videos.items()}
    if not timestamps:
        return _frame_index_sources(paths, counts, max_frames)
    return _timestamp_sources(paths, counts, timestamps, max_frames, sync_tolerance, where)
