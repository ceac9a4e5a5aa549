"""``surfphase bench accuracy``: the default workflow on the varied synthetic preset,
scored against the truth beside the classical two-view baseline.

Steps (:func:`run_accuracy_bench`):

1. the campaign: ``surfphase synth --preset bench`` (or a given one), written once;
2. the workflow on it with the config ``surfphase new-campaign`` writes (the project's
   ``config/config.yaml``) and :data:`BENCH_CONFIG` on top — refinement off, ingest
   scale 0.5 (the preset's native frames are 192–320 px) — through its ``evaluate``
   stage (:func:`write_run_campaign`, then ``surfphase run``);
3. the classical baseline at the recordings' native resolution: the session ingested at
   scale 1 with the calibrated cameras, masked with the same ``masks:`` settings, mask
   centroids triangulated (:func:`surfphase.eval.baseline.baseline_bubbles`), velocities
   raw (finite differences) and smoothed along each track
   (:func:`surfphase.eval.baseline.smoothed_velocity`), the smoothing's window (seconds)
   and order chosen on a grid to minimise the baseline's own mean relative velocity
   error over the sessions scored (an oracle choice: the strongest bar);
4. per session the metrics of :func:`session_metrics` from the workflow's outputs
   (``fit/bubbles.csv``, ``mesh/*.ply``, ``evaluate/metrics.json``) and the truth
   (``gt/``), then one table: a row per session, the mean and the worst.

Matching (velocities, precision and recall): per frame, reported and true centroids are
paired one-to-one by the Hungarian algorithm on ``distance / r_eq`` of the true bubble,
gated at :data:`GATE_R_EQ` (0.5 r_eq) before the assignment
(:func:`surfphase.eval.velocity.gated_assignment`: most pairs within the gate first). Reported bubble-frames are the rows of the fit's
``bubbles.csv``: ids ≥ 1 count as real when matched, the nucleation region (id 0) when a
true bubble is attached to the plate in that frame (its surface within
:data:`ATTACHED_R_EQ` r_eq of it). Recall is over the free (not attached) true
bubble-frames seen in both input views (gt masks). Surfaces are compared on area-uniform
samples (:func:`surfphase.eval.geometry.sample_surface`): each true sample belongs to the
true bubble nearest in ``distance / r_eq`` to its centroid.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from scipy.spatial import cKDTree

from surfphase.eval import baseline as bl
from surfphase.eval import velocity
from surfphase.eval.geometry import chamfer, read_ply, sample_surface
from surfphase.mesh.measure import signed_volume, vertex_components

#: Matching gate between reported and true centroids, in r_eq of the true bubble.
GATE_R_EQ = 0.5
#: A mesh point counts as on the surface within this many r_eq of the nearest true bubble.
NEAR_R_EQ = 0.25
#: A true bubble is attached when its surface comes within this many r_eq of the plate.
ATTACHED_R_EQ = 0.05
#: A mesh component (connected piece) belongs to the true bubble most of its surface
#: samples are nearest, counting samples within this many r_eq of that bubble's surface
#: (for volume and extent); a component with none belongs to no bubble.
COMPONENT_R_EQ = 1.0
#: Surface samples per mesh and per true surface in each frame.
SAMPLES = 20000
#: Config on top of ``surfphase new-campaign``'s defaults.
BENCH_CONFIG = {"ingest": {"scale": 0.5}, "refine": {"enabled": False}}
#: Grid of the baseline's track smoothing: windows (s) and polynomial orders.
SMOOTH_WINDOWS_S = (1e-3, 2e-3, 3e-3, 5e-3, 8e-3, 12e-3, 20e-3)
SMOOTH_ORDERS = (1, 2, 3)

XYZ, VEL = ["x", "y", "z"], ["vx", "vy", "vz"]


# --- metric functions (pure) ------------------------------------------------------------


def detection(
    pred: pd.DataFrame,
    truth: pd.DataFrame,
    seen_both: dict[int, set[int]],
    attached: dict[int, set[int]],
    gate_r_eq: float = GATE_R_EQ,
) -> dict:
    """Precision and recall of reported bubble-frames.

    Args:
        pred: reported rows ``frame, bubble, x, y, z`` (m); bubble 0 = nucleation region.
        truth: true rows ``frame, bubble, x, y, z, r_eq`` (m).
        seen_both: ``{frame: ids of true bubbles seen in both input views}``.
        attached: ``{frame: ids of true bubbles attached to the plate}``.
        gate_r_eq: matching gate, r_eq of the true bubble.

    Returns:
        ``precision`` (real reported / reported), ``recall`` (reported free true
        bubble-frames seen in both views / all of them), and the counts ``reported``,
        ``real``, ``free_seen``, ``free_found`` (NaN ratios when a count is 0).
    """
    reported = real = free_seen = free_found = 0
    frames = sorted(set(pred["frame"].astype(int)) | set(truth["frame"].astype(int)))
    for f in frames:
        p = pred[pred["frame"] == f]
        g = truth[truth["frame"] == f]
        nuc = p[p["bubble"] == 0]
        bub = p[p["bubble"] >= 1]
        reported += len(nuc) + len(bub)
        if len(nuc) and attached.get(f):
            real += len(nuc)
        matched_true: set[int] = set()
        if len(bub) and len(g):
            d = np.linalg.norm(
                bub[XYZ].to_numpy(np.float64)[:, None] - g[XYZ].to_numpy(np.float64)[None], axis=-1
            )
            cost = d / g["r_eq"].to_numpy(np.float64)[None]
            for _, j in velocity.gated_assignment(cost, gate_r_eq):
                real += 1
                matched_true.add(int(g["bubble"].iloc[j]))
        free = set(seen_both.get(f, set())) - set(attached.get(f, set()))
        free &= set(g["bubble"].astype(int))
        free_seen += len(free)
        free_found += len(free & matched_true)
    return {
        "precision": real / reported if reported else math.nan,
        "recall": free_found / free_seen if free_seen else math.nan,
        "reported": reported,
        "real": real,
        "free_seen": free_seen,
        "free_found": free_found,
    }


def label_points(points: np.ndarray, centroids: np.ndarray, r_eq: np.ndarray) -> np.ndarray:
    """(N,) index of the bubble nearest each of (N, 3) points in ``|p − c| / r_eq``
    (centroids (B, 3) m, r_eq (B,) m); −1 for every point when B = 0."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(centroids) == 0:
        return np.full(len(P), -1)
    d = np.linalg.norm(P[:, None] - np.asarray(centroids)[None], axis=-1)
    return np.argmin(d / np.asarray(r_eq)[None], axis=1)


def extent_ratio(points: np.ndarray, along: np.ndarray) -> float:
    """Extent (max − min of the projections) of (N, 3) ``points`` along the horizontal
    unit direction ``along`` over their extent along the horizontal direction across it
    (``up × along``, up = lab +y)."""
    a = np.asarray(along, dtype=np.float64)
    a = a / np.linalg.norm(a)
    across = np.cross([0.0, 1.0, 0.0], a)
    across /= np.linalg.norm(across)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ext_across = np.ptp(P @ across)
    return float(np.ptp(P @ a) / ext_across) if ext_across > 0 else math.nan


def horizontal_bisector(view_dirs: Sequence[np.ndarray]) -> np.ndarray:
    """Unit horizontal direction bisecting the input cameras' viewing directions."""
    d = np.sum([np.asarray(v, dtype=np.float64) / np.linalg.norm(v) for v in view_dirs], axis=0)
    d[1] = 0.0
    n = np.linalg.norm(d)
    if n < 1e-9:
        raise ValueError("the cameras' viewing directions have no horizontal bisector")
    return d / n


def mesh_components(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) connected-component id of each triangle (triangles sharing a vertex)."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return vertex_components(faces, len(verts))[faces[:, 0]]


@dataclass
class TrueFrame:
    """The truth of one frame: surface samples and the bubbles they belong to.

    Attributes:
        ids, centroids (B, 3) m, r_eq (B,) m, volumes (B,) m³ (= 4/3 π r_eq³);
        points (N, 3) m samples of the true surface, label (N,) index into ids;
        seen (B,) bool: seen in both input views; attached (B,) bool.
    """

    ids: np.ndarray
    centroids: np.ndarray
    r_eq: np.ndarray
    points: np.ndarray
    label: np.ndarray
    seen: np.ndarray
    attached: np.ndarray

    @property
    def volumes(self) -> np.ndarray:
        return 4.0 / 3.0 * np.pi * self.r_eq**3


def true_frame(
    rows: pd.DataFrame,
    verts: np.ndarray,
    faces: np.ndarray,
    seen_ids: set[int],
    n: int = SAMPLES,
    seed: int = 0,
) -> TrueFrame:
    """:class:`TrueFrame` from the truth's ``bubbles.csv`` rows of one frame, its mesh
    (metres) and the ids both input views see."""
    ids = rows["bubble"].to_numpy(np.int64)
    cen = rows[XYZ].to_numpy(np.float64)
    r = rows["r_eq"].to_numpy(np.float64)
    if len(faces) and len(ids):
        pts = sample_surface(verts, faces, n, seed)
        lab = label_points(pts, cen, r)
    else:
        pts, lab = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    attached = np.zeros(len(ids), dtype=bool)
    for b in range(len(ids)):
        ys = pts[lab == b, 1]
        attached[b] = bool(ys.size and ys.min() < ATTACHED_R_EQ * r[b])
    seen = np.array([int(i) in seen_ids for i in ids], dtype=bool)
    return TrueFrame(ids, cen, r, pts, lab, seen, attached)


def frame_surface_metrics(
    tf: TrueFrame,
    mesh: tuple[np.ndarray, np.ndarray] | None,
    bisector: np.ndarray,
    n: int = SAMPLES,
    seed: int = 1,
) -> dict:
    """Surface metrics of one frame's mesh against the truth.

    Returns ``chamfer_mm`` (whole mesh vs the whole surfaces of the true bubbles seen in
    both views; NaN when either is empty), ``r_eq_mm`` (their mean r_eq), ``near`` (share
    of mesh samples within :data:`NEAR_R_EQ` r_eq of any true surface, r_eq of the
    nearest sample's bubble; NaN without a mesh), and per seen true bubble ``bubbles``:
    ``[(id, volume error, extent ratio pred / truth)]`` (volume error ``V/V_true − 1``
    of the mesh components it owns (:data:`COMPONENT_R_EQ`), −1 when none; ratio NaN
    then). A mesh that joins several bubbles in one piece gives its whole volume to one.
    """
    vis = np.flatnonzero(tf.seen)
    vis_pts = tf.points[np.isin(tf.label, vis)]
    out = {
        "chamfer_mm": math.nan,
        "r_eq_mm": float(tf.r_eq[vis].mean() * 1e3) if vis.size else math.nan,
        "near": math.nan,
        "bubbles": [],
    }
    has_mesh = mesh is not None and len(mesh[1]) > 0
    if has_mesh:
        verts, faces = mesh
        pts = sample_surface(verts, faces, n, seed)
        if len(vis_pts):
            out["chamfer_mm"] = chamfer(pts, vis_pts)["mean_mm"]
        comp = mesh_components(verts, faces)
        comp_of_sample = _sample_components(verts, faces, comp, pts)
        if len(tf.points):
            d, j = cKDTree(tf.points).query(pts)
            r_near = tf.r_eq[tf.label[j]]
            out["near"] = float(np.mean(d <= NEAR_R_EQ * r_near))
            voter = np.where(d <= COMPONENT_R_EQ * r_near, tf.label[j], -1)
        else:
            out["near"] = 0.0
            voter = np.full(len(pts), -1)
        owner = _component_owners(comp, comp_of_sample, voter)
    for b in vis:
        true_ratio = extent_ratio(tf.points[tf.label == b], bisector)
        vol_err, ratio = -1.0, math.nan
        if has_mesh:
            mine = [c for c, o in owner.items() if o == b]
            if mine:
                vol = sum(abs(signed_volume(verts, faces[comp == c])) for c in mine)
                vol_err = vol / tf.volumes[b] - 1.0
                sel = np.isin(comp_of_sample, mine)
                if sel.sum() >= 4:
                    ratio = extent_ratio(pts[sel], bisector) / true_ratio
        out["bubbles"].append((int(tf.ids[b]), float(vol_err), float(ratio)))
    return out


def _sample_components(verts, faces, comp, pts) -> np.ndarray:
    """Component of each surface sample (that of the nearest triangle centre)."""
    centres = np.asarray(verts)[np.asarray(faces)].mean(axis=1)
    return comp[cKDTree(centres).query(pts)[1]]


def _component_owners(comp, comp_of_sample, voter) -> dict[int, int]:
    """``{component: index of its true bubble, or −1}``: the true bubble most of the
    component's surface samples lie near (``voter``: each sample's bubble when within
    :data:`COMPONENT_R_EQ` r_eq of that bubble's surface, else −1); −1 when none is."""
    out = {}
    for c in np.unique(comp):
        v = voter[(comp_of_sample == c) & (voter >= 0)]
        out[int(c)] = int(np.bincount(v).argmax()) if v.size else -1
    return out


def velocity_scores(pred: pd.DataFrame, truth: pd.DataFrame, gate_r_eq: float = GATE_R_EQ):
    """Relative error, mean |error| (m/s) and per-component mean |error| of the reported
    bubbles (ids ≥ 1) matched to the truth within ``gate_r_eq``."""
    m = velocity.match_bubbles_relative(pred[pred["bubble"] >= 1], truth, gate_r_eq)
    e = velocity.velocity_errors(m)
    return {
        "relative_error": e["relative_error"],
        "mean_abs_error_mps": e["mean_abs_error_mps"],
        "matched": e["matched"],
        **{f"abs_{k}": v for k, v in velocity.component_errors(m).items()},
    }


def smoothed_table(base: pd.DataFrame, fps: float, window_s: float, order: int) -> pd.DataFrame:
    """The baseline's table with velocities from track smoothing (window s, order)."""
    out = base.copy()
    if len(out):
        out[VEL] = bl.smoothed_velocity(
            out["bubble"].to_numpy(), out["frame"].to_numpy(), out["time_s"].to_numpy(),
            out[XYZ].to_numpy(), fps, window_s, order,
        )  # fmt: skip
    return out


def method_track_table(
    fit_dir: Path, window_s: float, order: int, min_track_frames: int | None = None
) -> pd.DataFrame:
    """The method's ``bubbles.csv`` as ``fit: track_window_s = window_s`` (and
    ``track_order``) writes it, computed from the same fit's ``surfels.npz`` and, when
    the session's masks have them (``fit: anchor_centres``), their ``anchors.csv``
    (:func:`surfphase.fit.outputs.bubble_table`, :func:`~surfphase.fit.outputs.anchored_table`:
    the table is a function of these)."""
    from surfphase.fit.outputs import anchored_table, bubble_table, nucleation_frames, read_anchors
    from surfphase.folders.fit import read_fit_surfels
    from surfphase.folders.ingest import read_ingest
    from surfphase.folders.masks import read_masks

    arrays = read_fit_surfels(fit_dir)
    # The workflow's layout: results/<session>/{ingest,masks,fit}.
    ingest = read_ingest(Path(fit_dir).parent / "ingest")
    masks = Path(fit_dir).parent / "masks"
    anchors = read_anchors(masks / "anchors.csv", ingest.session)
    if anchors is None:
        return bubble_table(arrays, arrays["time_s"], arrays["frame"], window_s, order)
    labels = list(read_masks(masks, ingest.input_cameras(), ingest.session).labels.values())
    frames = np.asarray(arrays["frame"], dtype=np.int64)
    nuc = nucleation_frames(labels, frames)
    table = bubble_table(arrays, arrays["time_s"], frames)
    if min_track_frames is None:
        from surfphase.fit.stage import DEFAULTS

        min_track_frames = int(DEFAULTS["min_track_frames"])
    return anchored_table(table, anchors, nuc, window_s, order, min_track_frames, len(frames))


def track_consistency(pred: pd.DataFrame) -> float:
    """Mean |d/dt centroid − velocity| (m/s) over bubble-frames (ids ≥ 1) inside a run of
    the same id: the centroid track's own central difference against the reported
    velocity (0 when a user who differentiates the trajectory gets the same velocity)."""
    errs = []
    for _, g in pred[pred["bubble"] >= 1].sort_values("frame").groupby("bubble"):
        f = g["frame"].to_numpy()
        t = g["time_s"].to_numpy()
        x = g[XYZ].to_numpy(np.float64)
        v = g[VEL].to_numpy(np.float64)
        for i in range(1, len(g) - 1):
            if f[i - 1] == f[i] - 1 and f[i + 1] == f[i] + 1:
                d = (x[i + 1] - x[i - 1]) / (t[i + 1] - t[i - 1])
                if np.isfinite(v[i]).all():
                    errs.append(float(np.linalg.norm(d - v[i])))
    return float(np.mean(errs)) if errs else math.nan


def choose_method_smoothing(
    fits: dict[str, Path], truth: dict[str, pd.DataFrame]
) -> tuple[tuple[float, int], pd.DataFrame]:
    """As :func:`choose_smoothing`, for the method's own tracks (``fit: track_window_s``)."""
    return _best_on_grid(
        lambda w, o: [
            velocity_scores(method_track_table(d, w, o), truth[s])["relative_error"]
            for s, d in fits.items()
        ],
        SMOOTH_WINDOWS_S,
        SMOOTH_ORDERS,
    )


# --- one session ----------------------------------------------------------------------


def seen_in_both(masks: Sequence[np.ndarray]) -> dict[int, set[int]]:
    """``{frame: ids ≥ 1 present in every (T, H, W) label stack}``."""
    out = {}
    for f in range(min(len(m) for m in masks)):
        sets = [set(np.unique(np.asarray(m[f]))) for m in masks]
        out[f] = {int(i) for i in set.intersection(*sets) if i >= 1}
    return out


def session_metrics(
    session: str,
    gt_dir: Path,
    fit_dir: Path,
    mesh_dir: Path,
    evaluate_dir: Path,
    baseline_raw: pd.DataFrame | None,
    n: int = SAMPLES,
) -> dict:
    """Every column of the table for one session (see the module docstring), plus the
    per-frame figures behind them. ``baseline_raw``: the native-resolution baseline
    (:func:`surfphase.eval.baseline.baseline_bubbles`), scored here raw."""
    from surfphase.cameras import load_cameras

    truth = pd.read_csv(gt_dir / "bubbles.csv")
    cams = load_cameras(gt_dir / "cameras.json")
    bisector = horizontal_bisector([cams["cam0"].view_dir, cams["cam1"].view_dir])
    masks = [np.load(gt_dir / "masks" / f"{c}.npy", mmap_mode="r") for c in ("cam0", "cam1")]
    seen = seen_in_both(masks)
    row: dict = {"session": session}
    pred = None
    bubbles_csv = fit_dir / "bubbles.csv"
    if bubbles_csv.is_file():
        pred = pd.read_csv(bubbles_csv)
    else:
        row["error"] = f"session {session}: {bubbles_csv} missing (the workflow failed)"
    frames = range(len(masks[0]))
    tfs, surf = {}, []
    for f in frames:
        g = truth[truth["frame"] == f]
        verts, faces = read_ply(gt_dir / "meshes" / f"{f:06d}.ply")
        tfs[f] = true_frame(g, verts, faces, seen.get(f, set()), n=n, seed=f)
        ply = mesh_dir / f"{f:06d}.ply"
        mesh = read_ply(ply) if ply.is_file() else None
        if pred is not None:
            surf.append(frame_surface_metrics(tfs[f], mesh, bisector, n=n, seed=10_000 + f))
    attached = {f: {int(i) for i in tf.ids[tf.attached]} for f, tf in tfs.items()}
    if pred is not None:
        row["method"] = velocity_scores(pred, truth)
        row["detection"] = detection(pred, truth, seen, attached)
        ch = [s["chamfer_mm"] for s in surf]
        req = [s["r_eq_mm"] for s in surf]
        row["chamfer_mm"] = _nanmean(ch)
        row["chamfer_pct_r_eq"] = _nanmean(
            [100 * c / r for c, r in zip(ch, req, strict=True) if np.isfinite(c * r)]
        )
        row["near_share"] = _nanmean([s["near"] for s in surf])
        per_bubble = [b for s in surf for b in s["bubbles"]]
        row["volume_error_pct"] = _nanmean([100 * abs(v) for _, v, _ in per_bubble])
        row["extent_ratio_vs_truth"] = _nanmean([r for _, _, r in per_bubble])
        row["frames_without_mesh"] = int(
            sum(not (mesh_dir / f"{f:06d}.ply").is_file() for f in frames)
        )
    if baseline_raw is not None:
        row["baseline_raw"] = velocity_scores(baseline_raw, truth)
    mpath = evaluate_dir / "metrics.json"
    if mpath.is_file():
        held = (json.loads(mpath.read_text()).get("heldout") or {}).get("mean") or {}
        row["psnr"] = held.get("psnr", math.nan)
        row["ssim"] = held.get("ssim", math.nan)
    return row


def _nanmean(values) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else math.nan


# --- the table ------------------------------------------------------------------------

#: (column title, getter, better: "low" | "high" | "one", format) of the table.
COLUMNS = [
    ("v rel: method", ("method", "relative_error"), "low", "{:.3f}"),
    ("v rel: baseline raw", ("baseline_raw", "relative_error"), "low", "{:.3f}"),
    ("v rel: baseline smoothed", ("baseline_smoothed", "relative_error"), "low", "{:.3f}"),
    ("v rel: method track-smoothed", ("method_smoothed", "relative_error"), "low", "{:.3f}"),
    ("d/dt track − v m/s: method", ("consistency", "method"), "low", "{:.4f}"),
    ("d/dt track − v: smoothed", ("consistency", "method_smoothed"), "low", "{:.4f}"),
    ("abs err vx/vy/vz m/s: method", ("method", "abs_v"), "low", None),
    ("abs err vx/vy/vz: raw", ("baseline_raw", "abs_v"), "low", None),
    ("abs err vx/vy/vz: smoothed", ("baseline_smoothed", "abs_v"), "low", None),
    ("precision", ("detection", "precision"), "high", "{:.3f}"),
    ("recall", ("detection", "recall"), "high", "{:.3f}"),
    ("Chamfer mm", ("chamfer_mm",), "low", "{:.3f}"),
    ("Chamfer % r_eq", ("chamfer_pct_r_eq",), "low", "{:.0f}"),
    ("within 0.25 r_eq", ("near_share",), "high", "{:.3f}"),
    ("volume err %", ("volume_error_pct",), "low", "{:.0f}"),
    ("bisector/across ÷ truth", ("extent_ratio_vs_truth",), "one", "{:.2f}"),
    ("held-out PSNR dB", ("psnr",), "high", "{:.2f}"),
    ("held-out SSIM", ("ssim",), "high", "{:.3f}"),
]


def _get(row: dict, path: tuple) -> float | tuple:
    if path[-1] == "abs_v":
        d = row.get(path[0]) or {}
        return tuple(d.get(f"abs_{k}", math.nan) for k in ("vx", "vy", "vz"))
    v = row
    for k in path:
        v = v.get(k, math.nan) if isinstance(v, dict) else math.nan
    return float(v) if v is not None else math.nan


def _fmt(v, fmt) -> str:
    if isinstance(v, tuple):
        return "/".join("–" if not np.isfinite(x) else f"{x:.3f}" for x in v)
    return "–" if not np.isfinite(v) else fmt.format(v)


def summary_rows(rows: Sequence[dict]) -> list[tuple[str, list]]:
    """``[(label, values)]``: each session, then ``mean`` and ``worst`` over sessions
    (NaNs skipped; worst = highest error, lowest score, farthest from 1 for the ratio)."""
    table = [(r["session"], [_get(r, c[1]) for c in COLUMNS]) for r in rows]
    mean, worst = [], []
    for k, (_, _, better, _) in enumerate(COLUMNS):
        vals = [t[1][k] for t in table]
        if isinstance(vals[0], tuple):
            arr = np.array(vals, dtype=np.float64)
            mean.append(tuple(_nanmean(arr[:, i]) for i in range(3)))
            worst.append(tuple(_nanmax(arr[:, i]) for i in range(3)))
            continue
        arr = np.array(vals, dtype=np.float64)
        fin = arr[np.isfinite(arr)]
        mean.append(float(fin.mean()) if fin.size else math.nan)
        if not fin.size:
            worst.append(math.nan)
        elif better == "low":
            worst.append(float(fin.max()))
        elif better == "high":
            worst.append(float(fin.min()))
        else:
            worst.append(float(fin[np.argmax(np.abs(fin - 1))]))
    return [*table, ("mean", mean), ("worst", worst)]


def _nanmax(a) -> float:
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else math.nan


def format_table(rows: Sequence[dict]) -> str:
    """The markdown table of :func:`summary_rows`."""
    head = ["session", *(c[0] for c in COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, vals in summary_rows(rows):
        cells = [_fmt(v, c[3]) for v, c in zip(vals, COLUMNS, strict=True)]
        lines.append("| " + " | ".join([label, *cells]) + " |")
    return "\n".join(lines)


def choose_smoothing(
    raw: dict[str, tuple[pd.DataFrame, float]],
    truth: dict[str, pd.DataFrame],
    windows_s: Sequence[float] = SMOOTH_WINDOWS_S,
    orders: Sequence[int] = SMOOTH_ORDERS,
) -> tuple[tuple[float, int], pd.DataFrame]:
    """The (window s, order) of the baseline's track smoothing with the lowest mean
    relative velocity error over the sessions, and the whole grid
    (``window_s, order, mean_relative_error, worst_relative_error``).

    ``raw``: ``{session: (baseline table, fps)}``; ``truth``: ``{session: bubbles.csv}``.
    """
    return _best_on_grid(
        lambda w, o: [
            velocity_scores(smoothed_table(tab, fps, w, o), truth[s])["relative_error"]
            for s, (tab, fps) in raw.items()
        ],
        windows_s,
        orders,
    )


def _best_on_grid(errors, windows_s: Sequence[float], orders: Sequence[int]):
    """Evaluate ``errors(window_s, order)`` (per-session relative errors) on the grid;
    → ((best window, best order) by the mean, the grid as a DataFrame)."""
    grid = []
    for w in windows_s:
        for o in orders:
            errs = [e for e in errors(w, o) if np.isfinite(e)]
            grid.append(
                (w, o, float(np.mean(errs)) if errs else math.nan, max(errs, default=math.nan))
            )
    df = pd.DataFrame(
        grid, columns=["window_s", "order", "mean_relative_error", "worst_relative_error"]
    )
    fin = df[np.isfinite(df["mean_relative_error"])]
    if fin.empty:
        return (windows_s[0], orders[0]), df
    best = fin.loc[fin["mean_relative_error"].idxmin()]
    return (float(best["window_s"]), int(best["order"])), df


def grid_table(grid: pd.DataFrame) -> str:
    """Markdown table of :func:`choose_smoothing`'s grid."""
    lines = [
        "| window ms | order | mean v rel | worst v rel |",
        "| --- | --- | --- | --- |",
    ]
    for r in grid.itertuples():
        lines.append(
            f"| {r.window_s * 1e3:g} | {r.order} | {r.mean_relative_error:.4f} "
            f"| {r.worst_relative_error:.4f} |"
        )
    return "\n".join(lines)


# --- the workflow ---------------------------------------------------------------------


def bench_config(set_values: Sequence[str] = ()) -> dict:
    """The config ``surfphase new-campaign`` writes, with :data:`BENCH_CONFIG` and
    ``KEY.SUB=VALUE`` items (YAML values) on top."""
    from surfphase.commands.new_campaign import _config_text
    from surfphase.commands.run import project_root

    cfg = yaml.safe_load(_config_text(project_root() / "config" / "config.yaml"))
    for sec, vals in BENCH_CONFIG.items():
        cfg.setdefault(sec, {}).update(vals)
    for item in set_values:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects KEY.SUB=VALUE, not {item!r}")
        *path, last = key.split(".")
        node = cfg
        for k in path:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ValueError(f"--set {item}: {k} is not a section of the config")
        node[last] = yaml.safe_load(value)
    return cfg


def write_run_campaign(synth_dir: Path, run_dir: Path, config: dict) -> pd.DataFrame:
    """A campaign folder ``run_dir/config/`` (config, sheets, board) whose sheets point
    at the synthetic campaign's videos, calibration images and truth (absolute paths).
    Every session of the synthetic campaign is in the sheet (a run of some sessions, or
    a scoring with ``--skip-run``, leaves the others' results valid); returns the sheet."""
    synth_dir, run_dir = Path(synth_dir).resolve(), Path(run_dir).resolve()
    cdir = run_dir / "config"
    cdir.mkdir(parents=True, exist_ok=True)
    sheet = pd.read_csv(synth_dir / "sessions.tsv", sep="\t", dtype=str, keep_default_na=False)
    for col in ("cam0", "cam1", "gt"):
        sheet[col] = [str(synth_dir / p) for p in sheet[col]]
    rigs = pd.read_csv(synth_dir / "rigs.tsv", sep="\t", dtype=str, keep_default_na=False)
    rigs = rigs[rigs["rig"].isin(set(sheet["rig"]))].copy()
    for col in ("cam0", "cam1"):
        rigs[col] = [str(synth_dir / p) for p in rigs[col]]
    (cdir / "board.yaml").write_text((synth_dir / "board.yaml").read_text())
    sheet.to_csv(cdir / "sessions.tsv", sep="\t", index=False)
    rigs.to_csv(cdir / "rigs.tsv", sep="\t", index=False)
    cfg = dict(config)
    cfg["sessions"], cfg["rigs"], cfg["results"] = (
        "config/sessions.tsv",
        "config/rigs.tsv",
        "results",
    )
    (cdir / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return sheet


def native_baseline(
    session: str, row: pd.Series, cameras_json: Path, work: Path, mask_params: dict
) -> tuple[pd.DataFrame, float]:
    """The two-view centroid baseline from masks at the recordings' native resolution:
    ingest at scale 1 (undistorted, calibrated cameras), the mask stage, triangulation.
    Returns (baseline table, fps)."""
    from surfphase.cameras import load_cameras
    from surfphase.eval.stage import read_session
    from surfphase.ingest import ingest_session
    from surfphase.masks.stage import run_mask_stage

    ing, msk = work / "ingest", work / "masks"
    fps = float(row["fps"])
    if not (ing / "meta.json").is_file():
        ingest_session(
            session,
            load_cameras(cameras_json),
            {"cam0": Path(row["cam0"]), "cam1": Path(row["cam1"])},
            fps,
            scale=1.0,
            out=ing,
        )
    if not (msk / "masks.json").is_file():
        run_mask_stage(ing, msk, mask_params)
    data = read_session(ing, msk)
    tab = bl.baseline_bubbles(data["cameras"], data["labels"], data["frames"], data["fps"])
    return tab, fps


def run_accuracy_bench(
    work: Path,
    campaign: Path | None = None,
    sessions: int | None = None,
    frames: int | None = None,
    seed: int = 0,
    cores: int = 2,
    set_values: Sequence[str] = (),
    skip_run: bool = False,
    samples: int = SAMPLES,
    log=print,
) -> dict:
    """The whole benchmark (module docstring). Returns ``{"rows": [...], "table": str,
    "smoothing": {...}, "config": {...}, "timings": {...}}``; also written to
    ``work/accuracy.json`` and ``work/accuracy.md``."""
    from surfphase.synth.campaign import write_campaign

    work = Path(work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    timings = {}
    if campaign is None:
        campaign = work / "campaign"
        if not (campaign / "synth.json").is_file():
            log(f"writing the bench preset into {campaign}")
            write_campaign(campaign, preset="bench", seed=seed, sessions=sessions, frames=frames)
    campaign = Path(campaign).resolve()
    if not (campaign / "sessions.tsv").is_file():
        raise FileNotFoundError(f"{campaign}: not a synthetic campaign (no sessions.tsv)")
    timings["synth_s"] = round(time.perf_counter() - t0, 1)
    all_sessions = pd.read_csv(campaign / "sessions.tsv", sep="\t", dtype=str)["session"]
    names = list(all_sessions[: sessions or len(all_sessions)])
    cfg = bench_config(set_values)
    run_dir = work / "run"
    sheet = write_run_campaign(campaign, run_dir, cfg).set_index("session")
    t1 = time.perf_counter()
    if not skip_run:
        # One session at a time, so that a run stopped early leaves whole sessions.
        for s in names:
            cmd = [sys.executable, "-m", "surfphase", "run", "--campaign", str(run_dir)]
            cmd += ["--cores", str(cores), "--session", s, "evaluate"]
            log("running: " + " ".join(cmd))
            rc = subprocess.call(cmd, env={**os.environ, "PYTHONUNBUFFERED": "1"})
            if rc:
                log(f"session {s}: the workflow exited with {rc}; it has no figures")
    timings["workflow_s"] = round(time.perf_counter() - t1, 1)

    t2 = time.perf_counter()
    res = run_dir / "results"
    raw, truths = {}, {}
    for s in names:
        gt = Path(sheet.loc[s, "gt"])
        truths[s] = pd.read_csv(gt / "bubbles.csv")
        cams = res / "calib" / sheet.loc[s, "rig"] / "cameras.json"
        if not cams.is_file():
            log(f"session {s}: no calibration ({cams}); no baseline")
            continue
        try:
            raw[s] = native_baseline(s, sheet.loc[s], cams, work / "native" / s, cfg["masks"])
        except (ValueError, FileNotFoundError) as e:
            log(f"session {s}: native baseline failed: {e}")
    timings["baseline_s"] = round(time.perf_counter() - t2, 1)
    (window, order), grid = choose_smoothing(raw, truths)
    fits = {s: res / s / "fit" for s in names if (res / s / "fit" / "surfels.npz").is_file()}
    (m_window, m_order), m_grid = choose_method_smoothing(fits, truths)
    t3 = time.perf_counter()
    rows = []
    for s in names:
        r = session_metrics(
            s,
            Path(sheet.loc[s, "gt"]),
            res / s / "fit",
            res / s / "mesh",
            res / s / "evaluate",
            raw[s][0] if s in raw else None,
            n=samples,
        )
        if s in raw:
            tab, fps = raw[s]
            r["baseline_smoothed"] = velocity_scores(
                smoothed_table(tab, fps, window, order), truths[s]
            )
        if s in fits:
            smooth = method_track_table(fits[s], m_window, m_order)
            r["method_smoothed"] = velocity_scores(smooth, truths[s])
            r["consistency"] = {
                "method": track_consistency(pd.read_csv(fits[s] / "bubbles.csv")),
                "method_smoothed": track_consistency(smooth),
            }
        rows.append(r)
    timings["metrics_s"] = round(time.perf_counter() - t3, 1)
    timings["total_s"] = round(time.perf_counter() - t0, 1)
    table = format_table(rows)
    notes = (
        f"Gate: reported and true bubbles match when their centroids are within "
        f"{GATE_R_EQ:g} r_eq of the true bubble (Hungarian per frame). Baseline smoothed: "
        f"Savitzky–Golay (deriv=1) over {window * 1e3:g} ms, order {order} (best of the "
        f"grid below on these sessions). Method track-smoothed: `fit: track_window_s: "
        f"{m_window:g}`, `track_order: {m_order}` (best of the same grid for the method), "
        "computed from the same fits' surfels. Config: `surfphase new-campaign` defaults + "
        f"{json.dumps(BENCH_CONFIG)}"
        + (f" + --set {' '.join(set_values)}" if set_values else "")
        + f"; {cores} cores."
    )
    result = {
        "rows": rows,
        "table": table,
        "notes": notes,
        "smoothing": {"window_s": window, "order": order, "grid": grid.to_dict("records")},
        "method_smoothing": {
            "window_s": m_window,
            "order": m_order,
            "grid": m_grid.to_dict("records"),
        },
        "config": cfg,
        "campaign": str(campaign),
        "timings": timings,
    }
    (work / "accuracy.json").write_text(json.dumps(_finite(result), indent=1))
    md = [table, "", notes, "", "Baseline:", "", grid_table(grid), "", "Method:", "",
          grid_table(m_grid)]  # fmt: skip
    (work / "accuracy.md").write_text("\n".join(md) + "\n")
    return result


def _finite(obj):
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj
