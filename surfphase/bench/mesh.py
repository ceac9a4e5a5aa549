"""``surfphase bench mesh``: Chamfer distance of the meshes to ground-truth meshes.

For each chosen frame: the symmetric Chamfer distance (mm) between the stage's mesh and
the true mesh (:func:`surfphase.eval.geometry.mesh_chamfer`), as a percentage of the
frame's mean true equivalent radius; beside it, two bounds that come from the fit, not
from meshing: the mean distance from the fitted surfels' centres (opacity > 0.5) to the
true surface, and the same for the centres moved onto the surfels' own SDF zero level set
(μ − f·n), the alternative to depth fusion; and ``true_in_fit_to_mesh_mm``, the mean
distance to the mesh from the true points inside the fitted surfels' bounding box (grown
by 0.5 mm), which leaves out true bubbles the fit never reconstructed (e.g. outside the
input views).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial import cKDTree

from surfphase.eval.geometry import mesh_chamfer, read_ply, sample_surface
from surfphase.fit.outputs import load_surfels
from surfphase.mesh.stage import run_mesh


def surfel_distances(surfels: dict, t: int, true_points: np.ndarray) -> dict:
    """Mean distance (mm) from frame position ``t``'s surfels (alive, opacity > 0.5) to
    (M, 3) true surface points (metres): centres, and centres moved by −f·n."""
    from surfphase.render.projection import quat_to_rotmat

    a = surfels["alive"][t] & (surfels["opacity"][t] > 0.5)
    tree = cKDTree(true_points)
    out = {"surfel_to_true_mm": float(tree.query(surfels["means"][t][a])[0].mean() * 1e3)}
    f = surfels["sdf"][t][a]
    if np.isfinite(f).all():
        n = quat_to_rotmat(torch.as_tensor(surfels["quats"][t][a])).numpy()[:, :, 2]
        p = surfels["means"][t][a] - f[:, None] * n
        out["surfel_sdf_to_true_mm"] = float(tree.query(p)[0].mean() * 1e3)
    return out


def bench_mesh(
    fit_dir: str | os.PathLike,
    ingest_dir: str | os.PathLike,
    gt_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    frames: list[int],
    params: dict | None = None,
    device: str = "cpu",
    n_points: int = 20000,
) -> pd.DataFrame:
    """Mesh ``frames`` (positions in surfels.npz) into ``out_dir`` and compare each with
    ``gt_dir/meshes/<frame:06d>.ply`` and ``gt_dir/bubbles.csv``; one row per frame."""
    gt_dir = Path(gt_dir)
    table = gt_dir / "bubbles.csv"
    if not table.exists():
        raise FileNotFoundError(f"{table}: no ground-truth bubble table")
    r_eq = pd.read_csv(table)
    t0 = time.perf_counter()
    summary = run_mesh(fit_dir, ingest_dir, out_dir, {**(params or {}), "frames": frames}, device)
    seconds = time.perf_counter() - t0
    surfels = load_surfels(Path(fit_dir) / "surfels.npz")
    rows = []
    for t, r in zip(frames, summary["frames"], strict=True):
        frame = r["frame"]
        true_ply = gt_dir / "meshes" / f"{frame:06d}.ply"
        cd = mesh_chamfer(Path(out_dir) / f"{frame:06d}.ply", true_ply, n_points, seed=0)
        req_mm = float(r_eq.loc[r_eq["frame"] == frame, "r_eq"].mean() * 1e3)
        vt, ft = read_ply(true_ply)
        vp, fp = read_ply(Path(out_dir) / f"{frame:06d}.ply")
        true_pts = sample_surface(vt, ft, n_points, seed=1)
        alive = surfels["means"][t][surfels["alive"][t]]
        lo, hi = alive.min(0) - 5e-4, alive.max(0) + 5e-4
        inside = true_pts[np.all((true_pts >= lo) & (true_pts <= hi), axis=1)]
        mesh_tree = cKDTree(sample_surface(vp, fp, n_points, seed=0))
        rows.append(
            {
                "frame": frame,
                "chamfer_mm": cd["mean_mm"],
                "mesh_to_true_mm": cd["a_to_b_mm"],
                "true_to_mesh_mm": cd["b_to_a_mm"],
                "r_eq_mean_mm": req_mm,
                "chamfer_pct_r_eq": 100 * cd["mean_mm"] / req_mm,
                "true_in_fit_to_mesh_mm": float(mesh_tree.query(inside)[0].mean() * 1e3),
                **surfel_distances(surfels, t, true_pts),
                "vertices": r["vertices"],
                "components": r["components"],
                "seconds_mesh": r["seconds"],
            }
        )
    df = pd.DataFrame(rows)
    df.attrs["seconds_total"] = seconds
    return df
