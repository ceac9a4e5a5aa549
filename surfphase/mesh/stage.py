"""The mesh stage: one PLY mesh per fitted frame, with per-vertex velocity.

``OUT/<frame:06d>.ply`` — binary PLY, vertex ``x y z`` (float32, metres, lab frame),
``vx vy vz`` (float32, m/s: the velocity of the nearest alive surfel) and ``red green
blue`` (uchar: viridis over [0, ``speed_max``] m/s); triangle faces.
``OUT/mesh.json`` — the parameters used and, per frame, ``frame``, ``vertices``,
``faces``, ``components``, ``watertight``, ``seconds``.

Method: the frame's alive surfels are rendered (median depth where alpha > 0.5) into the
input cameras and ``n_orbit`` orbit views about the surfels' mean (30° steps about the
lab +y axis from the first input camera), fused into a truncated signed distance volume
(:mod:`surfphase.mesh.fuse`), meshed by marching cubes and cleaned with pymeshlab
(:mod:`surfphase.mesh.cleanup`).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from surfphase.cameras import Camera, load_cameras, orbit_cameras
from surfphase.fit.outputs import load_surfels
from surfphase.io import atomic_write_json
from surfphase.mesh.cleanup import clean_mesh, mesh_stats
from surfphase.mesh.fuse import fuse_depths, marching_cubes_mesh, render_depths, voxel_grid
from surfphase.mesh.ply import speed_colors, write_mesh_ply

DEFAULTS: dict = {
    "voxels": 64,  # voxels along the longest side of the surfels' bounding box
    "voxel_m": None,  # or an explicit voxel edge, metres (overrides "voxels")
    "trunc_voxels": 3.0,  # truncation τ, in voxels
    "margin_voxels": 4.0,  # grid margin around the surfels' bounding box, in voxels
    "render_scale": 2.0,  # depth maps rendered at this multiple of the input size
    "opacity_min": 0.1,  # surfels below this are left out of the depth maps ...
    "solid": True,  # ... the others rendered opaque, so thin shells block the view
    "scale_factor": 1.5,  # surfel sizes ×this for the depth maps (closes pinholes)
    "alpha_min": 0.5,  # pixels with more accumulated alpha get the median depth
    "silhouette_alpha": 0.05,  # silhouette (holes filled) threshold; see render_depths
    "n_orbit": 11,
    "orbit_step_deg": 30.0,
    "min_component_m": 3.0e-4,  # components with a smaller bounding-box diagonal go
    "smooth_steps": 5,  # Taubin steps
    "max_hole_edges": 30,
    "speed_max": 0.4,  # m/s, top of the colour map; "session" = max vertex speed seen
    "frames": None,  # positions (0-based) in surfels.npz; None = all
}


def mesh_params(params: dict | None) -> dict:
    """Defaults updated with ``params``; unknown keys are an error."""
    p = dict(DEFAULTS)
    for k, v in (params or {}).items():
        if k not in DEFAULTS:
            raise ValueError(f"mesh: unknown parameter {k!r} (known: {sorted(DEFAULTS)})")
        p[k] = v
    return p


def vertex_velocities(
    verts: np.ndarray, surfel_means: np.ndarray, surfel_velocity: np.ndarray
) -> np.ndarray:
    """(V, 3) velocity (m/s) of each vertex: that of the nearest surfel ((N, 3) metres,
    (N, 3) m/s)."""
    if len(verts) == 0:
        return np.zeros((0, 3))
    _, idx = cKDTree(surfel_means).query(verts)
    return np.asarray(surfel_velocity, np.float64)[idx]


def view_cameras(inputs: list[Camera], center: np.ndarray, p: dict) -> list[Camera]:
    """Input cameras plus orbit views about ``center``, all scaled by ``render_scale``."""
    cams = [c.undistorted() for c in inputs]
    if int(p["n_orbit"]) > 0:
        cams += orbit_cameras(cams[0], center, int(p["n_orbit"]), float(p["orbit_step_deg"]))
    return [c.scaled(float(p["render_scale"])) for c in cams]


def mesh_frame(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity: np.ndarray,
    inputs: list[Camera],
    p: dict,
    device: str = "cpu",
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh of one frame's surfels ((N, 3) m, (N, 4), (N, 2) ln m, (N,)) seen by the
    input cameras; returns (V, 3) vertices (metres) and (F, 3) faces."""
    extent = float(np.ptp(means, axis=0).max())
    voxel = float(p["voxel_m"]) if p["voxel_m"] else extent / float(p["voxels"])
    trunc = float(p["trunc_voxels"]) * voxel
    cams = view_cameras(inputs, means.mean(0), p)
    keep = opacity >= float(p["opacity_min"])
    if keep.sum() < 4:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    depths = render_depths(
        means[keep],
        quats[keep],
        log_scales[keep] + np.log(float(p["scale_factor"])),
        np.ones(int(keep.sum())) if p["solid"] else opacity[keep],
        cams,
        device,
        p["alpha_min"],
        p["silhouette_alpha"],
    )
    origin, shape = voxel_grid(means, voxel, float(p["margin_voxels"]) * voxel)
    sdf = fuse_depths(depths, cams, origin, shape, voxel, trunc)
    verts, faces = marching_cubes_mesh(sdf, origin, voxel)
    return clean_mesh(
        verts,
        faces,
        float(p["min_component_m"]),
        int(p["smooth_steps"]),
        int(p["max_hole_edges"]),
    )


def run_mesh(
    fit_dir: str | os.PathLike,
    ingest_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    params: dict | None = None,
    device: str = "auto",
) -> dict:
    """Mesh every fitted frame of a session; write ``OUT/<frame:06d>.ply`` and
    ``OUT/mesh.json`` (see the module docstring); return the mesh.json content."""
    from surfphase.device import resolve_device

    p = mesh_params(params)
    dev = str(resolve_device(device))
    fit_dir, ingest_dir, out_dir = Path(fit_dir), Path(ingest_dir), Path(out_dir)
    surfels = load_surfels(fit_dir / "surfels.npz")
    cam_path = ingest_dir / "cameras.json"
    if not cam_path.exists():
        raise FileNotFoundError(f"{cam_path}: no cameras.json in the ingest folder")
    cams = load_cameras(cam_path)
    names = [str(c) for c in np.atleast_1d(surfels.get("cameras", []))]
    inputs = [cams[n] for n in names if n in cams] or [
        c for c in cams.values() if c.role == "input"
    ]
    if not inputs:
        raise ValueError(f"{cam_path}: no input cameras")
    session = None
    meta_path = ingest_dir / "meta.json"
    if meta_path.exists():
        session = json.loads(meta_path.read_text()).get("session")

    n_frames = surfels["alive"].shape[0]
    picks = range(n_frames) if p["frames"] is None else [int(t) for t in p["frames"]]
    for t in picks:
        if not 0 <= t < n_frames:
            raise ValueError(f"{fit_dir}: frame position {t} outside 0..{n_frames - 1}")
    meshes = []
    for t in picks:
        t0 = time.perf_counter()
        a = surfels["alive"][t]
        if a.sum() < 4:
            verts, faces = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        else:
            verts, faces = mesh_frame(
                surfels["means"][t][a],
                surfels["quats"][t][a],
                surfels["log_scales"][t][a],
                surfels["opacity"][t][a],
                inputs,
                p,
                dev,
            )
            vel = vertex_velocities(verts, surfels["means"][t][a], surfels["velocity"][t][a])
        if len(verts) == 0:
            vel = np.zeros((0, 3))
        meshes.append((t, verts, faces, vel, time.perf_counter() - t0))

    if p["speed_max"] == "session":
        speeds = [np.linalg.norm(m[3], axis=1).max() for m in meshes if len(m[3])]
        vmax = float(max(speeds)) if speeds and max(speeds) > 0 else 1.0
    else:
        vmax = float(p["speed_max"])
    rows = []
    for t, verts, faces, vel, secs in meshes:
        t1 = time.perf_counter()
        frame = int(surfels["frame"][t])
        colors = speed_colors(np.linalg.norm(vel, axis=1), vmax)
        write_mesh_ply(out_dir / f"{frame:06d}.ply", verts, faces, vel, colors)
        rows.append(
            {
                "frame": frame,
                "vertices": len(verts),
                "faces": len(faces),
                **mesh_stats(faces, len(verts)),
                "seconds": secs + time.perf_counter() - t1,
            }
        )
    summary = {
        "session": session,
        "units": "metres, m/s",
        "speed_max": vmax,
        "device": dev,
        "params": p,
        "frames": rows,
    }
    atomic_write_json(out_dir / "mesh.json", summary)
    return summary
