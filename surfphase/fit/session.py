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

import numpy as np

from surfphase.cameras import Camera
from surfphase.folders.frames import unit_float
from surfphase.folders.ingest import read_ingest
from surfphase.folders.masks import read_anchors, read_masks, read_merges


class SessionData:
    """The frames, masks and cameras of one session (memory-mapped stacks), read through
    the folder readers (:func:`surfphase.folders.ingest.read_ingest`,
    :func:`surfphase.folders.masks.read_masks`), which validate them and name the file
    and the session in every error.

    ``images(t)`` → (C, H, W, D) float32 in [0, 1]; ``labels(t)`` → C × (H, W) int32.
    """

    def __init__(self, ingest_dir: str | os.PathLike, masks_dir: str | os.PathLike):
        ing = read_ingest(ingest_dir, min_cameras=2)
        self.meta = ing.meta
        self.session = ing.session
        self.fps = ing.require_fps()
        self.cameras: list[Camera] = ing.input_cameras()
        self.stacks: list[np.ndarray] = list(ing.stacks.values())
        masks = read_masks(masks_dir, self.cameras, ing.session, n_frames=ing.n_frames)
        self.label_stacks: list[np.ndarray] = list(masks.labels.values())
        self.n_frames = ing.n_frames
        self.merges = read_merges(masks_dir, self.session)
        self.anchors = read_anchors(masks_dir, self.session)
        self.frame_indices = ing.frame_indices
        self.times = self.frame_indices / self.fps
        self.height, self.width = self.stacks[0].shape[1:3]

    def images(self, t: int) -> np.ndarray:
        out = [unit_float(s[t]) for s in self.stacks]
        return np.stack([a[..., None] if a.ndim == 2 else a for a in out])

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
        """Session frame indices where every view's masks show the nucleation region and
        the first two agree on a piece of it."""
        from surfphase.fit.outputs import nucleation_frames

        return nucleation_frames(
            self.label_stacks, self.frame_indices[: self.n_frames], self.cameras
        )

    def fingerprint(self) -> str:
        """Hash of everything the fit reads: the ingest's metadata, every frame and every
        label of every view, the cameras, the mask stage's merges and anchors. A
        checkpoint resumes only a run with the same fingerprint (with the masks of one
        frame changed, or their anchors, a rerun refits instead of keeping the surfels
        fitted to the old ones)."""
        h = hashlib.sha256(json.dumps(self.meta, sort_keys=True).encode())
        for s, lab in zip(self.stacks, self.label_stacks, strict=True):
            h.update(str((s.shape, str(s.dtype), lab.shape, str(lab.dtype))).encode())
            for arr in (s, lab):
                for t in range(arr.shape[0]):
                    h.update(np.ascontiguousarray(arr[t]).data)
        for c in self.cameras:
            h.update(json.dumps(c.to_dict(), sort_keys=True).encode())
        merges = {
            str(t): {str(b): sorted(int(q) for q in ps) for b, ps in m.items()}
            for t, m in self.merges.items()
        }
        h.update(json.dumps(merges, sort_keys=True).encode())
        if self.anchors is not None:
            h.update(self.anchors.to_csv(index=False).encode())
        return h.hexdigest()
