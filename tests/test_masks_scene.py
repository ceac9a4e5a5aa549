"""A small two-view shadowgraph movie of spheres, drawn independently of the masks code.

Each sphere is drawn in each view as the disk of its projected silhouette (centre
projected, radius f·R/depth) with a dark ring and a bright core, far spheres first,
on a bright uneven backlight. The truth labels give the sphere index per pixel.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from surfphase.cameras import look_at, orbit_cameras, save_cameras

SCENE_CENTER = np.array([0.0, 0.006, 0.0])


def rig(size: int = 128):
    fx = 1800.0 * size / 512
    cam0 = look_at("cam0", [0.0, 0.008, 0.06], SCENE_CENTER, fx=fx, width=size, height=size)
    (cam1,) = orbit_cameras(cam0, SCENE_CENTER, n_views=1, step_deg=35.0)
    from dataclasses import replace

    return {"cam0": cam0, "cam1": replace(cam1, name="cam1", role="input")}


def draw_view(cam, spheres, seed: int, noise: float = 0.01, core: bool = True):
    """spheres: list of (centre (3,), radius m). Returns (image float32, truth int32).

    ``core=False`` draws uniformly dark disks instead of rings with a bright core.
    """
    h, w = cam.height, cam.width
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    bg = (
        0.8
        + 0.08 * (xx / w)
        - 0.06 * (yy / h)
        - 0.12 * (((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (w * w / 4 + h * h / 4))
    )
    img = bg.copy()
    truth = np.full((h, w), -1, np.int32)
    depth = [cam.world_to_camera(c[None])[0, 2] for c, _ in spheres]
    ss = 3
    off = (np.arange(ss) + 0.5) / ss - 0.5
    oy, ox = np.meshgrid(off, off, indexing="ij")
    for k in np.argsort(depth)[::-1]:
        c, r = spheres[k]
        ((u, v),) = cam.project(c[None], distort=False)
        rp = cam.K[0, 0] * r / depth[k]
        d = np.sqrt((xx[..., None, None] + ox - u) ** 2 + (yy[..., None, None] + oy - v) ** 2)
        rho = d / rp
        inner = 0.1 + 0.75 * np.exp(-((rho / 0.5) ** 2)) if core else 0.12
        trans = np.where(rho < 1, inner, 1.0).mean(axis=(2, 3))
        cover = (rho < 1).mean(axis=(2, 3)) >= 0.5
        img = np.where(cover | (trans < 1), img * trans, img)
        truth[cover] = k
    img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 1).astype(np.float32), truth


def write_ingest(
    folder: Path,
    tracks,
    n_frames: int,
    size: int = 128,
    dtype=np.float32,
    session: str = "s01",
    core: bool = True,
):
    """tracks: list of functions frame → (centre, radius) or None. Writes an ingest folder.

    Returns ``{camera: (T, H, W) truth}`` (sphere index per pixel, −1 background).
    """
    cams = rig(size)
    folder.mkdir(parents=True, exist_ok=True)
    truths = {}
    for ci, (name, cam) in enumerate(cams.items()):
        frames, tr = [], []
        for t in range(n_frames):
            sph = [f(t) for f in tracks]
            idx = [i for i, s in enumerate(sph) if s is not None]
            im, lab = draw_view(cam, [sph[i] for i in idx], seed=1000 * ci + t, core=core)
            lut = np.array(idx + [-1], np.int32)
            frames.append(im)
            tr.append(lut[lab])
        st = np.stack(frames)
        if dtype == np.uint16:
            st = np.round(st * 65535).astype(np.uint16)
        np.save(folder / f"{name}.npy", st)
        truths[name] = np.stack(tr)
    save_cameras(folder / "cameras.json", cams)
    (folder / "meta.json").write_text(
        json.dumps(
            {
                "session": session,
                "fps": 2000.0,
                "frames": list(range(n_frames)),
                "cameras": list(cams),
            }
        )
    )
    return truths


def rising(x, y0, z, r, speed_px=0.0, t0=0, t1=10**9, dy=1.2e-4):
    """A sphere rising by ``dy`` metres per frame, alive on frames [t0, t1)."""

    def f(t):
        if not (t0 <= t < t1):
            return None
        return np.array([x, y0 + dy * (t - t0), z]), r

    return f
