"""A tiny ray-cast session (two cameras, lit spheres) for the fit's tests, and its checks.

Independent of the renderer and of ``surfphase.synth``: spheres are ray-cast in numpy
(3×3 supersampling), masks are the id of the sphere hit at each pixel centre.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from surfphase.cameras import look_at, save_cameras

LIGHT = np.array([0.3, 1.0, 0.5]) / np.linalg.norm([0.3, 1.0, 0.5])
BACKGROUND = 0.8


def toy_cameras(size: int = 48, azimuths=(0.0, 35.0)):
    """Cameras ``cam0``, ``cam1``, … at ``azimuths`` (degrees about +y), 6 cm away."""
    target = np.array([0.0, 0.003, 0.0])
    cams = []
    for k, az in enumerate(azimuths):
        a = math.radians(az)
        eye = target + np.array([0.06 * math.sin(a), 0.002, 0.06 * math.cos(a)])
        cams.append(
            look_at(f"cam{k}", eye, target, fx=1800.0 * size / 512, width=size, height=size)
        )
    return cams


def toy_spheres(frame: int, fps: float, velocity=(0.02, 0.25, 0.0)):
    """[(bubble id, centre (3,) m, radius m)] at ``frame``: a static nucleation bubble 0
    on the plate and bubble 1 rising at ``velocity`` m/s."""
    t = frame / fps
    c1 = np.array([0.0008, 0.0038, 0.0]) + np.asarray(velocity) * t
    return [(0, np.array([-0.0004, 0.0009, 0.0]), 0.001), (1, c1, 0.0011)]


def _smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    s = np.clip((x - a) / (b - a), 0.0, 1.0)
    return s * s * (3 - 2 * s)


def raycast(cam, spheres, ss: int = 3, look: str = "lit"):
    """(H, W) image in [0, 1] and (H, W) int32 labels of spheres seen by ``cam``.

    ``look``: ``"lit"`` — spheres lit from :data:`LIGHT` (the same shade from every
    camera); ``"backlit"`` — a shadowgraph: dark where the ray meets the sphere
    obliquely, a bright core where the sphere faces the camera (view-dependent)."""
    H, W = cam.height, cam.width
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    img = np.zeros((H, W))
    labels = np.full((H, W), -1, np.int32)
    o = cam.center
    for k, (dy, dx) in enumerate([(a, b) for a in offs for b in offs] + [(0.0, 0.0)]):
        vv, uu = np.meshgrid(np.arange(H) + dy, np.arange(W) + dx, indexing="ij")
        d = cam.pixel_rays(np.stack([uu.ravel(), vv.ravel()], 1), distorted=False)
        best = np.full(d.shape[0], np.inf)
        shade = np.full(d.shape[0], BACKGROUND)
        lab = np.full(d.shape[0], -1, np.int32)
        for bid, c, r in spheres:
            oc = o - c
            b = d @ oc
            disc = b * b - (oc @ oc - r * r)
            hit = disc > 0
            tt = np.where(hit, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
            closer = hit & (tt > 0) & (tt < best)
            p = o + tt[closer, None] * d[closer]
            n = (p - c) / r
            best[closer] = tt[closer]
            if look == "backlit":
                cos = np.abs(np.einsum("nk,nk->n", n, d[closer]))
                shade[closer] = BACKGROUND * (0.09 + 0.64 * _smoothstep(0.8, 0.95, cos))
            else:
                shade[closer] = 0.15 + 0.55 * np.clip(n @ LIGHT, 0, None)
            lab[closer] = bid
        if k < ss * ss:
            img += shade.reshape(H, W) / (ss * ss)
        else:
            labels = lab.reshape(H, W)
    return img, labels


def make_toy_session(
    root: Path,
    frames: int = 4,
    size: int = 48,
    fps: float = 1000.0,
    look: str = "lit",
    azimuths=(0.0, 35.0),
):
    """Write ``root/ingest`` and ``root/masks`` of a toy session; return (ingest, masks).
    ``look``: see :func:`raycast`; ``azimuths``: see :func:`toy_cameras`."""
    cams = toy_cameras(size, azimuths)
    ingest, masks = root / "ingest", root / "masks"
    ingest.mkdir(parents=True, exist_ok=True)
    masks.mkdir(parents=True, exist_ok=True)
    for cam in cams:
        imgs, labs = [], []
        for f in range(frames):
            im, lab = raycast(cam, toy_spheres(f, fps), look=look)
            imgs.append(im.astype(np.float32))
            labs.append(lab)
        np.save(ingest / f"{cam.name}.npy", np.stack(imgs))
        np.save(masks / f"{cam.name}_labels.npy", np.stack(labs))
    save_cameras(ingest / "cameras.json", cams)
    meta = {"session": "toy", "fps": fps, "frame_indices": list(range(frames))}
    (ingest / "meta.json").write_text(json.dumps(meta))
    return ingest, masks


def test_toy_session_masks_match_projected_spheres(tmp_path):
    ingest, masks = make_toy_session(tmp_path, frames=2, size=32)
    labs = np.load(masks / "cam0_labels.npy")
    cam = toy_cameras(32)[0]
    for f in range(2):
        for bid, c, _r in toy_spheres(f, 1000.0):
            u, v = np.rint(cam.project(c[None], distort=False)[0]).astype(int)
            assert labs[f, v, u] == bid
    imgs = np.load(ingest / "cam1.npy")
    assert imgs.shape == (2, 32, 32) and 0 <= imgs.min() and imgs.max() <= 1
