"""A whole synthetic campaign on disk, in the campaign format of docs/campaign.md.

Layout under ``out`` (paths in the TSVs are relative to the TSV's folder)::

    config.yaml            {sessions: sessions.tsv, rigs: rigs.tsv, prior_clips: clips, seed: N}
    sessions.tsv           session, rig, fps, frames (empty = all), cam0, cam1, gt
    rigs.tsv               rig, board, cam0, cam1 (calibration image folders)
    board.yaml             ChArUco board (charuco.board_yaml_dict())
    synth.json             settings, merges and timings of this run (informative)
    rig01/calib/<cam>/poseNNN.png      calibration images (surfphase.synth.charuco)
    <session>/<cam>/000000.png …       raw input videos: native size, true distortion,
                                       8-bit PNG (16-bit with bit_depth=16)
    <session>/gt/cameras.json          all true cameras (cam0/cam1 native with distortion;
                                       mid, orbit01..11 at fit size, no distortion),
                                       top-level "fps" and "fit_scale"
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
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from surfphase.cameras import save_cameras
from surfphase.io import save_npy
from surfphase.synth import charuco, shadowgraph
from surfphase.synth.bubbles import BubbleScene
from surfphase.synth.groundtruth import bubble_table, frame_truth, mesh_volume, write_ply
from surfphase.synth.monoclips import write_clip, write_png
from surfphase.synth.rig import default_rig

#: Downscale from native raw frames to the fit size (the workflow's ingest scale).
FIT_SCALE = 0.25
INPUTS = ("cam0", "cam1")

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
}


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
        cfg[k] = type(cfg[k])(v)
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


def session_scene(seed: int, index: int, cfg: dict) -> BubbleScene:
    """The scene of session ``index`` (0-based). Session 0 always contains a merge."""
    duration = cfg["frames"] / cfg["fps"]
    want_merge = index == 0
    for attempt in range(30):
        scene = BubbleScene(
            int(np.random.default_rng([seed, index, attempt]).integers(0, 2**31)),
            duration,
            bubbles=cfg["bubbles"],
            force_merge=want_merge,
        )
        if not want_merge or scene.merges():
            return scene
    raise ValueError(f"synth seed {seed}: could not arrange a merge in session 1")


def _write_session(sdir: Path, scene: BubbleScene, cfg: dict, seed: int, index: int) -> dict:
    native, fps, frames = cfg["native"], cfg["fps"], cfg["frames"]
    fit = int(round(native * FIT_SCALE))
    rig = default_rig(native=native)
    gt_cams = {n: rig[n] for n in INPUTS}
    for name, cam in rig.items():
        if name not in INPUTS:
            gt_cams[name] = cam.scaled(FIT_SCALE)
    held = [n for n in gt_cams if n not in INPUTS] if cfg["heldout"] else []
    gt = sdir / "gt"
    save_cameras(gt / "cameras.json", gt_cams, fps=fps, fit_scale=FIT_SCALE)

    rays, bgs, sizes, sigmas, names = [], [], [], [], []
    for n in INPUTS:
        cam = gt_cams[n]
        rays.append(shadowgraph.camera_rays(cam, distorted=True))
        bgs.append(shadowgraph.background(n, cam.height, cam.width, seed=seed))
        sizes.append(None)
        sigmas.append(0.8 * native / 512)
        names.append(n)
    for n in held:
        cam = gt_cams[n].scaled(2.0)  # 2× supersampling, area-averaged down
        rays.append(shadowgraph.camera_rays(cam, distorted=False))
        bgs.append(shadowgraph.background(n, cam.height, cam.width, seed=seed))
        sizes.append((fit, fit))
        sigmas.append(0.5)
        names.append(n)

    for n, r, bg, size, sigma in zip(names, rays, bgs, sizes, sigmas, strict=True):
        if n not in INPUTS:
            ref = shadowgraph.empty_view(r, bg, size, sigma)
            write_png(gt / "views_background" / f"{n}.png", shadowgraph.quantize(ref, 16))
    masks = {n: np.full((frames, native, native), -1, dtype=np.int32) for n in INPUTS}
    truths, vol_err = [], []
    t_render = t_truth = 0.0
    for f in range(frames):
        state = scene.state(f / fps)
        t0 = time.perf_counter()
        rngs = [np.random.default_rng([seed, index, ci, f]) for ci in range(len(names))]
        views = shadowgraph.render_views(state, rays, bgs, rngs, sizes, sigmas)
        for n, (img, lab, clean) in zip(names, views, strict=True):
            q = shadowgraph.quantize(img, cfg["bit_depth"])
            if n in INPUTS:
                write_png(sdir / n / f"{f:06d}.png", q)
                masks[n][f] = lab
            else:
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
    for n in INPUTS:
        save_npy(gt / "masks" / f"{n}.npy", masks[n])
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
        preset: ``"demo"`` (2 sessions, 24 frames at 1500 fps, native 512, 8 clips)
            or ``"tiny"`` (1 session, 6 frames, native 256, 2 clips, coarse meshes).
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
    timings: dict[str, float] = {}
    board = charuco.board_yaml_dict()
    (root / "board.yaml").write_text(yaml.safe_dump(board, sort_keys=False))
    rig = default_rig(native=cfg["native"])
    t0 = time.perf_counter()
    charuco.write_calibration_images({n: rig[n] for n in INPUTS}, root / "rig01" / "calib", seed)
    timings["calibration_s"] = round(time.perf_counter() - t0, 3)
    pd.DataFrame(
        [["rig01", "board.yaml", "rig01/calib/cam0", "rig01/calib/cam1"]],
        columns=["rig", "board", "cam0", "cam1"],
    ).to_csv(root / "rigs.tsv", sep="\t", index=False)

    rows, sessions = [], {}
    for i in range(cfg["sessions"]):
        name = f"session{i + 1:02d}"
        scene = session_scene(seed, i, cfg)
        t0 = time.perf_counter()
        sessions[name] = _write_session(root / name, scene, cfg, seed, i)
        sessions[name]["seconds"] = round(time.perf_counter() - t0, 3)
        fps = cfg["fps"]
        fps_text = str(int(fps)) if float(fps).is_integer() else repr(fps)
        rows.append([name, "rig01", fps_text, "", f"{name}/cam0", f"{name}/cam1", f"{name}/gt"])
    pd.DataFrame(rows, columns=["session", "rig", "fps", "frames", "cam0", "cam1", "gt"]).to_csv(
        root / "sessions.tsv", sep="\t", index=False
    )

    t0 = time.perf_counter()
    fit = int(round(cfg["native"] * FIT_SCALE))
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
        "fit_scale": FIT_SCALE,
        "sessions": sessions,
        "clips": clips,
        "timings": timings,
    }
