"""The ``evaluate`` stage of one session: metrics JSON, baseline and velocity tables.

Inputs (folders of earlier stages, read through :mod:`surfphase.folders`):

* ``INGEST`` — ``cameras.json`` (undistorted cameras), ``meta.json`` (``session``,
  ``fps``, ``frame_indices``), ``<cam>.npy`` frame stacks;
* ``MASKS`` — ``<cam>_labels.npy`` (int32 T × H × W, −1 background, ids shared across
  views and time, 0 the nucleation region);
* ``FIT`` — ``bubbles.csv`` (``frame, time_s, bubble, x, y, z, vx, vy, vz``; m, m/s, lab
  frame) and, for held-out views, ``surfels.npz`` (:mod:`surfphase.fit.outputs`); the
  final fit, and optionally the stage-1 fit and ablation fits in the same format;
* ``GT`` (synthetic sessions only) — ``cameras.json``, ``bubbles.csv`` (with ``r_eq``
  for the region metrics),
  ``views/<cam>/<frame:06d>.png`` (held-out views as recorded), optionally
  ``views_clean/<cam>/<frame:06d>.png`` (the same without sensor noise) and
  ``views_background/<cam>.png`` (each held-out camera's reference frame without
  bubbles), ``meshes/<frame:06d>.ply``;
* ``MESHES`` (optional, from the mesh stage) — ``<frame:06d>.ply``, metres.

Outputs in ``OUT`` (each written whole or not at all):

* ``metrics.json`` — ``session``; ``heldout`` (per held-out camera and ``mean``: ``l1``,
  ``psnr`` dB, ``ssim``, ``frames`` over the full frame, and ``region``: the same inside
  the true bubbles' region, :mod:`.regions`, with ``pixels`` its mean size; the
  protocol is in ``settings.heldout``: with ``views_clean`` and ``views_background`` the
  reconstructed bubbles are rendered over the held-out camera's reference frame and
  compared with the noiseless views, and ``heldout_whole`` then holds the figures of
  the whole image predicted — the input views' mean background behind the bubbles,
  compared with the recorded views);
  ``velocity`` (``method`` and ``baseline``: ``mean_abs_error_mps``,
  ``relative_error``, ``mean_speed_gt_mps``, ``matched``); ``chamfer_mm`` (with method
  meshes); ``reference2d`` (always: the 2D reference's relative x/y errors of ``method``
  and ``baseline``; with ground truth also ``truth``, the true velocities of the
  baseline-matched bubbles against the reference, which scores the reference itself);
  ``stage1`` (with a stage-1 fit) and ``ablations`` ``{name: …}`` (with ablation fits):
  each ``fit`` (its folder), ``velocity`` (errors as the method's), ``heldout`` and
  ``heldout_whole`` (as above) and ``reference2d`` (its errors against the 2D reference);
  ``sizes`` (:func:`surfphase.eval.sizes.size_metrics`: the meshes' bubble-frames with a
  volume, their mean and median equivalent diameter, mean volume, and with ground truth
  the equivalent diameter's relative error against the matched true bubbles');
  non-finite numbers are ``null``;
* ``bubbles.csv`` — the fit's ``bubbles.csv`` with each bubble-frame's ``volume_m3``,
  ``d_eq_m`` and ``closed`` from the meshes (``MESHES/bubble_sizes.csv``; NaN where it
  has none) and ``cut`` (its silhouette touches the image border in some view: its
  size rests on the silhouette completed beyond the border): positions, velocities and
  sizes in one table;
* ``baseline_bubbles.csv`` — the two-view centroid baseline (:mod:`.baseline`);
* ``velocity_table.csv`` — one row per compared bubble-frame, column ``source``
  (``method``/``baseline``, and ``stage1`` / the ablation names with ground truth):
  with ground truth the matches of
  :func:`surfphase.eval.velocity.match_bubbles`, without it the rows of
  :func:`surfphase.eval.reference2d.compare_to_reference`.

Bubble 0 (the nucleation region at the plate) is not a bubble of the ground truth and is
left out of the velocity comparisons unless ``include_nucleation``. The baseline is
compared on the frames present in the fit's ``bubbles.csv`` only, so that method and
baseline errors average over the same frames.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.cameras import Camera, load_cameras
from surfphase.eval import baseline as bl
from surfphase.eval import geometry, reference2d, regions, sizes, velocity
from surfphase.eval.heldout import fit_heldout, heldout_protocol, nanmean
from surfphase.folders.fit import BUBBLE_COLUMNS, read_csv_table, read_fit_bubbles
from surfphase.folders.ingest import read_ingest
from surfphase.folders.masks import read_masks
from surfphase.io import atomic_write_json, atomic_write_text


# -- inputs ------------------------------------------------------------------------------
def read_session(ingest_dir: Path, masks_dir: Path) -> dict:
    """Session name, fps, frame indices, and the undistorted cameras with label stacks
    (the ingest and masks folders through their readers, :mod:`surfphase.folders`)."""
    ingest = read_ingest(ingest_dir, min_cameras=2)
    fps = ingest.require_fps()
    cameras = ingest.input_cameras()
    masks = read_masks(masks_dir, cameras, ingest.session, n_frames=ingest.n_frames)
    return {
        "session": ingest.session,
        "fps": fps,
        "frames": ingest.frame_indices,
        "cameras": cameras,
        "labels": list(masks.labels.values()),
    }


def chamfer_per_frame(
    meshes_dir: Path,
    gt_meshes_dir: Path,
    frames: Sequence[int],
    n_points: int = 20000,
    seed: int = 0,
    cameras: Sequence[Camera] | None = None,
) -> dict:
    """Chamfer (mm) of ``meshes_dir/<frame:06d>.ply`` against the true mesh of each frame
    that has both; ``mean_mm``/``mean_sq_mm2`` averaged over frames, and ``per_frame``.

    With the input ``cameras`` (true ones), the comparison is restricted to the volume
    they all see (:func:`surfphase.eval.geometry.in_all_views`); ``whole_truth_mean_mm``
    is then the mean over frames without that restriction, for reference. Frames with
    nothing to compare in that volume are left out of the means (``frames`` counts the
    rest)."""
    per = {}
    for f in frames:
        name = f"{int(f):06d}.ply"
        a, b = meshes_dir / name, gt_meshes_dir / name
        if a.exists() and b.exists():
            per[int(f)] = geometry.mesh_chamfer(a, b, n_points, seed, cameras)
    if not per:
        return {}
    out = {
        "mean_mm": nanmean([v["mean_mm"] for v in per.values()]),
        "mean_sq_mm2": nanmean([v["mean_sq_mm2"] for v in per.values()]),
        "frames": int(sum(np.isfinite(v["mean_mm"]) for v in per.values())),
        "points_per_mesh": n_points,
    }
    if cameras is not None:
        out["volume"] = "seen by every input camera (" + ", ".join(c.name for c in cameras) + ")"
        out["whole_truth_mean_mm"] = float(
            np.mean([v["whole_truth_mean_mm"] for v in per.values()])
        )
    out["per_frame"] = {str(k): v for k, v in per.items()}
    return out


def _finite(obj):
    """JSON-safe copy: non-finite floats become None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float | np.floating) and not math.isfinite(float(obj)):
        return None
    return obj


def _truth_region_table(gt_dir: Path, name: str) -> pd.DataFrame | None:
    """The true bubbles with ``r_eq`` for region metrics, or None if it has no radius."""
    cols = ["frame", "x", "y", "z"]
    truth = read_csv_table(gt_dir / "bubbles.csv", cols, f"session {name}")
    return truth if "r_eq" in truth.columns else None


# -- the stage ---------------------------------------------------------------------------
@dataclass
class _Scoring:
    """What every fit of one session is scored against (filled by :func:`_score_truth`)."""

    name: str
    data: dict
    keep: Callable[[pd.DataFrame], pd.DataFrame]
    max_match_dist: float
    device: str
    region_scale: float
    gt_dir: Path | None = None
    truth: pd.DataFrame | None = None
    region_truth: pd.DataFrame | None = None
    held: list[Camera] = field(default_factory=list)
    seen_by: list[Camera] | None = None
    tables: list[pd.DataFrame] = field(default_factory=list)


def _read_fits(
    name: str,
    fit_dir: Path,
    fit_stage1_dir: Path | None,
    ablations: Mapping[str, Path],
    compare_meshes: Mapping[str, Path],
) -> tuple[pd.DataFrame, dict[str, tuple[Path, pd.DataFrame]]]:
    """Every fit's ``bubbles.csv`` (so that a missing one fails before any long
    computation): the final fit's, and ``{label: (folder, table)}`` of the others."""
    for label, d in ablations.items():
        if not label or label in ("method", "baseline", "stage1"):
            raise ValueError(f"{d}: session {name}: ablation name {label!r} is not allowed")
    method = read_fit_bubbles(fit_dir, f"session {name}")
    others: dict[str, tuple[Path, pd.DataFrame]] = {}
    if fit_stage1_dir is not None:
        d = Path(fit_stage1_dir)
        others["stage1"] = (d, read_fit_bubbles(d, f"session {name} stage 1"))
    for label, d in ablations.items():
        others[label] = (d, read_fit_bubbles(d, f"session {name} {label}"))
    for label, d in compare_meshes.items():
        if label not in others:
            raise ValueError(
                f"{d}: session {name}: meshes of {label!r}, which is not a fit scored here "
                "(stage1 needs the stage-1 fit, an ablation its fit)"
            )
    return method, others


def _score_truth(
    sc: _Scoring,
    metrics: dict,
    method: pd.DataFrame,
    base_cmp: pd.DataFrame,
    fit_dir: Path,
    meshes_dir: Path | None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """With ground truth: the velocity errors of method and baseline, the held-out views
    and the Chamfer distance into ``metrics``; fills ``sc``'s truth fields.

    Returns the method's matches and the truth under the masks' bubble ids.
    """
    gt_dir, name = sc.gt_dir, sc.name
    sc.truth = read_csv_table(gt_dir / "bubbles.csv", BUBBLE_COLUMNS, f"session {name}")
    sc.region_truth = _truth_region_table(gt_dir, name)
    metrics["settings"]["region"] = (
        f"projected spheres of {sc.region_scale:g}·r_eq around the true bubbles"
        if sc.region_truth is not None
        else "none: the ground truth's bubbles.csv has no r_eq column"
    )
    metrics["velocity"] = {}
    for label, pred in (("method", method), ("baseline", base_cmp)):
        m = velocity.match_bubbles(sc.keep(pred), sc.truth, sc.max_match_dist)
        metrics["velocity"][label] = velocity.velocity_errors(m)
        if label == "method":
            method_matches = m.copy()
        if label == "baseline":
            # The truth under the masks' bubble ids (through the baseline's matches),
            # to score the 2D reference itself.
            truth_by_mask_id = m[["frame", "bubble", "gt_vx", "gt_vy", "gt_vz"]].rename(
                columns={"gt_vx": "vx", "gt_vy": "vy", "gt_vz": "vz"}
            )
        m.insert(0, "source", label)
        sc.tables.append(m)
    gt_cams = load_cameras(gt_dir / "cameras.json")
    views_dir = gt_dir / "views"
    if views_dir.is_dir():
        sc.held = [c for n, c in gt_cams.items() if (views_dir / n).is_dir()]
    if sc.held:
        metrics["settings"]["heldout"] = heldout_protocol(gt_dir)
    metrics.update(
        fit_heldout(fit_dir, sc.held, gt_dir, sc.device, sc.region_truth, sc.region_scale)
    )
    cams = sc.data["cameras"]
    inputs = [gt_cams[c.name] for c in cams if c.name in gt_cams]
    sc.seen_by = inputs if len(inputs) == len(cams) else None
    if meshes_dir is not None:
        metrics["chamfer_mm"] = chamfer_per_frame(
            Path(meshes_dir), gt_dir / "meshes", sc.data["frames"].tolist(), cameras=sc.seen_by
        )
    return method_matches, truth_by_mask_id


def _reference_2d(
    sc: _Scoring,
    reference_camera: str | None,
    ingest_dir: Path,
    base: pd.DataFrame,
) -> tuple[pd.DataFrame, Camera]:
    """The 2D reference velocities of one input view (default the first) and its camera."""
    data = sc.data
    cams = {c.name: (c, lab) for c, lab in zip(data["cameras"], data["labels"], strict=True)}
    ref_name = reference_camera or data["cameras"][0].name
    if ref_name not in cams:
        raise ValueError(
            f"{ingest_dir}: session {sc.name}: no camera {ref_name!r} for the 2D reference"
        )
    ref_cam, ref_lab = cams[ref_name]
    ref = reference2d.reference_velocities(ref_cam, ref_lab, data["frames"], data["fps"], base)
    return ref, ref_cam


def _score_other(
    sc: _Scoring,
    label: str,
    d: Path,
    pred: pd.DataFrame,
    ref: pd.DataFrame,
    ref_cam: Camera,
    compare_meshes: Mapping[str, Path],
) -> dict:
    """Stage 1 or an ablation: the same velocity, held-out and 2D-reference scores."""
    res: dict = {"fit": str(d)}
    if sc.truth is not None:
        m = velocity.match_bubbles(sc.keep(pred), sc.truth, sc.max_match_dist)
        res["velocity"] = velocity.velocity_errors(m)
        m.insert(0, "source", label)
        sc.tables.append(m)
        res.update(fit_heldout(d, sc.held, sc.gt_dir, sc.device, sc.region_truth, sc.region_scale))
        if label in compare_meshes:
            res["chamfer_mm"] = chamfer_per_frame(
                compare_meshes[label],
                sc.gt_dir / "meshes",
                sc.data["frames"].tolist(),
                cameras=sc.seen_by,
            )
    res["reference2d"] = reference2d.compare_to_reference(sc.keep(pred), ref, ref_cam)[0]
    return res


def _with_sizes(
    method: pd.DataFrame,
    meshes_dir: Path | None,
    gt_dir: Path | None,
    method_matches: pd.DataFrame | None,
    cut: set[tuple[int, int]],
) -> tuple[pd.DataFrame, dict]:
    """The fit's table with the meshes' per-bubble sizes (the bubble-frames in ``cut``,
    which the image border cuts, flagged), and their summary metrics."""
    size_csv = Path(meshes_dir) / "bubble_sizes.csv" if meshes_dir is not None else None
    sizes_in = pd.read_csv(size_csv) if size_csv is not None and size_csv.is_file() else None
    with_sizes = sizes.bubble_sizes_table(method, sizes_in, cut)
    truth_r = None
    if gt_dir is not None:
        gt_table = pd.read_csv(Path(gt_dir) / "bubbles.csv")
        truth_r = gt_table[["frame", "bubble", "r_eq"]] if "r_eq" in gt_table else None
    return with_sizes, sizes.size_metrics(with_sizes, method_matches, truth_r)


def _write_outputs(
    out_dir: Path,
    with_sizes: pd.DataFrame,
    base: pd.DataFrame,
    tables: Sequence[pd.DataFrame],
    metrics: dict,
) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "bubbles.csv", with_sizes.to_csv(index=False, float_format="%.9g"))
    atomic_write_text(out_dir / "baseline_bubbles.csv", base.to_csv(index=False))
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    atomic_write_text(out_dir / "velocity_table.csv", table.to_csv(index=False))
    atomic_write_json(out_dir / "metrics.json", metrics)


def run_evaluate(
    ingest_dir: str | os.PathLike,
    masks_dir: str | os.PathLike,
    fit_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    gt_dir: str | os.PathLike | None = None,
    meshes_dir: str | os.PathLike | None = None,
    session: str | None = None,
    device: str = "cpu",
    max_match_dist: float = velocity.MAX_MATCH_DIST,
    include_nucleation: bool = False,
    reference_camera: str | None = None,
    fit_stage1_dir: str | os.PathLike | None = None,
    ablations: Mapping[str, str | os.PathLike] | None = None,
    region_scale: float = regions.REGION_SCALE,
    compare_meshes: Mapping[str, str | os.PathLike] | None = None,
) -> dict:
    """Evaluate one session (see the module docstring); returns the metrics dict.

    Args:
        ingest_dir, masks_dir, fit_dir: outputs of the ingest, mask and fit stages
            (``fit_dir``: the final fit, stage 2 when refinement is on).
        out_dir: where ``metrics.json``, ``baseline_bubbles.csv`` and
            ``velocity_table.csv`` go.
        gt_dir: ground-truth folder (synthetic sessions), or None for real data.
        meshes_dir: the method's meshes (``<frame:06d>.ply``), for the Chamfer distance.
        session: session name (default: ``meta.json``'s).
        device: torch device for rendering held-out views.
        max_match_dist: gating distance of the bubble matching, metres.
        include_nucleation: compare bubble 0 (nucleation region) too.
        reference_camera: view of the 2D reference (default: the first input camera).
        fit_stage1_dir: the stage-1 fit (no refinement), scored like the final fit into
            ``metrics["stage1"]``.
        ablations: ``{name: fit folder}`` of ablation fits (e.g. ``no_sdf``), scored
            into ``metrics["ablations"][name]``.
        region_scale: bubble region = projected spheres of ``region_scale · r_eq``.
        compare_meshes: ``{name: meshes folder}`` of ``stage1`` or an ablation: with
            ground truth, their Chamfer distance goes into that fit's entry.
    """
    from surfphase.device import resolve_device

    ingest_dir, masks_dir, fit_dir, out_dir = map(Path, (ingest_dir, masks_dir, fit_dir, out_dir))
    data = read_session(ingest_dir, masks_dir)
    name = session or data["session"]
    ablations = {str(k): Path(v) for k, v in (ablations or {}).items()}
    compare_meshes = {str(k): Path(v) for k, v in (compare_meshes or {}).items()}
    method, others = _read_fits(name, fit_dir, fit_stage1_dir, ablations, compare_meshes)
    base = bl.baseline_bubbles(data["cameras"], data["labels"], data["frames"], data["fps"])
    keep = (lambda df: df) if include_nucleation else (lambda df: df[df["bubble"] >= 1])
    metrics: dict = {
        "session": name,
        "frames": int(len(data["frames"])),
        "fps": data["fps"],
        "cameras": [c.name for c in data["cameras"]],
        "settings": {
            "max_match_dist_m": float(max_match_dist),
            "include_nucleation": bool(include_nucleation),
        },
    }
    # The baseline is compared on the frames the method reconstructed, so both errors in a
    # table average over the same frames (baseline_bubbles.csv keeps every frame).
    base_cmp = base[base["frame"].isin(method["frame"].unique())]
    metrics["settings"]["frames_compared"] = int(base_cmp["frame"].nunique())
    sc = _Scoring(name, data, keep, max_match_dist, str(resolve_device(device)), region_scale)
    method_matches = truth_by_mask_id = None
    if gt_dir is not None:
        sc.gt_dir = Path(gt_dir)
        method_matches, truth_by_mask_id = _score_truth(
            sc, metrics, method, base_cmp, fit_dir, meshes_dir
        )
    ref, ref_cam = _reference_2d(sc, reference_camera, ingest_dir, base)
    metrics["reference2d"] = {"camera": ref_cam.name}
    for label, pred in (("method", method), ("baseline", base_cmp)):
        res, rows = reference2d.compare_to_reference(keep(pred), ref, ref_cam)
        metrics["reference2d"][label] = res
        if gt_dir is None:
            rows.insert(0, "source", label)
            sc.tables.append(rows)
    if truth_by_mask_id is not None:
        metrics["reference2d"]["truth"] = reference2d.compare_to_reference(
            truth_by_mask_id, ref, ref_cam
        )[0]
    for label, (d, pred) in others.items():
        res = _score_other(sc, label, d, pred, ref, ref_cam, compare_meshes)
        if label == "stage1":
            metrics["stage1"] = res
        else:
            metrics.setdefault("ablations", {})[label] = res
    # Per-bubble sizes from the meshes, beside the fit's positions and velocities.
    cut = sizes.cut_bubble_frames(data["labels"], data["frames"])
    with_sizes, metrics["sizes"] = _with_sizes(method, meshes_dir, sc.gt_dir, method_matches, cut)
    metrics = _finite(metrics)
    _write_outputs(out_dir, with_sizes, base, sc.tables, metrics)
    return metrics


def campaign_table(metrics: Sequence[dict]) -> pd.DataFrame:
    """One row per session: the metrics JSONs flattened (``velocity.method.relative_error``
    …), session first, then velocity (method beside baseline, stage 1 and the ablations),
    held-out means (full frame, then the bubbles' region), Chamfer and the 2D reference;
    per-frame Chamfer values are left out, and so are the per-camera held-out values of
    stage 1 and the ablations (their means stay)."""
    flat = []
    for m in metrics:
        m = dict(m)
        if isinstance(m.get("chamfer_mm"), dict):
            m["chamfer_mm"] = {k: v for k, v in m["chamfer_mm"].items() if k != "per_frame"}
        m.pop("cameras", None)
        if isinstance(m.get("stage1"), dict):
            m["stage1"] = _means_only(m["stage1"])
        if isinstance(m.get("ablations"), dict):
            m["ablations"] = {k: _means_only(v) for k, v in m["ablations"].items()}
        flat.append(m)
    df = pd.json_normalize(flat, sep=".")
    # Column groups in order, as regular expressions matched at the start of a name.
    order = [
        r"session$", r"velocity\.", r"stage1\.velocity\.", r"ablations\.[^.]+\.velocity\.",
        r"heldout\.mean\.(?!region)", r"stage1\.heldout\.mean\.(?!region)",
        r"ablations\.[^.]+\.heldout\.mean\.(?!region)", r"heldout\.mean\.region\.",
        r"stage1\.heldout\.mean\.region\.", r"ablations\.[^.]+\.heldout\.mean\.region\.",
        r"heldout_whole\.mean\.", r"stage1\.heldout_whole\.mean\.",
        r"ablations\.[^.]+\.heldout_whole\.mean\.",
        r"chamfer_mm\.", r"stage1\.chamfer_mm\.", r"ablations\.[^.]+\.chamfer_mm\.",
        r"reference2d\.", r"stage1\.reference2d\.",
        r"ablations\.[^.]+\.reference2d\.", r"heldout\.", r"heldout_whole\.",
    ]  # fmt: skip
    cols: list[str] = []
    for group in order:
        pat = re.compile(group)
        cols += [c for c in df.columns if pat.match(c) and c not in cols]
    cols += [c for c in df.columns if c not in cols]
    return df[cols]


def _means_only(fit_metrics: dict) -> dict:
    """A stage-1 / ablation entry without its per-camera held-out values."""
    out = dict(fit_metrics)
    for key in ("heldout", "heldout_whole"):
        if isinstance(out.get(key), dict):
            out[key] = {k: v for k, v in out[key].items() if k == "mean"}
    if isinstance(out.get("chamfer_mm"), dict):
        out["chamfer_mm"] = {k: v for k, v in out["chamfer_mm"].items() if k != "per_frame"}
    return out
