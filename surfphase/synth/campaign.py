"""A whole synthetic campaign on disk, in the campaign format of docs/campaign.md.

Layout under ``out`` (paths in the TSVs are relative to the TSV's folder)::

    config.yaml            {sessions: sessions.tsv, rigs: rigs.tsv, prior_clips: clips, seed: N}
    sessions.tsv           session, rig, fps, frames (empty = all), cam0, cam1, gt
    rigs.tsv               rig, board, cam0, cam1 (calibration image folders)
    board.yaml             ChArUco board (charuco.board_yaml_dict())
    synth.json             settings, merges and timings of this run (informative)
    rig01/calib/<cam>/poseNNN.png      calibration images (surfphase.synth.charuco);
                                       pose000.png is the lab-frame reference image
    <session>/<cam>/000000.png …       raw input videos: native size, true distortion,
                                       8-bit PNG (16-bit with bit_depth=16)
    <session>/gt/cameras.json          all true cameras (cam0/cam1 native with distortion;
                                       mid, orbit01..11 at fit size, no distortion),
                                       top-level "fps" and "fit_scale"

The ``bench`` preset (:data:`BENCH_SESSIONS`; ``bench-mixed``: their settings recombined
by the seed; ``bench-drawn``: settings drawn by the seed from :data:`DRAWN`'s ranges;
:func:`bench_specs`) differs: one rig per session
(``rigNN/calib/``), each session's videos in its own container (``<cam>.mp4``,
``<cam>.avi``, ``<cam>.tif``, ``<cam>.cih`` + ``.mraw``; :func:`write_video`), frames of
its own size (W×H), bit depth, frame rate, backlight, noise and blur, fit scale
:data:`BENCH_FIT_SCALE` and held-out views :data:`BENCH_HELDOUT` only; no clips.
    <session>/gt/bubbles.csv           frame, bubble, x, y, z (m), vx, vy, vz (m/s), r_eq (m)
    <session>/gt/merges.csv            t (s), frame (first frame showing the merged bubble),
                                       parent_a, parent_b, merged (bubble ids)
    <session>/gt/meshes/000000.ply     true surface per frame, metres (binary PLY)
    <session>/gt/views/<cam>/000000.png  held-out views at fit size, as recorded (noisy)
    <session>/gt/views_clean/<cam>/000000.png  the same without sensor noise, 16-bit
    <session>/gt/views_background/<cam>.png  the held-out camera's reference frame without
                                       bubbles (backlight and plate), noiseless, 16-bit
    <session>/gt/masks/<cam>.npy       int32 (frames, H, W) at the raw videos' native size:
                                       id of the bubble seen through each pixel's ray, -1 =
                                       background or plate (ids start at 1; 0 is unused)
    clips/clipNNN/000000.png …         monocular clips at fit size

Frame ``f`` is at ``t = f / fps``. Bubble ids, merges and velocities: see
:mod:`surfphase.synth.bubbles` and :mod:`surfphase.synth.groundtruth`. The whole
campaign is built in a temporary folder next to ``out`` and renamed onto it.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import tifffile
import yaml

from surfphase.cameras import save_cameras
from surfphase.io import atomic_path, save_npy
from surfphase.labformats import write_mraw
from surfphase.synth import charuco, shadowgraph
from surfphase.synth.bubbles import SHAPES, BubbleScene
from surfphase.synth.groundtruth import bubble_table, frame_truth, mesh_volume, write_ply
from surfphase.synth.monoclips import write_clip, write_png
from surfphase.synth.rig import default_rig, eye_height

#: Downscale from native raw frames to the fit size (the workflow's ingest scale).
FIT_SCALE = 0.25
INPUTS = ("cam0", "cam1")

#: The ``bench`` preset's sessions (``surfphase bench accuracy``): what labs vary.
#: ``angle`` (degrees between the input cameras about the vertical), ``elevation``
#: (degrees the cameras look down at the scene centre; 0 = the plate seen level, edge
#: on), ``size`` (native width, height, px), ``fps``, ``bubbles`` (mean number in the
#: column), ``merge`` (a merge inside the clip), ``shape`` (:data:`bubbles.SHAPES`),
#: ``radius_mm`` (detachment radius range), ``backlight`` (:data:`shadowgraph.BACKLIGHTS`),
#: ``noise`` (:data:`NOISE` level), ``blur`` (optics σ, native px), ``bit_depth`` (8, 12,
#: 16) and ``container`` (:data:`CONTAINERS`).
BENCH_SESSIONS: tuple[dict, ...] = (
    dict(angle=25.0, elevation=0.0, size=(256, 256), fps=1000.0, bubbles=3, merge=True,
         shape="sphere", radius_mm=(0.6, 1.2), backlight="smooth", noise="low", blur=0.6,
         bit_depth=8, container="mp4"),
    dict(angle=35.0, elevation=4.0, size=(320, 240), fps=2000.0, bubbles=3, merge=False,
         shape="spheroid", radius_mm=(0.8, 1.5), backlight="gradient", noise="mid", blur=0.8,
         bit_depth=16, container="tiff-lzw"),
    dict(angle=45.0, elevation=7.0, size=(240, 320), fps=5000.0, bubbles=4, merge=True,
         shape="tilted", radius_mm=(0.6, 1.3), backlight="stripes", noise="mid", blur=1.0,
         bit_depth=12, container="mraw"),
    dict(angle=60.0, elevation=10.0, size=(256, 256), fps=10000.0, bubbles=4, merge=False,
         shape="sphere", radius_mm=(0.3, 0.7), backlight="speckle", noise="low", blur=0.5,
         bit_depth=8, container="tiff"),
    dict(angle=30.0, elevation=9.0, size=(320, 256), fps=3000.0, bubbles=4, merge=True,
         shape="spheroid", radius_mm=(0.5, 1.1), backlight="dim", noise="high", blur=0.8,
         bit_depth=16, container="mraw"),
    dict(angle=50.0, elevation=2.0, size=(288, 224), fps=1500.0, bubbles=3, merge=False,
         shape="tilted", radius_mm=(0.7, 1.5), backlight="smooth", noise="high", blur=1.3,
         bit_depth=8, container="avi"),
    dict(angle=40.0, elevation=10.0, size=(224, 224), fps=7500.0, bubbles=3, merge=True,
         shape="default", radius_mm=(0.5, 1.5), backlight="gradient", noise="low", blur=0.7,
         bit_depth=12, container="mraw"),
    dict(angle=55.0, elevation=5.0, size=(320, 320), fps=1000.0, bubbles=5, merge=True,
         shape="tilted", radius_mm=(0.4, 1.0), backlight="stripes", noise="mid", blur=1.0,
         bit_depth=16, container="tiff-lzw"),
)  # fmt: skip
#: Sensor noise levels of the bench sessions: (full well electrons, read noise fraction).
NOISE = {"low": (8000.0, 0.002), "mid": (2500.0, 0.003), "high": (700.0, 0.008)}
#: Containers of a session's input videos: a folder of PNGs, multi-page TIFF
#: (uncompressed or LZW), Photron MRAW + CIH (8, 12 packed or 16 bit), and 8-bit video
#: (MPEG-4 Part 2 in .mp4, lossy; FFV1 in .avi, lossless).
CONTAINERS = ("png", "tiff", "tiff-lzw", "mraw", "mp4", "avi")
#: Frame rate written in the header of video containers (a playback rate, as labs export).
VIDEO_PLAYBACK_FPS = 30.0

PRESETS: dict[str, dict] = {
    "demo": {
        "sessions": 2,
        "frames": 24,
        "fps": 1500.0,
        "native": 512,
        "bubbles": 5,
        "clips": 8,
        "clip_frames": 24,
        "mesh_spacing": 7e-5,
        "bit_depth": 8,
        "heldout": True,
    },
    "tiny": {
        "sessions": 1,
        "frames": 6,
        "fps": 1500.0,
        "native": 256,
        "bubbles": 4,
        "clips": 2,
        "clip_frames": 6,
        "mesh_spacing": 1e-4,
        "bit_depth": 8,
        "heldout": True,
    },
    # Varied sessions (BENCH_SESSIONS), one rig each, refinement off: no clips; two
    # held-out views (mid-way, and 90° from cam0: a side view of the depth axis).
    "bench": {
        "sessions": len(BENCH_SESSIONS),
        "frames": 24,
        "fps": 0.0,  # per session
        "native": 0,  # per session
        "bubbles": 0,  # per session
        "clips": 0,
        "clip_frames": 1,
        "mesh_spacing": 5e-5,
        "bit_depth": 0,  # per session
        "heldout": True,
    },
}
PRESETS["bench-mixed"] = dict(PRESETS["bench"])
PRESETS["bench-drawn"] = dict(PRESETS["bench"])
#: The presets of varied sessions, one rig each: ``bench`` (:data:`BENCH_SESSIONS` as
#: they are), ``bench-mixed`` (their settings recombined by the seed) and
#: ``bench-drawn`` (every setting drawn by the seed from the ranges of :data:`DRAWN`;
#: :func:`bench_specs`).
BENCH_PRESETS = ("bench", "bench-mixed", "bench-drawn")
#: The ranges ``bench-drawn`` draws each session's settings from: uniform in ``angle``
#: and ``elevation`` (degrees, rounded to 0.5), native width and height (px, steps of
#: 16), ``fps`` log-uniform (rounded to 250), ``bubbles`` (integers), the smaller
#: detachment radius and the width of the radius range (mm, hi capped at 1.5) and
#: ``blur`` (px, rounded to 0.05); ``merge`` a coin; one of each ``shape``,
#: ``backlight``, ``noise`` and (bit depth, container) pair.
DRAWN: dict = {
    "angle": (25.0, 60.0),
    "elevation": (0.0, 10.0),
    "size": (208, 336),
    "fps": (1000.0, 10000.0),
    "bubbles": (3, 5),
    "radius_lo_mm": (0.3, 0.9),
    "radius_span_mm": (0.3, 0.7),
    "radius_max_mm": 1.5,
    "blur": (0.5, 1.4),
    "pairs": ((8, "mp4"), (8, "avi"), (8, "tiff"), (8, "png"), (12, "mraw"),
              (16, "mraw"), (16, "tiff"), (16, "tiff-lzw")),
}  # fmt: skip
#: What ``bench-mixed`` recombines: each group of :data:`BENCH_SESSIONS`' keys is
#: shuffled across the sessions on its own (a container keeps its bit depth: video is
#: 8 bit).
MIX_GROUPS: tuple[tuple[str, ...], ...] = (
    ("angle",), ("elevation",), ("size",), ("fps",), ("bubbles",), ("merge",), ("shape",),
    ("radius_mm",), ("backlight",), ("noise",), ("blur",), ("bit_depth", "container"),
)  # fmt: skip
#: Settings the bench preset fixes per session (BENCH_SESSIONS), not overridable.
_BENCH_FIXED = ("fps", "native", "bubbles", "bit_depth")
#: Fit scale of the bench preset (its held-out views' size; the workflow's ingest scale).
BENCH_FIT_SCALE = 0.5
#: Held-out cameras rendered by the bench preset.
BENCH_HELDOUT = ("mid", "orbit03")


def campaign_settings(preset: str = "demo", **overrides) -> dict:
    """The preset's settings with ``overrides`` applied (``None`` values ignored)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown synth preset {preset!r}; choose from {sorted(PRESETS)}")
    cfg = dict(PRESETS[preset])
    for k, v in overrides.items():
        if v is None:
            continue
        if k not in cfg:
            raise ValueError(f"unknown synth option {k!r}; known: {sorted(cfg)}")
        if preset in BENCH_PRESETS and k in _BENCH_FIXED:
            raise ValueError(f"synth --preset {preset}: {k} is set per session, not overridable")
        cfg[k] = type(cfg[k])(v)
    if preset in BENCH_PRESETS:
        if not 1 <= cfg["sessions"] <= len(BENCH_SESSIONS):
            raise ValueError(
                f"synth --preset {preset}: sessions must be 1..{len(BENCH_SESSIONS)}, "
                f"got {cfg['sessions']}"
            )
        if cfg["frames"] < 2:
            raise ValueError(f"synth: bench sessions need ≥ 2 frames, got {cfg['frames']}")
        return cfg
    if cfg["sessions"] < 1 or cfg["frames"] < 1 or cfg["clips"] < 0 or cfg["clip_frames"] < 1:
        raise ValueError(f"synth: sessions and frames must be ≥ 1 and clips ≥ 0, got {cfg}")
    if cfg["fps"] <= 0:
        raise ValueError(f"synth: fps must be positive, got {cfg['fps']}")
    if cfg["native"] < 64 or cfg["native"] % 4:
        raise ValueError(
            f"synth: native size must be a multiple of 4 and ≥ 64, got {cfg['native']}"
        )
    if cfg["bubbles"] < 1:
        raise ValueError(f"synth: bubbles must be ≥ 1, got {cfg['bubbles']}")
    if cfg["bit_depth"] not in (8, 16):
        raise ValueError(f"synth: bit depth must be 8 or 16, got {cfg['bit_depth']}")
    return cfg


def session_scene(seed: int, index: int, cfg: dict, spec: dict | None = None) -> BubbleScene:
    """The scene of session ``index`` (0-based). Session 0 always contains a merge;
    with a bench ``spec`` (:data:`BENCH_SESSIONS`), the sessions whose ``merge`` is set
    do, and the others have none."""
    duration = cfg["frames"] / (spec["fps"] if spec else cfg["fps"])
    want_merge = bool(spec["merge"]) if spec else index == 0
    extra = {}
    if spec:
        lo, hi = spec["radius_mm"]
        extra = {"radius_range": (lo * 1e-3, hi * 1e-3), "shape": spec["shape"]}
    for attempt in range(30):
        scene = BubbleScene(
            int(np.random.default_rng([seed, index, attempt]).integers(0, 2**31)),
            duration,
            bubbles=spec["bubbles"] if spec else cfg["bubbles"],
            force_merge=want_merge,
            **extra,
        )
        if want_merge and scene.merges():
            return scene
        if not want_merge and (not spec or not scene.merges()):
            return scene
    what = "arrange a merge" if want_merge else "avoid a merge"
    raise ValueError(f"synth seed {seed}: could not {what} in session {index + 1}")


def bench_specs(preset: str, seed: int) -> tuple[dict, ...]:
    """The varied sessions' settings: :data:`BENCH_SESSIONS` for ``bench``; for
    ``bench-mixed``, each group of :data:`MIX_GROUPS` permuted across the sessions by
    ``seed`` on its own, so every value stays one the preset has, in combinations it
    does not (views 25° apart at 10,000 fps, tilted spheroids on a dim backlight...);
    for ``bench-drawn``, every setting drawn by ``seed`` from :data:`DRAWN`'s ranges
    (:func:`drawn_spec`): values the other two never have."""
    if preset == "bench":
        return BENCH_SESSIONS
    if preset == "bench-drawn":
        return tuple(drawn_spec(seed, i) for i in range(len(BENCH_SESSIONS)))
    if preset != "bench-mixed":
        raise ValueError(f"not a bench preset: {preset!r}; choose from {BENCH_PRESETS}")
    rng = np.random.default_rng([seed, 7331])
    specs = [dict(s) for s in BENCH_SESSIONS]
    for group in MIX_GROUPS:
        order = rng.permutation(len(specs))
        values = [{k: BENCH_SESSIONS[j][k] for k in group} for j in order]
        for spec, v in zip(specs, values, strict=True):
            spec.update(v)
    return tuple(specs)


def drawn_spec(seed: int, index: int) -> dict:
    """Session ``index``'s settings of ``bench-drawn``, drawn from :data:`DRAWN` by
    ``(seed, index)`` (the keys of :data:`BENCH_SESSIONS`' entries)."""
    rng = np.random.default_rng([seed, index, 4242])
    d = DRAWN

    def uniform(lo_hi, step):
        return round(float(round(rng.uniform(*lo_hi) / step) * step), 4)

    side = np.arange(d["size"][0], d["size"][1] + 1, 16)
    lo = uniform(d["radius_lo_mm"], 0.05)
    hi = min(lo + uniform(d["radius_span_mm"], 0.05), d["radius_max_mm"])
    fps = float(np.exp(rng.uniform(*np.log(d["fps"]))))
    bit_depth, container = d["pairs"][int(rng.integers(len(d["pairs"])))]
    return dict(
        angle=uniform(d["angle"], 0.5),
        elevation=uniform(d["elevation"], 0.5),
        size=(int(rng.choice(side)), int(rng.choice(side))),
        fps=float(min(max(round(fps / 250.0) * 250.0, d["fps"][0]), d["fps"][1])),
        bubbles=int(rng.integers(d["bubbles"][0], d["bubbles"][1] + 1)),
        merge=bool(rng.integers(2)),
        shape=str(rng.choice(SHAPES)),
        radius_mm=(round(lo, 2), round(hi, 2)),
        backlight=str(rng.choice(shadowgraph.BACKLIGHTS)),
        noise=str(rng.choice(sorted(NOISE))),
        blur=uniform(d["blur"], 0.05),
        bit_depth=int(bit_depth),
        container=str(container),
    )


def session_spec(cfg: dict, index: int, bench: Sequence[dict] = BENCH_SESSIONS) -> dict:
    """Everything that sets session ``index`` apart: a bench spec (``bench``, as
    :func:`bench_specs` gives them), or the preset's own (square ``native`` frames, the
    reference rig, smooth backlight, PNG folders)."""
    if "native" in cfg and cfg["native"] > 0:
        return dict(
            angle=35.0, elevation=None, size=(cfg["native"], cfg["native"]), fps=cfg["fps"],
            bubbles=cfg["bubbles"], merge=index == 0, shape="default", radius_mm=None,
            backlight="smooth", noise=None, blur=0.8 * cfg["native"] / 512,
            bit_depth=cfg["bit_depth"], container="png", fit_scale=FIT_SCALE, heldout=None,
        )  # fmt: skip
    return {**bench[index], "fit_scale": BENCH_FIT_SCALE, "heldout": BENCH_HELDOUT}


def session_rig(spec: dict) -> dict:
    """True cameras of a session's rig (:func:`surfphase.synth.rig.default_rig`)."""
    w, h = spec["size"]
    kw = {"native": w, "native_height": h, "baseline_deg": spec["angle"]}
    if spec["elevation"] is not None:
        kw["height"] = eye_height(spec["elevation"])
    return default_rig(**kw)


def write_video(path_stem: Path, frames: np.ndarray, container: str, bit_depth: int, fps: float):
    """Write (n, H, W) grey frames (uint8, or uint16 for 12/16 bit) as ``container``
    (:data:`CONTAINERS`); returns the path the sessions sheet names (a folder or file)."""
    n, h, w = frames.shape
    if container == "png":
        for f in range(n):
            write_png(path_stem / f"{f:06d}.png", frames[f])
        return path_stem
    if container in ("tiff", "tiff-lzw"):
        path = path_stem.with_suffix(".tif")
        if bit_depth == 12:
            raise ValueError(f"{path}: 12-bit frames are written as MRAW, not TIFF")
        comp = "lzw" if container == "tiff-lzw" else None
        with atomic_path(path) as tmp:
            tifffile.imwrite(tmp, frames, photometric="minisblack", compression=comp)
        return path
    if container == "mraw":
        return write_mraw(path_stem.with_suffix(".cih"), frames, bit_depth, fps)
    if container in ("mp4", "avi"):
        if bit_depth != 8:
            raise ValueError(f"{path_stem}: video containers hold 8-bit frames only")
        path = path_stem.with_suffix("." + container)
        fourcc = cv2.VideoWriter_fourcc(*("mp4v" if container == "mp4" else "FFV1"))
        # High-speed recordings are exported at a playback rate; the sheet has the fps.
        writer = cv2.VideoWriter(str(path), fourcc, VIDEO_PLAYBACK_FPS, (w, h), True)
        if not writer.isOpened():
            raise OSError(f"{path}: OpenCV cannot write {container} video")
        for f in range(n):
            writer.write(cv2.cvtColor(frames[f], cv2.COLOR_GRAY2BGR))
        writer.release()
        return path
    raise ValueError(f"unknown container {container!r}; choose from {CONTAINERS}")


def _write_session(
    sdir: Path, scene: BubbleScene, cfg: dict, seed: int, index: int, spec: dict
) -> dict:
    fps, frames, bits = spec["fps"], cfg["frames"], spec["bit_depth"]
    (width, height), fit_scale = spec["size"], spec["fit_scale"]
    rig = session_rig(spec)
    gt_cams = {n: rig[n] for n in INPUTS}
    for name, cam in rig.items():
        if name not in INPUTS:
            gt_cams[name] = cam.scaled(fit_scale)
    held = [n for n in gt_cams if n not in INPUTS] if cfg["heldout"] else []
    if spec["heldout"] is not None:
        held = [n for n in held if n in spec["heldout"]]
    gt = sdir / "gt"
    save_cameras(gt / "cameras.json", gt_cams, fps=fps, fit_scale=fit_scale)
    pattern = spec["backlight"]
    noise = NOISE[spec["noise"]] if spec["noise"] else None

    rays, bgs, sizes, sigmas, names = [], [], [], [], []
    for n in INPUTS:
        cam = gt_cams[n]
        rays.append(shadowgraph.camera_rays(cam, distorted=True))
        bgs.append(shadowgraph.background(n, cam.height, cam.width, seed=seed, pattern=pattern))
        sizes.append(None)
        sigmas.append(spec["blur"])
        names.append(n)
    for n in held:
        cam = gt_cams[n].scaled(2.0)  # 2× supersampling, area-averaged down
        rays.append(shadowgraph.camera_rays(cam, distorted=False))
        bgs.append(shadowgraph.background(n, cam.height, cam.width, seed=seed, pattern=pattern))
        sizes.append((gt_cams[n].width, gt_cams[n].height))
        sigmas.append(0.5)
        names.append(n)

    for n, r, bg, size, sigma in zip(names, rays, bgs, sizes, sigmas, strict=True):
        if n not in INPUTS:
            ref = shadowgraph.empty_view(r, bg, size, sigma)
            write_png(gt / "views_background" / f"{n}.png", shadowgraph.quantize(ref, 16))
    masks = {n: np.full((frames, height, width), -1, dtype=np.int32) for n in INPUTS}
    raw = {n: [] for n in INPUTS}
    truths, vol_err = [], []
    t_render = t_truth = 0.0
    for f in range(frames):
        state = scene.state(f / fps)
        t0 = time.perf_counter()
        rngs = [np.random.default_rng([seed, index, ci, f]) for ci in range(len(names))]
        views = shadowgraph.render_views(state, rays, bgs, rngs, sizes, sigmas, noise=noise)
        for n, (img, lab, clean) in zip(names, views, strict=True):
            if n in INPUTS:
                raw[n].append(shadowgraph.quantize(img, bits))
                masks[n][f] = lab
            else:
                q = shadowgraph.quantize(img, bits if bits in (8, 16) else 16)
                write_png(gt / "views" / n / f"{f:06d}.png", q)
                write_png(gt / "views_clean" / n / f"{f:06d}.png", shadowgraph.quantize(clean, 16))
        t1 = time.perf_counter()
        tr = frame_truth(state, spacing=cfg["mesh_spacing"])
        write_ply(gt / "meshes" / f"{f:06d}.ply", tr.verts, tr.faces)
        truths.append(tr)
        if tr.volumes.size:
            vol_err.append(mesh_volume(tr.verts, tr.faces) / tr.volumes.sum() - 1)
        t_truth += time.perf_counter() - t1
        t_render += t1 - t0
    videos = {}
    for n in INPUTS:
        save_npy(gt / "masks" / f"{n}.npy", masks[n])
        path = write_video(sdir / n, np.stack(raw[n]), spec["container"], bits, fps)
        videos[n] = path.relative_to(sdir.parent).as_posix()
    table = bubble_table(truths, fps)
    table.to_csv(gt / "bubbles.csv", index=False, float_format="%.12g", na_rep="nan")
    # First frame at which the merged bubble exists (same test as Bubble.alive).
    merges = [
        (round(t, 9), next((f for f in range(frames) if t <= f / fps), frames), a, b, m)
        for t, a, b, m in scene.merges()
    ]
    pd.DataFrame(merges, columns=["t", "frame", "parent_a", "parent_b", "merged"]).to_csv(
        gt / "merges.csv", index=False, float_format="%.9g"
    )
    per_frame = table.groupby("frame").size().reindex(range(frames), fill_value=0)
    visible = [int(np.unique(m[m >= 0]).size) for m in masks["cam0"]]
    return {
        "videos": videos,
        "spec": {k: v for k, v in spec.items() if k != "heldout"},
        "heldout": held,
        "merges": merges,
        "bubbles_per_frame": per_frame.tolist(),
        "visible_in_cam0_per_frame": visible,
        "mesh_volume_error_pct": [round(100 * min(vol_err), 3), round(100 * max(vol_err), 3)]
        if vol_err
        else None,
        "render_s": round(t_render, 3),
        "truth_s": round(t_truth, 3),
    }


def write_campaign(
    out: Path, preset: str = "demo", seed: int = 0, overwrite: bool = False, **overrides
) -> Path:
    """Write a self-contained synthetic campaign under ``out`` (layout: module docstring).

    Args:
        out: campaign folder; must not exist or be empty, unless ``overwrite``.
        preset: ``"demo"`` (2 sessions, 24 frames at 1500 fps, native 512, 8 clips),
            ``"tiny"`` (1 session, 6 frames, native 256, 2 clips, coarse meshes) or
            ``"bench"`` (:data:`BENCH_SESSIONS`, 24 frames each; ``sessions`` takes the
            first N; fps, native, bubbles and bit_depth are set per session) or
            ``"bench-mixed"`` (the same settings recombined by ``seed``,
            :func:`bench_specs`).
        seed: everything is deterministic in it.
        overrides: ``sessions``, ``frames``, ``fps``, ``native``, ``bubbles``,
            ``clips``, ``clip_frames``, ``mesh_spacing`` (m), ``bit_depth`` (8/16),
            ``heldout`` (render held-out views).

    Returns:
        ``out``.
    """
    cfg = campaign_settings(preset, **overrides)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"{out}: folder exists and is not empty (use --force / overwrite=True)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    try:
        log = _build(tmp, cfg, preset, seed)
        (tmp / "synth.json").write_text(json.dumps(log, indent=1))
        _apply_umask(tmp)
        if out.exists():
            old = out.with_name(f".{out.name}.old{os.getpid()}")
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def _apply_umask(root: Path) -> None:
    """Give the campaign ordinary permissions (temporary names are created private)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(root, 0o777 & ~umask)
    for dirpath, dirnames, filenames in os.walk(root):
        for d in dirnames:
            os.chmod(os.path.join(dirpath, d), 0o777 & ~umask)
        for f in filenames:
            os.chmod(os.path.join(dirpath, f), 0o666 & ~umask)


def _build(root: Path, cfg: dict, preset: str, seed: int) -> dict:
    t_start = time.perf_counter()
    timings: dict[str, float] = {"calibration_s": 0.0}
    board = charuco.board_yaml_dict()
    (root / "board.yaml").write_text(yaml.safe_dump(board, sort_keys=False))
    bench = bench_specs(preset, seed) if preset in BENCH_PRESETS else BENCH_SESSIONS
    specs = [session_spec(cfg, i, bench) for i in range(cfg["sessions"])]
    # The demo and tiny presets share one rig; the bench presets have one per session.
    shared = preset not in BENCH_PRESETS
    rig_rows, rows, sessions = [], [], {}
    for i, spec in enumerate(specs):
        name = f"session{i + 1:02d}"
        rig_name = "rig01" if shared else f"rig{i + 1:02d}"
        if not shared or i == 0:
            rig = session_rig(spec)
            t0 = time.perf_counter()
            charuco.write_calibration_images(
                {n: rig[n] for n in INPUTS}, root / rig_name / "calib", seed if shared else seed + i
            )
            timings["calibration_s"] += round(time.perf_counter() - t0, 3)
            rig_rows.append(
                [rig_name, "board.yaml", f"{rig_name}/calib/cam0", f"{rig_name}/calib/cam1"]
            )
        scene = session_scene(seed, i, cfg, None if shared else spec)
        t0 = time.perf_counter()
        sessions[name] = _write_session(root / name, scene, cfg, seed, i, spec)
        sessions[name]["seconds"] = round(time.perf_counter() - t0, 3)
        fps = spec["fps"]
        fps_text = str(int(fps)) if float(fps).is_integer() else repr(fps)
        vids = sessions[name]["videos"]
        rows.append([name, rig_name, fps_text, "", vids["cam0"], vids["cam1"], f"{name}/gt"])
    pd.DataFrame(rig_rows, columns=["rig", "board", "cam0", "cam1"]).to_csv(
        root / "rigs.tsv", sep="\t", index=False
    )
    pd.DataFrame(rows, columns=["session", "rig", "fps", "frames", "cam0", "cam1", "gt"]).to_csv(
        root / "sessions.tsv", sep="\t", index=False
    )

    t0 = time.perf_counter()
    fit = int(round(cfg["native"] * FIT_SCALE))  # clip size (bench: no clips)
    clips = []
    (root / "clips").mkdir()
    for k in range(cfg["clips"]):
        clip_seed = int(np.random.default_rng([seed, 9001, k]).integers(0, 2**31))
        info = write_clip(
            root / "clips" / f"clip{k:03d}", clip_seed, cfg["clip_frames"], fit, cfg["bit_depth"]
        )
        clips.append(info)
    timings["clips_s"] = round(time.perf_counter() - t0, 3)
    config = {"sessions": "sessions.tsv", "rigs": "rigs.tsv", "prior_clips": "clips", "seed": seed}
    (root / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    timings["total_s"] = round(time.perf_counter() - t_start, 3)
    return {
        "preset": preset,
        "seed": seed,
        "settings": cfg,
        "fit_scale": BENCH_FIT_SCALE if preset in BENCH_PRESETS else FIT_SCALE,
        "sessions": sessions,
        "clips": clips,
        "timings": timings,
    }
