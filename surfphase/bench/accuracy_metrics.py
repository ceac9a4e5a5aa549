"""The accuracy bench's figures of one session (:mod:`surfphase.bench.accuracy` runs the
bench and tables them): velocity errors, detection precision and recall, surface
distance, volume and extent of the meshes, against the synthetic truth. Matching and
units: see :mod:`surfphase.bench.accuracy`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

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
XYZ, VEL = ["x", "y", "z"], ["vx", "vy", "vz"]


# --- metric functions (pure) ------------------------------------------------------------


def detection(
    pred: pd.DataFrame,
    truth: pd.DataFrame,
    seen_both: dict[int, set[int]],
    attached: dict[int, set[int]],
    gate_r_eq: float = GATE_R_EQ,
    centred: dict[int, set[int]] | None = None,
) -> dict:
    """Precision and recall of reported bubble-frames.

    Args:
        pred: reported rows ``frame, bubble, x, y, z`` (m); bubble 0 = nucleation region.
        truth: true rows ``frame, bubble, x, y, z, r_eq`` (m).
        seen_both: ``{frame: ids of true bubbles seen in both input views}``.
        attached: ``{frame: ids of true bubbles attached to the plate}``.
        gate_r_eq: matching gate, r_eq of the true bubble.
        centred: ``{frame: ids of true bubbles whose centroid projects inside both
            input views}``: ``recall_centred`` is the recall over those only.

    Returns:
        ``precision`` (real reported / reported), ``recall`` (reported free true
        bubble-frames seen in both views / all of them), and the counts ``reported``,
        ``real``, ``free_seen``, ``free_found`` (NaN ratios when a count is 0); with
        ``centred`` also ``recall_centred``, ``centred_seen``, ``centred_found``.
    """
    reported = real = free_seen = free_found = centred_seen = centred_found = 0
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
        if centred is not None:
            inside = free & set(centred.get(f, set()))
            centred_seen += len(inside)
            centred_found += len(inside & matched_true)
    out = {
        "precision": real / reported if reported else math.nan,
        "recall": free_found / free_seen if free_seen else math.nan,
        "reported": reported,
        "real": real,
        "free_seen": free_seen,
        "free_found": free_found,
    }
    if centred is not None:
        out["recall_centred"] = centred_found / centred_seen if centred_seen else math.nan
        out["centred_seen"] = centred_seen
        out["centred_found"] = centred_found
    return out


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


def known_velocity_matches(
    pred: pd.DataFrame, truth: pd.DataFrame, gate_r_eq: float = GATE_R_EQ
) -> pd.DataFrame:
    """The reported bubbles (ids ≥ 1) matched to the truth within ``gate_r_eq``
    (:func:`surfphase.eval.velocity.match_bubbles_relative`) whose velocity is known."""
    m = velocity.match_bubbles_relative(pred[pred["bubble"] >= 1], truth, gate_r_eq)
    return m[np.isfinite(m["abs_error_mps"].to_numpy(np.float64))]


def paired_velocity_scores(
    pred: pd.DataFrame, other: pd.DataFrame, truth: pd.DataFrame, gate_r_eq: float = GATE_R_EQ
) -> dict:
    """Both tables' velocities on the true bubble-frames that each matches (ids ≥ 1,
    :func:`surfphase.eval.velocity.match_bubbles_relative`, velocities known in both):
    ``{"matched": n, "method": rel, "baseline": rel}``, each relative error the mean
    |error| (m/s) over those n bubble-frames divided by their mean true speed — one
    denominator for both, so the two differ only by their errors on the same bubbles."""
    keys = ["frame", "gt_bubble"]
    both = [known_velocity_matches(t, truth, gate_r_eq) for t in (pred, other)]
    j = both[0].merge(both[1][[*keys, "abs_error_mps"]], on=keys, suffixes=("", "_other"))
    if j.empty:
        return {"matched": 0, "method": math.nan, "baseline": math.nan}
    speed = np.linalg.norm(j[["gt_vx", "gt_vy", "gt_vz"]].to_numpy(np.float64), axis=1).mean()
    return {
        "matched": int(len(j)),
        "method": float(j["abs_error_mps"].mean() / speed),
        "baseline": float(j["abs_error_mps_other"].mean() / speed),
    }


def reported_volume_scores(
    sized: pd.DataFrame, truth: pd.DataFrame, gate_r_eq: float = GATE_R_EQ
) -> dict:
    """The volumes a session reports (``sized``: the evaluation's ``bubbles.csv``, with
    ``volume_m3`` and ``cut``) against the true bubbles they match (``truth``: ``frame,
    bubble, x, y, z, vx, vy, vz, r_eq``, m; true volume 4/3 π r_eq³), over the matched
    bubble-frames (ids ≥ 1) within ``gate_r_eq`` that have a volume.

    Returns ``error_pct`` (mean |V / V_true − 1| in %), ``error_pct_cut`` (the same over
    the bubble-frames flagged ``cut``), ``cut_share`` (their share) and ``sized_share``
    (the share of matched bubble-frames with a volume); NaN where nothing counts.
    """
    pred = sized[sized["bubble"] >= 1]
    m = velocity.match_bubbles_relative(pred, truth, gate_r_eq)
    if m.empty:
        return dict.fromkeys(("error_pct", "error_pct_cut", "cut_share", "sized_share"), math.nan)
    cols = ["frame", "bubble", "volume_m3", *(["cut"] if "cut" in pred else [])]
    m = m.merge(pred[cols], on=["frame", "bubble"], how="left")
    v = m["volume_m3"].to_numpy(np.float64)
    v_true = 4.0 / 3.0 * np.pi * m["gt_r_eq"].to_numpy(np.float64) ** 3
    ok = np.isfinite(v)
    err = 100.0 * np.abs(v[ok] / v_true[ok] - 1.0)
    cut = m["cut"].to_numpy(bool)[ok] if "cut" in m else np.zeros(len(err), bool)
    return {
        "error_pct": float(err.mean()) if err.size else math.nan,
        "error_pct_cut": float(err[cut].mean()) if cut.any() else math.nan,
        "cut_share": float(cut.mean()) if err.size else math.nan,
        "sized_share": float(ok.mean()),
    }


# --- one session ----------------------------------------------------------------------


def seen_in_both(masks: Sequence[np.ndarray]) -> dict[int, set[int]]:
    """``{frame: ids ≥ 1 present in every (T, H, W) label stack}``."""
    out = {}
    for f in range(min(len(m) for m in masks)):
        sets = [set(np.unique(np.asarray(m[f]))) for m in masks]
        out[f] = {int(i) for i in set.intersection(*sets) if i >= 1}
    return out


def centred_in_views(truth: pd.DataFrame, cameras: Sequence) -> dict[int, set[int]]:
    """``{frame: ids of the true bubbles whose centroid projects inside every camera's
    image}`` (``truth``: rows ``frame, bubble, x, y, z`` in m; pixel centres at
    integers, the image ``[−0.5, size − 0.5)``)."""
    out: dict[int, set[int]] = {}
    xyz = truth[XYZ].to_numpy(np.float64)
    inside = np.ones(len(truth), bool)
    for cam in cameras:
        uv = np.asarray(cam.project(xyz), np.float64).reshape(-1, 2)
        inside &= (uv[:, 0] >= -0.5) & (uv[:, 0] < cam.width - 0.5)
        inside &= (uv[:, 1] >= -0.5) & (uv[:, 1] < cam.height - 0.5)
    for f, b, ok in zip(
        truth["frame"].astype(int), truth["bubble"].astype(int), inside, strict=True
    ):
        if ok:
            out.setdefault(int(f), set()).add(int(b))
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
        centred = centred_in_views(truth, [cams["cam0"], cams["cam1"]])
        row["detection"] = detection(pred, truth, seen, attached, centred=centred)
        ch = [s["chamfer_mm"] for s in surf]
        req = [s["r_eq_mm"] for s in surf]
        row["chamfer_mm"] = nanmean(ch)
        row["chamfer_pct_r_eq"] = nanmean(
            [100 * c / r for c, r in zip(ch, req, strict=True) if np.isfinite(c * r)]
        )
        row["near_share"] = nanmean([s["near"] for s in surf])
        per_bubble = [b for s in surf for b in s["bubbles"]]
        row["volume_error_pct"] = nanmean([100 * abs(v) for _, v, _ in per_bubble])
        row["extent_ratio_vs_truth"] = nanmean([r for _, _, r in per_bubble])
        row["frames_without_mesh"] = int(
            sum(not (mesh_dir / f"{f:06d}.ply").is_file() for f in frames)
        )
    if baseline_raw is not None:
        row["baseline_raw"] = velocity_scores(baseline_raw, truth)
    sized_csv = evaluate_dir / "bubbles.csv"
    if sized_csv.is_file():
        row["volume_reported"] = reported_volume_scores(pd.read_csv(sized_csv), truth)
    mpath = evaluate_dir / "metrics.json"
    if mpath.is_file():
        held = (json.loads(mpath.read_text()).get("heldout") or {}).get("mean") or {}
        row["psnr"] = held.get("psnr", math.nan)
        row["ssim"] = held.get("ssim", math.nan)
    return row


def nanmean(values) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else math.nan
