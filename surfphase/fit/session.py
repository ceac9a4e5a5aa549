"""The inputs of a session's fit: its frames, masks, cameras and the mask stage's events
and anchors (:class:`SessionData`), read from the ingest and mask folders.

Frames are memory-mapped; ``images(t)`` gives (C, H, W, D) float32 in [0, 1] and
``labels(t)`` the C (H, W) int32 instance masks (−1 background, 0 the nucleation
region, ≥ 1 bubbles). Positions are metres (lab frame), times seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from surfphase.cameras import Camera, load_cameras
from surfphase.io import stack_frame_indices


def read_merges(path: Path) -> dict[int, dict[int, set[int]]]:
    """``{frame position: {merged bubble: parent bubbles}}`` from the mask stage's
    ``events.csv`` (``merge`` rows of any camera; parents and children are ``+``-joined
    bubble ids). A missing file (masks from elsewhere) means no merges are known."""
    import pandas as pd

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
        raise ValueError(f"{path}: not a merge/split event table of the mask stage ({e})") from e
    return out


class SessionData:
    """The frames, masks and cameras of one session (memory-mapped stacks).

    ``images(t)`` → (C, H, W, D) float32 in [0, 1]; ``labels(t)`` → C × (H, W) int32.
    """

    def __init__(self, ingest_dir: str | os.PathLike, masks_dir: str | os.PathLike):
        ingest_dir, masks_dir = Path(ingest_dir), Path(masks_dir)
        cam_path = ingest_dir / "cameras.json"
        if not cam_path.exists():
            raise FileNotFoundError(f"{cam_path}: no cameras.json in the ingest folder")
        cams = load_cameras(cam_path)
        meta_path = ingest_dir / "meta.json"
        if not meta_path.exists():
            raise FileNotFoundError(f"{meta_path}: no meta.json in the ingest folder")
        try:
            self.meta = json.loads(meta_path.read_text())
        except ValueError as e:
            raise ValueError(f"{meta_path}: not valid JSON ({e})") from e
        self.session = str(self.meta.get("session", ingest_dir.name))
        self.fps = float(self.meta.get("fps", 0) or 0)
        if not self.fps > 0:
            raise ValueError(f"{meta_path}: session {self.session}: fps must be positive")
        self.cameras: list[Camera] = []
        self.stacks: list[np.ndarray] = []
        self.label_stacks: list[np.ndarray] = []
        for name, cam in cams.items():
            p = ingest_dir / f"{name}.npy"
            if not p.exists():
                continue
            m = masks_dir / f"{name}_labels.npy"
            if not m.exists():
                raise FileNotFoundError(f"{m}: session {self.session}: no masks for {name}")
            stack = np.load(p, mmap_mode="r")
            labs = np.load(m, mmap_mode="r")
            if stack.shape[1:3] != (cam.height, cam.width):
                raise ValueError(
                    f"{p}: session {self.session}: frames are {stack.shape[1:3]}, "
                    f"cameras.json says {(cam.height, cam.width)}"
                )
            if labs.shape[:3] != stack.shape[:3]:
                raise ValueError(
                    f"{m}: session {self.session}: masks {labs.shape} do not match "
                    f"frames {stack.shape}"
                )
            self.cameras.append(cam.undistorted())
            self.stacks.append(stack)
            self.label_stacks.append(labs)
        if len(self.cameras) < 2:
            raise ValueError(
                f"{ingest_dir}: session {self.session}: need frame stacks of ≥ 2 cameras "
                f"listed in cameras.json, found {len(self.cameras)}"
            )
        self.n_frames = min(s.shape[0] for s in self.stacks)
        self.merges = read_merges(masks_dir / "events.csv")
        from surfphase.fit.outputs import read_anchors

        self.anchors = read_anchors(masks_dir / "anchors.csv", self.session)
        self.frame_indices = stack_frame_indices(self.meta, self.n_frames, meta_path)
        self.times = self.frame_indices / self.fps
        self.height, self.width = self.stacks[0].shape[1:3]

    def images(self, t: int) -> np.ndarray:
        out = []
        for s in self.stacks:
            a = np.asarray(s[t])
            if a.dtype == np.uint16:
                a = a.astype(np.float32) / 65535.0
            elif a.dtype == np.uint8:
                a = a.astype(np.float32) / 255.0
            else:
                a = a.astype(np.float32)
            if a.ndim == 2:
                a = a[..., None]
            out.append(np.clip(a, 0.0, 1.0))
        return np.stack(out)

    def labels(self, t: int) -> list[np.ndarray]:
        return [np.asarray(s[t]).astype(np.int32) for s in self.label_stacks]

    def anchor_centres(self, t: int) -> dict[int, np.ndarray]:
        """``{bubble: (3,) triangulated centre (m)}`` at frame position ``t`` (the mask
        stage's ``anchors.csv``; empty without it)."""
        if self.anchors is None:
            return {}
        rows = self.anchors[self.anchors["frame"] == int(self.frame_indices[t])]
        xyz = rows[["x", "y", "z"]].to_numpy(np.float64)
        return {int(b): xyz[i] for i, b in enumerate(rows["bubble"])}

    def nucleation_frames(self) -> set[int]:
        """Session frame indices where every view's masks show the nucleation region."""
        from surfphase.fit.outputs import nucleation_frames

        return nucleation_frames(self.label_stacks, self.frame_indices[: self.n_frames])

    def fingerprint(self) -> str:
        h = hashlib.sha256(json.dumps(self.meta, sort_keys=True).encode())
        for s, lab in zip(self.stacks, self.label_stacks, strict=True):
            h.update(str((s.shape, str(s.dtype), lab.shape)).encode())
            h.update(np.ascontiguousarray(s[0]).tobytes())
            h.update(np.ascontiguousarray(lab[-1]).tobytes())
        for c in self.cameras:
            h.update(json.dumps(c.to_dict(), sort_keys=True).encode())
        return h.hexdigest()
