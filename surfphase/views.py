"""Novel views: the stage-1 fit rendered into orbit cameras about the scene centre.

``OUT/`` (the ``render_views`` stage): the views folder, whose layout, reader and writer
are :mod:`surfphase.folders.views` (``cameras.json`` of the orbit cameras, per view
``<v>.npy`` uint16 frames, ``<v>_alpha.npy``, ``<v>.mp4``; ``background.npy``).

Orbit view k (1-based) is the reference input camera (the fit's first, unless named)
rotated by k·``step_deg`` about the lab +y axis through the scene centre
(:func:`surfphase.cameras.orbit_cameras`): same distance, height and intrinsics, looking
at the centre. The scene centre is the least-squares closest point of the input cameras'
optical axes (:func:`scene_center`), which is where a rig's cameras aim.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from surfphase.cameras import Camera, load_cameras, orbit_cameras
from surfphase.folders.ingest import read_ingest
from surfphase.folders.views import read_views, write_views
from surfphase.settings import check_keys
from surfphase.views_params import DEFAULTS  # every setting, with its default


def views_params(params: dict | None) -> dict:
    """Defaults updated with ``params``; unknown keys are an error."""
    check_keys(DEFAULTS, params, "render-views")
    return {**DEFAULTS, **(params or {})}


def scene_center(cameras: Sequence[Camera]) -> np.ndarray:
    """(3,) least-squares closest point (metres) of the cameras' optical axes.

    Minimises Σ_c ‖(I − d_c d_cᵀ)(x − o_c)‖², o_c the centre and d_c the unit axis of
    camera c; needs ≥ 2 non-parallel axes.
    """
    if len(cameras) < 2:
        raise ValueError(f"scene_center: need ≥ 2 cameras, got {len(cameras)}")
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in cameras:
        d = cam.view_dir / np.linalg.norm(cam.view_dir)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    if np.linalg.cond(A) > 1e8:
        raise ValueError("scene_center: the cameras' optical axes are parallel")
    return np.linalg.solve(A, b)


def orbit_view_cameras(
    inputs: Sequence[Camera],
    n_views: int = 11,
    step_deg: float = 30.0,
    reference: str | None = None,
) -> tuple[list[Camera], np.ndarray]:
    """The orbit cameras ``orbit01`` … and the scene centre (3,) metres.

    Args:
        inputs: the fit's input cameras (undistorted images), ≥ 2.
        n_views, step_deg: number of views and azimuth step (degrees) about lab +y.
        reference: name of the input camera view k rotates from (default the first).
    """
    inputs = list(inputs)
    ref = inputs[0]
    if reference is not None:
        named = [c for c in inputs if c.name == reference]
        if not named:
            raise ValueError(
                f"render-views: reference camera {reference!r} is not an input camera "
                f"({', '.join(c.name for c in inputs)})"
            )
        ref = named[0]
    center = scene_center(inputs)
    return orbit_cameras(ref.undistorted(), center, int(n_views), float(step_deg)), center


def input_cameras(ingest_dir: str | os.PathLike) -> list[Camera]:
    """The fit's input cameras: those of the ingest folder with a frame stack, in stack
    order (the order of the fit's ``bg_images``), undistorted."""
    return read_ingest(ingest_dir, min_cameras=2).input_cameras()


def fit_background(surfels: dict[str, np.ndarray], height: int, width: int) -> np.ndarray:
    """(H, W) float32 grey background behind the bubbles in a novel view: the mean of the
    input views' fit backgrounds (``bg_images``) when they have this size, else the fit's
    constant background colour (channels averaged)."""
    bg = surfels.get("bg_images")
    if bg is not None and bg.shape[1:3] == (height, width):
        img = np.asarray(bg, np.float32).mean(axis=0)
    else:
        colour = np.asarray(surfels["background"], np.float32).reshape(1, 1, -1)
        img = np.broadcast_to(colour, (height, width, colour.shape[-1]))
    return np.ascontiguousarray(img.mean(axis=-1), dtype=np.float32)


def render_frame(
    surfels: dict[str, np.ndarray],
    t: int,
    cameras: Sequence[Camera],
    background: np.ndarray,
    device: str | torch.device = "cpu",
) -> tuple[np.ndarray, np.ndarray]:
    """Render frame position ``t`` of the fit into ``cameras``.

    Args:
        surfels: arrays of ``surfels.npz`` (:mod:`surfphase.fit.outputs`).
        t: 0-based frame position in the file.
        cameras: C undistorted cameras of one size (H, W).
        background: (H, W) grey image behind the surfels, [0, 1].

    Returns:
        grey (C, H, W) float32 in [0, 1] (colour channels averaged) and alpha (C, H, W).
    """
    from surfphase.fit.outputs import rasterize_frame
    from surfphase.render import over_background

    alive = np.asarray(surfels["alive"][t], bool)
    H, W = cameras[0].height, cameras[0].width
    if not alive.any():
        n = len(cameras)
        return np.broadcast_to(background, (n, H, W)).copy(), np.zeros((n, H, W), np.float32)
    rgb, alpha = rasterize_frame(surfels, t, cameras, torch.device(device), clamp_colors=True)
    grey = rgb.mean(-1).cpu().numpy()
    a = alpha[..., 0].cpu().numpy()
    image = np.clip(over_background(grey, a, background), 0, 1)
    return image.astype(np.float32), a.astype(np.float32)


def render_views(
    surfels_path: str | os.PathLike,
    ingest_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    params: dict | None = None,
    device: str | torch.device = "cpu",
    log=print,
) -> dict:
    """Render every orbit view of a stage-1 fit into ``out_dir`` (see the module table).

    Args:
        surfels_path: the fit's ``surfels.npz``.
        ingest_dir: the session's ingest folder (``cameras.json``, stacks, ``meta.json``).
        out_dir: the views folder to write (replaced whole if it exists).
        params: overrides of :data:`DEFAULTS`.
        device: torch device of the renderer.
        log: progress lines (``None`` for silence).

    Returns:
        a summary (views, frames, size, seconds).
    """
    from surfphase.fit.outputs import load_surfels

    p = views_params(params)
    t0 = time.perf_counter()
    surfels = load_surfels(surfels_path)
    ingest = read_ingest(ingest_dir, min_cameras=2)
    session, fps = ingest.session, ingest.require_fps()
    inputs = ingest.input_cameras()
    cams, center = orbit_view_cameras(inputs, p["n_views"], p["step_deg"], p["reference"])
    H, W = inputs[0].height, inputs[0].width
    background = fit_background(surfels, H, W)
    T = int(np.asarray(surfels["alive"]).shape[0])
    frames = np.zeros((len(cams), T, H, W), np.float32)
    alphas = np.zeros((len(cams), T, H, W), np.float32)
    for t in range(T):
        frames[:, t], alphas[:, t] = render_frame(surfels, t, cams, background, device)
        if log and ((t + 1) % 8 == 0 or t + 1 == T):
            log(f"session {session}: rendered frame {t + 1}/{T} of {len(cams)} views")
    meta = {
        "session": session, "fps": fps,
        "frame": np.asarray(surfels.get("frame", np.arange(T))).tolist(),
        "scene_center": center.tolist(), "reference": p["reference"] or inputs[0].name,
        "n_views": int(p["n_views"]), "step_deg": float(p["step_deg"]),
    }  # fmt: skip
    write_views(out_dir, cams, frames, alphas, background, meta)
    return {
        "session": session,
        "views": [c.name for c in cams],
        "frames": T,
        "size": [H, W],
        "scene_center_m": center.tolist(),
        "seconds": round(time.perf_counter() - t0, 2),
    }


def oracle_views(
    gt_dir: str | os.PathLike,
    views_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
) -> dict:
    """Write the true images of every orbit view as a refinement folder: what a perfect
    prior would return, to measure how far stage 2 can go with this rig (a benchmark on
    synthetic data; ground truth needed).

    Reads ``views_dir/cameras.json`` (the orbit cameras, lab frame, and the session
    frames), ``gt_dir/cameras.json`` (the true cameras, which for a synthetic campaign
    include the same orbit views) and ``gt_dir/views_clean/<v>/<frame:06d>.png`` (the
    noiseless views; ``views/`` where there are none). Writes ``out_dir/<v>.npy``, (T, H,
    W) uint16 grey like ``refine``'s, and ``out_dir/oracle.json``.

    Returns:
        The ``oracle.json`` content: per view the offset (m) between its true camera
        centre and the calibrated orbit camera's (calibration and scene-centre error, which
        the oracle views carry), and the folder the frames came from.

    Raises:
        FileNotFoundError: an orbit view without a true camera or frame of that name.
        ValueError: a true view whose image size differs from the orbit view's.
    """
    import cv2

    from surfphase.io import atomic_path, atomic_write_json

    gt_dir, views_dir, out_dir = Path(gt_dir), Path(views_dir), Path(out_dir)
    views = read_views(views_dir)
    orbit = list(views.cameras.values())
    truth = load_cameras(gt_dir / "cameras.json")
    src = gt_dir / "views_clean" if (gt_dir / "views_clean").is_dir() else gt_dir / "views"
    frames = [int(f) for f in views.frame]
    out_dir.mkdir(parents=True, exist_ok=True)
    info: dict = {"gt": str(gt_dir), "views": str(views_dir), "source": str(src), "offsets_m": {}}
    for cam in orbit:
        if cam.name not in truth:
            raise FileNotFoundError(f"{gt_dir / 'cameras.json'}: no true camera {cam.name}")
        stack = np.empty((len(frames), cam.height, cam.width), dtype=np.uint16)
        for i, f in enumerate(frames):
            path = src / cam.name / f"{f:06d}.png"
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise FileNotFoundError(f"{path}: no true frame {f} of view {cam.name}")
            if img.ndim == 3:
                img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
            if img.shape != stack.shape[1:]:
                raise ValueError(
                    f"{path}: {img.shape[1]}×{img.shape[0]} pixels, but orbit view "
                    f"{cam.name} is {cam.width}×{cam.height}"
                )
            stack[i] = img if img.dtype == np.uint16 else img.astype(np.uint16) * 257
        with atomic_path(out_dir / f"{cam.name}.npy") as tmp:
            np.save(tmp, stack)
        info["offsets_m"][cam.name] = float(np.linalg.norm(cam.center - truth[cam.name].center))
    atomic_write_json(out_dir / "oracle.json", info)
    return info
