"""The independent 2D reference for sessions without ground truth (real data).

The way an experimentalist measures bubble velocity from one high-speed video: track
each bubble's mask centroid ``(u, v)`` in one view, differentiate over time (pixels/s),
and convert pixels to metres with the calibration at the bubble's depth ``Z`` (metres
along the camera's optical axis). With ``Z`` constant over the track, the camera-frame
velocity is ``Z·K⁻¹·(u̇, v̇, 0)``; rotated into the lab frame it is a vector in the
image plane. ``Z`` is the median over the track of the depth of the bubble's
two-view triangulated mask centroid (:mod:`surfphase.eval.baseline`), so the reference
never uses the method's reconstruction.

A 3D velocity ``v`` is compared through its image-plane part ``v − (v·n)·n`` (``n`` the
optical axis): for each lab component ``x`` and ``y``, the relative error is
``mean |v_x − r_x| / mean |r_x|`` over the bubble-frames both know.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from surfphase.cameras import Camera
from surfphase.eval.baseline import finite_difference, mask_centroids

REFERENCE_COLUMNS = ["frame", "time_s", "bubble", "u", "v", "depth_m", "ref_vx", "ref_vy", "ref_vz"]


def reference_velocities(
    camera: Camera,
    labels: np.ndarray,
    frame_indices: np.ndarray,
    fps: float,
    depths: pd.DataFrame,
) -> pd.DataFrame:
    """Per (frame, bubble) image-plane velocity (m/s, lab frame) from one view.

    Args:
        camera: the undistorted camera of ``labels``.
        labels: (T, H, W) int label stack of that view (−1 background).
        frame_indices: (T,) session frame index of each stack position.
        fps: frames per second.
        depths: a table ``frame, bubble, x, y, z`` of 3D bubble positions (m) that
            fixes each bubble's depth (median over its frames); bubbles without one
            are left out.

    Returns:
        :data:`REFERENCE_COLUMNS` (``u, v`` pixels; ``depth_m`` metres).
    """
    frame_indices = np.asarray(frame_indices, dtype=np.int64)
    cen = mask_centroids(labels)
    cen["frame"] = frame_indices[cen["index"].to_numpy()] if len(cen) else []
    cen["time_s"] = cen["frame"] / fps
    d = depths.dropna(subset=["x", "y", "z"])
    zc = camera.world_to_camera(d[["x", "y", "z"]].to_numpy())[:, 2]
    med = pd.Series(zc, index=d["bubble"].to_numpy()).groupby(level=0).median()
    cen = cen[cen["bubble"].isin(med.index)].reset_index(drop=True)
    if cen.empty:
        return pd.DataFrame(columns=REFERENCE_COLUMNS)
    cen["depth_m"] = med.loc[cen["bubble"]].to_numpy()
    uv_dot = finite_difference(
        cen["bubble"].to_numpy(), cen["index"].to_numpy(), cen["time_s"].to_numpy(),
        cen[["u", "v"]].to_numpy(),
    )  # fmt: skip
    Kinv = np.linalg.inv(camera.K)
    v_cam = cen["depth_m"].to_numpy()[:, None] * (uv_dot @ Kinv[:2, :2].T)
    v_cam = np.concatenate([v_cam, np.zeros((len(cen), 1))], axis=1)
    v_world = v_cam @ camera.R  # R^T applied to row vectors
    cen[["ref_vx", "ref_vy", "ref_vz"]] = v_world
    return cen[REFERENCE_COLUMNS].sort_values(["frame", "bubble"]).reset_index(drop=True)


def compare_to_reference(
    pred: pd.DataFrame, reference: pd.DataFrame, camera: Camera
) -> tuple[dict, pd.DataFrame]:
    """Relative errors of a 3D velocity table's image-plane x and y against the reference.

    Args:
        pred: ``frame, bubble, vx, vy, vz`` (m/s, lab frame; bubble ids as the masks').
        reference: output of :func:`reference_velocities`.
        camera: the reference's camera (its optical axis defines the image plane).

    Returns:
        ``({"relative_error_x", "relative_error_y", "mean_abs_error_x_mps",
        "mean_abs_error_y_mps", "matched"}, per-row table)``.
    """
    m = pred[["frame", "bubble", "vx", "vy", "vz"]].merge(
        reference[["frame", "bubble", "ref_vx", "ref_vy", "ref_vz"]], on=["frame", "bubble"]
    )
    v = m[["vx", "vy", "vz"]].to_numpy(np.float64)
    n = camera.view_dir / np.linalg.norm(camera.view_dir)
    vp = v - (v @ n)[:, None] * n
    m[["plane_vx", "plane_vy", "plane_vz"]] = vp
    r = m[["ref_vx", "ref_vy", "ref_vz"]].to_numpy(np.float64)
    ok = np.isfinite(vp).all(axis=1) & np.isfinite(r).all(axis=1)
    m = m[ok].reset_index(drop=True)
    vp, r = vp[ok], r[ok]
    out = {"matched": int(ok.sum())}
    for k, name in ((0, "x"), (1, "y")):
        if ok.any():
            err = np.abs(vp[:, k] - r[:, k])
            denom = np.abs(r[:, k]).mean()
            out[f"mean_abs_error_{name}_mps"] = float(err.mean())
            out[f"relative_error_{name}"] = float(err.mean() / denom) if denom > 0 else float("nan")
        else:
            out[f"mean_abs_error_{name}_mps"] = float("nan")
            out[f"relative_error_{name}"] = float("nan")
    return out, m
