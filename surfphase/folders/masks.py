"""The masks folder (``results/<session>/masks``): its reader and its writer.

=========================  ======================  ======================================
file                       content                 meaning
=========================  ======================  ======================================
``<cam>_labels.npy``       (T, H, W) int32         −1 background, 0 the nucleation region,
                                                   ≥ 1 a bubble id shared by all views
``instances.csv``          table                   ``frame, camera, bubble, area, cx, cy,
                                                   x0, y0, x1, y1, score`` (pixels)
``events.csv``             table                   ``frame, camera, event, parents,
                                                   children``
``anchors.csv``            table                   triangulated bubble centres (m)
``overlays/*.png``         RGB                     a few frames, views side by side
``masks.json``             JSON                    session, backend, parameters, counts
=========================  ======================  ======================================

The writer fills a temporary folder and moves the files into place only once all of
them are complete. :func:`read_masks` checks the label stacks against the cameras they
belong to; each error names the file and the session.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.cameras import Camera
from surfphase.io import atomic_write_json, atomic_write_text, save_npy

INSTANCES, EVENTS, ANCHORS, INFO = "instances.csv", "events.csv", "anchors.csv", "masks.json"


def labels_path(folder: str | Path, camera: str) -> Path:
    """``folder/<camera>_labels.npy``: a camera's label stack."""
    return Path(folder) / f"{camera}_labels.npy"


@dataclass(frozen=True)
class MasksFolder:
    """A masks folder's label stacks, validated against their cameras.

    Attributes:
        path: the folder.
        session: the session id the labels belong to (named in errors).
        labels: ``{camera: memory-mapped (T, H, W) integer labels}``, cameras' order.
    """

    path: Path
    session: str
    labels: dict[str, np.ndarray]

    @property
    def n_frames(self) -> int:
        """T, the frames of every label stack."""
        return int(next(iter(self.labels.values())).shape[0])

    def frame(self, camera: str, t: int) -> np.ndarray:
        """(H, W) int32 labels of ``camera`` at position ``t``."""
        return np.asarray(self.labels[camera][t]).astype(np.int32)


def read_masks(
    folder: str | Path,
    cameras: Sequence[Camera],
    session: str,
    n_frames: int | None = None,
    min_frames: int | None = None,
) -> MasksFolder:
    """The label stacks of ``cameras`` (memory-mapped), checked.

    Args:
        folder: the masks folder.
        cameras: the cameras whose labels are read (sizes checked against theirs).
        session: named in every error.
        n_frames: the frames the labels must have (the frame stacks'), or None.
        min_frames: the fewest frames the caller needs (e.g. the fit's), or None.

    Raises:
        FileNotFoundError: a camera without ``<cam>_labels.npy``.
        ValueError: labels that are not a (T, H, W) integer stack of the camera's size,
            cameras with different frame counts, or other than ``n_frames`` /
            fewer than ``min_frames`` frames.
    """
    folder = Path(folder)
    out: dict[str, np.ndarray] = {}
    for cam in cameras:
        path = labels_path(folder, cam.name)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: session {session}: no masks for {cam.name}")
        try:
            lab = np.load(path, mmap_mode="r")
        except ValueError as e:
            raise ValueError(f"{path}: session {session}: not a readable .npy ({e})") from e
        if not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(
                f"{path}: session {session}: labels stored as {lab.dtype}, expected integers"
            )
        if lab.ndim != 3 or lab.shape[1:] != (cam.height, cam.width):
            raise ValueError(
                f"{path}: session {session}: labels of shape {lab.shape} do not match "
                f"the {cam.width}×{cam.height} camera {cam.name}"
            )
        first = next(iter(out.items()), None)
        if first is not None and lab.shape[0] != first[1].shape[0]:
            raise ValueError(
                f"{path}: session {session}: {lab.shape[0]} frames, the masks of "
                f"{first[0]} have {first[1].shape[0]}"
            )
        if n_frames is not None and lab.shape[0] != n_frames:
            raise ValueError(
                f"{path}: session {session}: masks of {lab.shape[0]} frames, the frame "
                f"stacks have {n_frames}"
            )
        if min_frames is not None and lab.shape[0] < min_frames:
            raise ValueError(
                f"{path}: session {session}: masks of {lab.shape[0]} frames, {min_frames} needed"
            )
        out[cam.name] = lab
    return MasksFolder(folder, session, out)


def read_merges(folder: str | Path, session: str) -> dict[int, dict[int, set[int]]]:
    """``{frame position: {merged bubble: parent bubbles}}`` from ``folder/events.csv``
    (``merge`` rows of any camera; parents and children are ``+``-joined bubble ids).

    A missing file (masks from elsewhere) means no merges are known: ``{}``.

    Raises:
        ValueError: a file that is not the mask stage's event table, naming it and the
            session.
    """
    path = Path(folder) / EVENTS
    out: dict[int, dict[int, set[int]]] = {}
    if not path.exists():
        return out
    try:
        ev = pd.read_csv(path, dtype=str, keep_default_na=False)
        rows = ev[ev["event"] == "merge"]
        for f, par, chi in zip(rows["frame"], rows["parents"], rows["children"], strict=True):
            if not par.strip():
                continue  # no parent bubble known: nothing to take a history from
            for c in str(chi).split("+"):
                d = out.setdefault(int(f), {}).setdefault(int(c), set())
                d.update(int(q) for q in str(par).split("+"))
    except (KeyError, ValueError, pd.errors.ParserError) as e:
        raise ValueError(
            f"{path}: session {session}: not a merge/split event table of the mask stage ({e})"
        ) from e
    return out


def read_anchors(folder: str | Path, session: str) -> pd.DataFrame | None:
    """``folder/anchors.csv`` (``frame, bubble, x, y, z, ...``: triangulated bubble
    centres, m), or None when the masks have none (written before it existed).

    Raises:
        ValueError: a table without those columns, naming the file and the session.
    """
    path = Path(folder) / ANCHORS
    if not path.is_file():
        return None
    tab = pd.read_csv(path)
    missing = {"frame", "bubble", "x", "y", "z"} - set(tab.columns)
    if missing:
        raise ValueError(f"{path}: session {session}: anchors lack columns {sorted(missing)}")
    return tab


def write_masks(
    folder: str | Path,
    labels: Mapping[str, np.ndarray],
    instances: pd.DataFrame,
    events: pd.DataFrame,
    anchors: pd.DataFrame,
    overlays: Mapping[str, np.ndarray],
    info: Mapping,
) -> None:
    """Write a masks folder whole: label stacks, the three tables (instances at 3
    decimals, anchors at 9 significant digits), ``overlays/<name>`` PNGs (RGB uint8) and
    ``masks.json``; existing outputs are replaced (a stale ``overlays/`` removed)."""
    from surfphase.masks.overlay import save_png

    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        for name, lab in labels.items():
            save_npy(labels_path(tmp, name), lab)
        atomic_write_text(tmp / INSTANCES, instances.to_csv(index=False, float_format="%.3f"))
        atomic_write_text(tmp / EVENTS, events.to_csv(index=False))
        atomic_write_text(tmp / ANCHORS, anchors.to_csv(index=False, float_format="%.9g"))
        for name, rgb in overlays.items():
            save_png(tmp / "overlays" / name, rgb)
        atomic_write_json(tmp / INFO, dict(info))
        folder.mkdir(parents=True, exist_ok=True)
        if (folder / "overlays").exists():
            shutil.rmtree(folder / "overlays")
        for f in sorted(tmp.iterdir()):
            os.replace(f, folder / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
