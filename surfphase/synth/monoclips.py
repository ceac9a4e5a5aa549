"""Uncalibrated monocular clips of similar boiling scenes, for the video prior.

Each clip is one view of its own :class:`~surfphase.synth.bubbles.BubbleScene`
(own seed, bubble count and frame rate) from a random camera: any azimuth about
the vertical, 0.75–1.35× the reference rig's distance, somewhat above the scene
centre, field of view ±15 % of the rig's, mild random lens distortion. Frames are rendered like the held-out views
(2× supersampled, area-averaged) at ``size × size`` pixels.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from surfphase.cameras import Camera, look_at
from surfphase.io import atomic_path
from surfphase.synth import shadowgraph
from surfphase.synth.bubbles import BubbleScene
from surfphase.synth.rig import SCENE_CENTER, default_rig


def random_clip_camera(rng: np.random.Generator, size: int) -> Camera:
    """A random camera of ``size × size`` pixels looking at the scene (see module doc).

    Distance and focal length vary about the reference rig's cam0 (0.75–1.35× its
    distance, field of view within ±15 % of its), so the scene fills a similar part
    of the frame.
    """
    ref = default_rig(native=size)["cam0"]
    d_ref = float(np.linalg.norm(ref.center - SCENE_CENTER))
    az = rng.uniform(0, 2 * np.pi)
    dist = d_ref * rng.uniform(0.75, 1.35)
    eye = SCENE_CENTER + np.array(
        [dist * np.sin(az), rng.uniform(0.0, 0.2) * dist, dist * np.cos(az)]
    )
    target = SCENE_CENTER + np.array([rng.uniform(-1, 1) * 1e-3, rng.uniform(-1, 1.5) * 1e-3, 0.0])
    fx = ref.K[0, 0] * (dist / d_ref) * rng.uniform(0.85, 1.15)
    dist_coef = np.array([rng.uniform(-0.2, 0.05), rng.uniform(0, 0.15), 0.0, 0.0, 0.0])
    return look_at("clip", eye, target, fx=fx, width=size, height=size, dist=dist_coef)


def write_clip(
    out_dir: Path, seed: int, frames: int = 24, size: int = 128, bit_depth: int = 8
) -> dict:
    """Render one clip into ``out_dir/000000.png …``; returns its settings (for a log).

    ``frames`` frames at a random rate in {1000, 1500, 2000} fps; ``size`` pixels square.
    """
    rng = np.random.default_rng([seed, 5303])
    fps = float(rng.choice([1000.0, 1500.0, 2000.0]))
    n_bubbles = int(rng.integers(2, 8))
    scene = BubbleScene(int(rng.integers(0, 2**31)), frames / fps, bubbles=n_bubbles)
    cam = random_clip_camera(rng, size)
    rays = shadowgraph.camera_rays(cam.scaled(2.0), distorted=True)
    bg = shadowgraph.background(f"clip{seed}", 2 * size, 2 * size, seed=seed)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for f in range(frames):
        img, _ = shadowgraph.render_frame(
            scene.state(f / fps), rays, bg, np.random.default_rng([seed, 5304, f]),
            out_size=(size, size), blur_sigma=0.5,
        )  # fmt: skip
        write_png(out_dir / f"{f:06d}.png", shadowgraph.quantize(img, bit_depth))
    return {"seed": seed, "fps": fps, "bubbles": n_bubbles, "frames": frames, "size": size}


def write_png(path: Path, img: np.ndarray) -> None:
    """Write a grey 8- or 16-bit PNG whole or not at all."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"could not write {path}")
