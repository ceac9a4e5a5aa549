"""Outputs of the stage-1 fit, written whole or not at all.

``OUTDIR/surfels.npz`` — every surfel at every frame (F frames, N surfels: all surfels
ever created, column = the surfel's id; surfels appended later for new bubbles are padded
before they exist, and those a merge replaced are padded after it, see ``alive``):

=============  ============  ========================================================
key            shape/dtype   meaning
=============  ============  ========================================================
frame          (F,) int64    session frame index
time_s         (F,) float64  time of the frame, seconds
alive          (F, N) bool   the surfel exists at that frame
means          (F, N, 3) f4  centre, metres, lab frame
quats          (F, N, 4) f4  rotation (w, x, y, z), unit; normal = 3rd column
log_scales     (F, N, 2) f4  ln of the tangent standard deviations (metres)
colors         (F, N, D) f4  colour in [0, 1] (clamp when rendering)
sdf            (F, N) f4     SDF value f, metres (NaN in the "no SDF" ablation)
opacity        (F, N) f4     o = 4e^{−γf}/(1+e^{−γf})² (or the free opacity)
bubble         (F, N) int32  bubble bound at that frame (−1 none, 0 nucleation)
velocity       (F, N, 3) f4  per-surfel finite-difference velocity, m/s (0 if unknown)
gamma          (F,) f4       SDF sharpness γ, 1/metres (NaN without SDF)
background     (D,) f4       background colour for novel views (median of the images)
bg_images      (C,H,W,D) f4  per-input-view background images the fit rendered over
extent         () f8         scene extent L, metres
shade          (F, K, D) f4  shading curve added to the colours per view (only with
                             ``fit: shading``; :mod:`surfphase.render.shading`)
=============  ============  ========================================================

``OUTDIR/bubbles.csv`` — ``frame, time_s, bubble, x, y, z, vx, vy, vz, n_surfels``:
weighted centroids (metres) and finite-difference velocities (m/s) in the lab frame,
both from the same surfels (those bound to the bubble at that frame): central
differences along the bubble's track, one-sided at its first and last frame (a merge or
a new bubble starts a track; see :func:`bubble_table`).

``OUTDIR/curves.csv`` — ``frame, iter, loss, l1, dssim, normal, gamma, proj, psnr,
n_surfels``; ``OUTDIR/summary.json`` — per-frame input-view PSNR (dB), timings
(seconds), surfel counts; ``OUTDIR/renders/`` — ``frame<k>_<cam>.png``, observed (left)
vs rendered (right).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from surfphase.cameras import Camera
from surfphase.device import platform_record
from surfphase.fit import binding
from surfphase.io import atomic_path, atomic_write_json, atomic_write_text
from surfphase.tracks import moving_polynomial, savgol_window

if TYPE_CHECKING:  # imported where the surfels are rendered: readers of the fit need none
    import torch

PER_SURFEL = ("means", "quats", "log_scales", "colors", "opacity")


def stack_records(records: Sequence[dict], extent: float) -> dict[str, np.ndarray]:
    """Pad the per-frame records to (F, N, ...) arrays (see the module table).

    A record's rows are the surfels whose ids are ``r["ids"]`` (ascending; without
    ``ids``: ``0 … n−1``), so column ``i`` of every array is surfel ``i`` at every frame.
    """
    F = len(records)
    ids = [record_ids(r) for r in records]
    N = max((int(i.max()) + 1 if i.size else 0) for i in ids)
    D = records[0]["colors"].shape[1]
    out: dict[str, np.ndarray] = {
        "alive": np.zeros((F, N), dtype=bool),
        "means": np.zeros((F, N, 3), np.float32),
        "quats": np.zeros((F, N, 4), np.float32),
        "log_scales": np.zeros((F, N, 2), np.float32),
        "colors": np.zeros((F, N, D), np.float32),
        "opacity": np.zeros((F, N), np.float32),
        "sdf": np.full((F, N), np.nan, np.float32),
        "bubble": np.full((F, N), -1, np.int32),
        "gamma": np.full(F, np.nan, np.float32),
    }
    for t, r in enumerate(records):
        n = ids[t]
        out["alive"][t, n] = True
        for k in PER_SURFEL:
            out[k][t, n] = r[k]
        out["bubble"][t, n] = r["bubble"]
        if "sdf" in r:
            out["sdf"][t, n] = r["sdf"] * extent
            out["gamma"][t] = r["gamma"] / extent
    if "shade" in records[0]:
        out["shade"] = np.stack([np.asarray(r["shade"], np.float32) for r in records])
    return out


def frame_colors(
    surfels: dict[str, np.ndarray], frame: int, viewmats: torch.Tensor, device
) -> torch.Tensor:
    """Colours of frame position ``frame``'s live surfels as seen by C cameras
    (``viewmats`` (C, 4, 4)): (N, D), or (C, N, D) when the fit has a shading curve."""
    import torch

    from surfphase.render.shading import view_colors

    a = np.asarray(surfels["alive"][frame], bool)
    f = lambda k: torch.as_tensor(np.asarray(surfels[k][frame])[a], device=device)  # noqa: E731
    if "shade" not in surfels:
        return f("colors")
    knots = torch.as_tensor(np.asarray(surfels["shade"][frame]), device=device)
    return view_colors(f("colors"), f("means"), f("quats"), knots, viewmats.to(knots))


def rasterize_frame(
    surfels: dict[str, np.ndarray],
    frame: int,
    cameras: Sequence[Camera],
    device: torch.device,
    clamp_colors: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rasterize frame position ``frame``'s live surfels of a ``surfels.npz`` into
    ``cameras`` (one size), without gradients: ``(colors (C, H, W, D) premultiplied,
    alpha (C, H, W, 1))`` on ``device``, nothing composited yet. ``clamp_colors``: the
    surfel colours clamped to [0, 1] first (the orbit views)."""
    import torch

    from surfphase.render import camera_tensors, rasterize_surfels

    a = np.asarray(surfels["alive"][frame], bool)
    f = lambda k: torch.as_tensor(np.asarray(surfels[k][frame])[a], device=device)  # noqa: E731
    viewmats, Ks = camera_tensors(list(cameras), device, torch.float32)
    W, H = cameras[0].width, cameras[0].height
    with torch.no_grad():
        colors = frame_colors(surfels, frame, viewmats, device)
        if clamp_colors:
            colors = colors.clamp(0, 1)
        rgb, alpha, _ = rasterize_surfels(
            f("means"), f("quats"), torch.exp(f("log_scales")), f("opacity"), colors,
            viewmats, Ks, W, H,
        )  # fmt: skip
    return rgb, alpha


def record_ids(record: dict) -> np.ndarray:
    """The persistent surfel ids (n,) int64 of a frame record's rows."""
    if "ids" in record:
        return np.asarray(record["ids"], dtype=np.int64)
    return np.arange(record["means"].shape[0], dtype=np.int64)


def surfel_velocities(means: np.ndarray, alive: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(F, N, 3) per-surfel velocities (m/s): central differences where the surfel exists
    at both neighbours, else one-sided, else 0."""
    F = means.shape[0]
    v = np.zeros(means.shape, dtype=np.float64)
    m = means.astype(np.float64)
    for t in range(F):
        a = t - 1 if t > 0 else t
        b = t + 1 if t < F - 1 else t
        if a == b:
            continue
        ok = alive[a] & alive[b] & alive[t]
        v[t, ok] = (m[b, ok] - m[a, ok]) / (times[b] - times[a])
        if a != t and b != t:
            # Surfels born at t: forward difference.
            fwd = alive[t] & alive[b] & ~alive[a]
            v[t, fwd] = (m[b, fwd] - m[t, fwd]) / (times[b] - times[t])
            # Surfels retired after t (replaced at a merge): backward difference.
            bwd = alive[t] & alive[a] & ~alive[b]
            v[t, bwd] = (m[t, bwd] - m[a, bwd]) / (times[t] - times[a])
    return v.astype(np.float32)


def bubble_table(
    arrays: dict[str, np.ndarray],
    times: np.ndarray,
    frames: np.ndarray,
    track_window_s: float = 0.0,
    track_order: int = 2,
    rules: tuple = (),
) -> pd.DataFrame:
    """Per frame and bubble: centroid (m) and velocity (m/s) of the surfels bound at that
    frame (weights ``o·s_x·s_y`` at that frame).

    The velocity is the finite difference of the centroid of those same surfels (same
    weights) between the neighbouring frames of the bubble's track: central where the
    track goes on both ways, one-sided at its first and last frame, as the ground truth's
    ``np.gradient`` of each bubble's centroid. A track ends where
    :func:`~surfphase.fit.binding.track_continues` says so (merge, split, bubble born from
    the nucleation region or spawned at that frame), so a velocity is never differenced
    across a merge; a bubble whose track lasts one frame only gets the central difference
    of its surfels.
    """
    F = arrays["means"].shape[0]
    alive = arrays["alive"]
    bub = np.where(alive, arrays["bubble"], -1)
    w = np.stack(
        [
            np.where(
                alive[t],
                binding.surfel_weights(arrays["opacity"][t], np.exp(arrays["log_scales"][t])),
                0.0,
            )
            for t in range(F)
        ]
    )
    rows = []
    for t in range(F):
        cent = binding.bubble_centroids(arrays["means"][t], bub[t], w[t])
        for bid, c in sorted(cent.items()):
            a = t - 1 if t > 0 else t
            e = t + 1 if t < F - 1 else t
            if a < t and binding.track_continues(bub[t], bub[a], w[t], w[a], bid) is None:
                a = t
            if e > t and binding.track_continues(bub[t], bub[e], w[t], w[e], bid) is None:
                e = t
            if a == e:  # a one-frame track: the surfels' own central difference
                a, e = max(t - 1, 0), min(t + 1, F - 1)
            vel = np.full(3, np.nan)
            if a != e:
                sel = (bub[t] == bid) & alive[a] & alive[e]
                if sel.any():
                    ids = np.where(sel, bid, -1)
                    vd = binding.bubble_velocities(
                        arrays["means"][a], arrays["means"][e], ids, w[t], times[e] - times[a]
                    )
                    if bid in vd:
                        vel = vd[bid]
            rows.append(
                {
                    "frame": int(frames[t]),
                    "time_s": float(times[t]),
                    "bubble": int(bid),
                    "x": c[0],
                    "y": c[1],
                    "z": c[2],
                    "vx": vel[0],
                    "vy": vel[1],
                    "vz": vel[2],
                    "n_surfels": int((bub[t] == bid).sum()),
                }
            )
    cols = ["frame", "time_s", "bubble", "x", "y", "z", "vx", "vy", "vz", "n_surfels"]
    table = pd.DataFrame(rows, columns=cols)
    if track_window_s > 0 and len(table):
        pos = {int(f): t for t, f in enumerate(frames)}
        seg = track_segments(table, [pos[int(f)] for f in table["frame"]], bub, w)
        smooth_tracks(table, seg, track_window_s, track_order, *rules)
    return table


def nucleation_frames(
    label_stacks: Sequence[np.ndarray],
    frames: np.ndarray,
    cameras: Sequence[Camera] | None = None,
) -> set[int]:
    """Session frame indices (``frames``, one per stack position) where every view's
    (T, H, W) label stack shows the nucleation region (id 0): as for a bubble, both
    views must see it (one view alone sees fragments on the plate's edge too). With the
    views' ``cameras``, the first two views must also agree on at least one piece of it
    (:func:`surfphase.masks.anchors.agreeing_pieces`: a bubble attached to the plate
    seen by both), not only show some fragment each."""
    from surfphase.masks.anchors import NUCLEATION_ID, agreeing_pieces

    views = None if cameras is None else [c.undistorted() for c in list(cameras)[:2]]
    out = set()
    for t, f in enumerate(frames):
        labs = [np.asarray(lab[t]) for lab in label_stacks]
        if not all(bool((lab == NUCLEATION_ID).any()) for lab in labs):
            continue
        if views is not None and not agreeing_pieces(views, labs[0], labs[1], NUCLEATION_ID):
            continue
        out.add(int(f))
    return out


def anchored_table(
    table: pd.DataFrame,
    anchors: pd.DataFrame,
    nucleation_frames: set[int],
    track_window_s: float,
    track_order: int,
    min_track_frames: int = 1,
    n_frames: int | None = None,
    rules: tuple = (),
    min_visible: float = 0.0,
    gap_frames: int = 0,
) -> pd.DataFrame:
    """``bubbles.csv`` with each bubble's centre from its triangulated silhouettes.

    A bubble (id ≥ 1) is reported in the frames where ``anchors`` has its centre (both
    input views see it and agree), at that centre, when those frames make a run of at
    least ``min_track_frames`` consecutive frames (as particle-tracking codes drop
    tracks shorter than a few frames: a speck seen once is not a bubble; a session of
    ``n_frames`` < ``min_track_frames`` frames needs runs of all its frames); its velocity is the central difference
    along each run of consecutive frames of the id (one-sided at the run's ends), or with
    ``track_window_s`` > 0 both the centres and the velocities come from the moving
    polynomial of :func:`smooth_tracks` along each run (so they agree). The nucleation
    region (id 0) keeps its surfels' centroid, in the frames of ``nucleation_frames``
    (its mask is seen there). ``n_surfels`` is kept. A row whose ``visible`` share
    (the anchors' column, when they have it) is under ``min_visible`` is left out of the
    smoothing of its run; its centre is placed on the parabola through the run's
    nearest other centres and it has no velocity (NaN; :func:`place_on_parabola`): a
    centre fitted to a short arc moves with the bubble's shape modes as well as with its
    centre, so differences of such centres are no velocity, and a track through them
    would show a user who differentiates it another velocity than the one reported
    beside them. A run with fewer than :data:`WEAK_MIN_SURE` other rows keeps its
    centres as measured and has no velocity at all. Up to ``gap_frames`` consecutive
    frames missing between two centres of one id (a frame where its two views
    disagreed) are filled (:func:`_gap_rows`): placed on that parabola, then smoothed
    with the run they join as if measured, and reported without a velocity. A bubble is
    not cut in two tracks, nor its short end dropped by ``min_track_frames``, for one
    bad frame.

    Args:
        table: :func:`bubble_table` without smoothing.
        anchors: ``frame, bubble, x, y, z`` (m, lab frame).
        nucleation_frames: session frame indices where every view's masks show id 0.
        track_window_s, track_order: as ``fit: track_window_s``, ``track_order``.
        rules: :func:`smooth_tracks`' further arguments (:func:`track_rules`).
        min_visible: as ``fit: track_min_visible``.
        gap_frames: as ``fit: track_gap_frames`` (needs the anchors' ``visible``).
    """
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    nuc = table[(table["bubble"] == 0) & table["frame"].isin(sorted(nucleation_frames))]
    bub = table[table["bubble"] >= 1].drop(columns=xyz + vel)
    low = ["low", "reproj_px"] if {"low", "reproj_px"} <= set(anchors.columns) else []
    ratio = ["size_ratio"] if low and "size_ratio" in anchors.columns else []
    vis = ["visible"] if "visible" in anchors.columns else []
    a = anchors[anchors["bubble"] >= 1][["frame", "bubble", *xyz, *low, *ratio, *vis]]
    bub = bub.merge(a, on=["frame", "bubble"], how="inner")
    bub = pd.concat([bub, _unfitted_rows(table, bub, a)], ignore_index=True)
    if not low:
        bub["low"], bub["reproj_px"] = False, 0.0
    if not ratio:
        bub["size_ratio"] = 1.0
    if vis and gap_frames > 0:
        bub = pd.concat([bub, _gap_rows(table, bub, int(gap_frames))], ignore_index=True)
    bub = bub.sort_values(["bubble", "frame"], kind="stable").reset_index(drop=True)
    seg = _runs(bub)
    need = int(min_track_frames) if n_frames is None else min(int(min_track_frames), n_frames)
    keep = np.bincount(seg)[seg] >= need
    bub = bub[keep].reset_index(drop=True)
    bub[vel] = np.nan
    gap = ~np.isfinite(bub["x"].to_numpy(np.float64))  # _gap_rows
    if gap.any():
        # Placed first, then smoothed with their run as if measured: the run stays
        # uniformly sampled; a run too short to place them by loses them.
        seg = _runs(bub)
        sure = np.bincount(seg, weights=~gap, minlength=seg.max() + 1)[seg]
        bub = bub[~gap | (sure >= WEAK_MIN_SURE)].reset_index(drop=True)
        gap = ~np.isfinite(bub["x"].to_numpy(np.float64))
        place_on_parabola(bub, _runs(bub), gap, _reach(rules, track_window_s) or np.inf, True)
    weak = np.zeros(len(bub), bool)
    if vis:
        weak = bub["visible"].to_numpy(np.float64) < float(min_visible)
    if weak.any():
        seg = _runs(bub)
        sure = np.bincount(seg, weights=~weak, minlength=seg.max() + 1)[seg]
        # A run with too few sure centres to place the others by: measured, no velocity.
        measured = sure < WEAK_MIN_SURE
        fit = ~weak & ~measured
        part = bub[fit].reset_index(drop=True)
        _track_velocities(part, _runs(part), track_window_s, track_order, rules)
        bub.loc[fit, xyz + vel] = part[xyz + vel].to_numpy()
        # Over the leads' reach; the whole run where the track is not smoothed.
        reach = _reach(rules, track_window_s) or np.inf
        place_on_parabola(bub, seg, weak & ~measured, reach, velocity=False)
    else:
        _track_velocities(bub, _runs(bub), track_window_s, track_order, rules)
    bub.loc[gap, vel] = np.nan  # not measured: no velocity
    out = pd.concat([nuc, bub[table.columns]], ignore_index=True)
    return out.sort_values(["frame", "bubble"], kind="stable").reset_index(drop=True)


def _unfitted_rows(table: pd.DataFrame, bub: pd.DataFrame, a: pd.DataFrame) -> pd.DataFrame:
    """:func:`anchored_table`'s rows of the anchors ``a`` that no surfels of their id
    have at that frame (``bub``: the rows that have): a bubble leaving the frame, whose
    sliver the fit no longer holds (its continued centres,
    :func:`surfphase.masks.anchors.continued_centres`), or one the fit gave no surfels
    in a frame where both views' silhouettes agree on its centre, is reported there all
    the same (``n_surfels`` 0; ``time_s`` from the table's uniform sampling)."""
    have = bub.set_index(["frame", "bubble"]).index
    rows = a[~a.set_index(["frame", "bubble"]).index.isin(have)]
    times = _frame_times(table, rows["frame"].to_numpy()) if len(rows) else None
    if times is None:
        return bub.iloc[:0]
    out = rows.copy()
    out["time_s"] = times
    for c in bub.columns:
        if c not in out.columns:
            out[c] = 0 if c == "n_surfels" else np.nan
    return out[bub.columns]


def _frame_times(table: pd.DataFrame, frames: np.ndarray) -> np.ndarray | None:
    """(n,) times (s) of session ``frames`` from the table's uniform sampling (the line
    through its frames' ``time_s``); None where it has fewer than two frames."""
    ft = table.drop_duplicates("frame")[["frame", "time_s"]].to_numpy(np.float64)
    if len(ft) < 2:
        return None
    slope, icpt = np.polyfit(ft[:, 0], ft[:, 1], 1)
    return icpt + slope * np.asarray(frames, np.float64)


#: A gap in a track is filled only between centres whose views agree to within this
#: many pixels (``reproj_px``; the classical baseline's own test of a centre off the
#: epipolar geometry, :data:`surfphase.eval.baseline.MAX_REPROJ_PX`): a gap where a
#: pairing goes bad (its centres drifting 0.3-0.5 r_eq off over the frames before,
#: disagreeing by 1-3 px) would join a bad run to a good one.
GAP_MAX_REPROJ_PX = 0.75


def _gap_rows(table: pd.DataFrame, bub: pd.DataFrame, gap_frames: int) -> pd.DataFrame:
    """:func:`anchored_table`'s rows for the frames, at most ``gap_frames`` in a row,
    missing between two rows of one id in ``bub`` whose centres are both sound
    (``reproj_px`` at most :data:`GAP_MAX_REPROJ_PX`): no centre yet (NaN; the run's
    parabola places it), ``visible`` 1 and ``low`` False (smoothed with its run), no
    velocity; ``time_s`` from the table's uniform sampling, ``n_surfels`` from its row
    of that frame and id (0 without one)."""
    f = bub["frame"].to_numpy(np.int64)
    b = bub["bubble"].to_numpy(np.int64)
    order = np.lexsort((f, b))
    f, b = f[order], b[order]
    rep = bub["reproj_px"].to_numpy(np.float64)[order]
    step = np.diff(f)
    sound = (rep[:-1] <= GAP_MAX_REPROJ_PX) & (rep[1:] <= GAP_MAX_REPROJ_PX)
    at = np.flatnonzero((b[1:] == b[:-1]) & (step > 1) & (step <= gap_frames + 1) & sound)
    missing = [(int(f[i]) + k, int(b[i])) for i in at for k in range(1, int(step[i]))]
    out = pd.DataFrame(missing, columns=["frame", "bubble"])
    times = _frame_times(table, out["frame"].to_numpy()) if missing else None
    if times is None:
        return bub.iloc[:0]
    have = table.drop_duplicates(["frame", "bubble"]).set_index(["frame", "bubble"])
    key = pd.MultiIndex.from_frame(out)
    out["time_s"] = times
    if "n_surfels" in bub.columns:
        out["n_surfels"] = have["n_surfels"].reindex(key).fillna(0).to_numpy().astype(int)
    out["visible"], out["low"], out["reproj_px"], out["size_ratio"] = 1.0, False, 0.0, 1.0
    for c in bub.columns:
        if c not in out.columns:
            out[c] = np.nan
    return out[bub.columns]


#: Fewest rows of a run with a sure centre (``visible`` at least ``fit:
#: track_min_visible``) that place its mostly hidden ones (:func:`place_on_parabola`).
WEAK_MIN_SURE = 3


def place_on_parabola(
    bub: pd.DataFrame, seg: np.ndarray, placed: np.ndarray, window_s: float, velocity: bool
) -> None:
    """Centres of each run's ``placed`` rows from the parabola fitted (least squares) to
    its other rows' centres over ``window_s`` seconds from the nearest of them (at least
    3 rows, else the 3 nearest), and the velocities of the run ``np.gradient`` of its
    centres, so that track and velocity still agree (NaN at the placed rows unless
    ``velocity``); in place. ``bub``: rows ``time_s, x, y, z, vx, vy, vz``, each run's
    rows (``seg``) in time order, at least 3 of them not placed in each run that has
    placed ones."""
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    for s in np.unique(seg[placed]):
        rows = np.flatnonzero(seg == s)
        t = bub["time_s"].to_numpy(np.float64)[rows]
        p = bub[xyz].to_numpy(np.float64)[rows]
        moved = placed[rows]
        known = np.flatnonzero(~moved)
        for i in np.flatnonzero(moved):
            j = known[np.argmin(np.abs(t[known] - t[i]))]
            ref = known[np.abs(t[known] - t[j]) <= window_s + 1e-12]
            if len(ref) < 3:
                ref = known[np.argsort(np.abs(t[known] - t[i]), kind="stable")[:3]]
            coef = np.polyfit(t[ref] - t[j], p[ref], 2)  # (3, 3): one parabola per axis
            p[i] = [np.polyval(coef[:, k], t[i] - t[j]) for k in range(3)]
        v = np.gradient(p, t, axis=0) if len(rows) > 1 else np.full((1, 3), np.nan)
        if not velocity:
            v[moved] = np.nan
        bub.loc[bub.index[rows], xyz] = p
        bub.loc[bub.index[rows], vel] = v


def _runs(bub: pd.DataFrame) -> np.ndarray:
    """(R,) run id of each row of ``bub`` (rows sorted by bubble, then frame): a run is
    one bubble's consecutive frames."""
    f = bub["frame"].to_numpy(np.int64)
    b = bub["bubble"].to_numpy(np.int64)
    new_run = np.r_[True, (b[1:] != b[:-1]) | (f[1:] != f[:-1] + 1)][: len(b)]
    return np.cumsum(new_run)


def _reach(rules: tuple, track_window_s: float) -> float:
    """Seconds over which a run's placed centres take their parabola: the blend window
    (``rules``' third entry, :func:`track_rules`), else ``track_window_s``."""
    return (rules[2] if len(rules) > 2 else 0.0) or track_window_s


def _track_velocities(
    bub: pd.DataFrame, seg: np.ndarray, track_window_s: float, track_order: int, rules: tuple
) -> None:
    """:func:`anchored_table`'s velocities (and smoothed centres) of the rows of ``bub``
    along their runs ``seg``, in place."""
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    for s in np.unique(seg):
        rows = np.flatnonzero(seg == s)
        if len(rows) >= 2:
            t = bub["time_s"].to_numpy()[rows]
            bub.loc[rows, vel] = np.gradient(bub[xyz].to_numpy(np.float64)[rows], t, axis=0)
    if track_window_s > 0 and len(bub):
        reach = _reach(rules, track_window_s)
        lead = lead_rows(
            bub["low"].to_numpy(bool), bub["reproj_px"].to_numpy(np.float64),
            bub["time_s"].to_numpy(np.float64), seg, reach,
            bub["size_ratio"].to_numpy(np.float64),
        )  # fmt: skip
        clean = bub[~lead].copy()
        smooth_tracks(clean, seg[~lead], track_window_s, track_order, *rules)
        bub.loc[~lead, xyz + vel] = clean[xyz + vel].to_numpy()
        if lead.any():
            extrapolate_leads(bub, seg, lead, reach)


#: A low row leads its track when its views disagree this many times more than the
#: track's next rows at most: damaged silhouettes disagreed by 0.65–0.98 px against
#: 0.05–0.2 px after them (benchmark session03); sound ones by as little as the rows
#: after them, give or take their noise (0.01–0.1 px at 10,000 fps).
LEAD_REPROJ_FACTOR = 2.0

#: The same test on the sizes the two views give a centre (the anchors' ``size_ratio``,
#: its excess over 1), but never below this excess: over the benchmark's 9,558
#: triangulated centres (sixteen draws) those whose views agree on size to within 5 %
#: lie 0.011-0.017 r_eq from the truth (median), against 0.12-3.1 r_eq over 15 %.
LEAD_SIZE_EXCESS_MIN = 0.05


def lead_rows(
    low: np.ndarray,
    reproj: np.ndarray,
    t: np.ndarray,
    seg: np.ndarray,
    window_s: float,
    size_ratio: np.ndarray | None = None,
) -> np.ndarray:
    """(R,) bool: the rows that lead a track (``seg``, rows in time order) with ``low``
    set (a bubble just off the plate), up to the last of them whose two views disagree
    (``reproj``: the anchors' ``reproj_px``; or ``size_ratio``, (R,) ≥ 1, the anchors'
    ratio of the sizes the views give the centre, its excess over 1 and over
    :data:`LEAD_SIZE_EXCESS_MIN`) more than :data:`LEAD_REPROJ_FACTOR` times as much as
    in any row of the track's next ``window_s`` seconds (``t``: seconds): there the
    plate's image damaged a silhouette and its centroid is not its centre's
    projection. A track with fewer than 3 rows after them has none."""
    out = np.zeros(len(seg), bool)
    excess = None if size_ratio is None else np.nan_to_num(size_ratio - 1.0, nan=0.0)
    for s in np.unique(seg):
        rows = np.flatnonzero(seg == s)
        k = int(np.argmin(low[rows])) if not low[rows].all() else len(rows)
        if not k or len(rows) - k < 3:
            continue
        after = rows[k:]
        after = after[t[after] <= t[after[0]] + window_s + 1e-12]
        ref = LEAD_REPROJ_FACTOR * float(reproj[after].max())
        damaged = reproj[rows[:k]] > ref
        if excess is not None:
            ref_size = max(LEAD_REPROJ_FACTOR * float(excess[after].max()), LEAD_SIZE_EXCESS_MIN)
            damaged |= excess[rows[:k]] > ref_size
        bad = np.flatnonzero(damaged)
        if bad.size:
            out[rows[: bad[-1] + 1]] = True
    return out


def extrapolate_leads(
    bub: pd.DataFrame, seg: np.ndarray, lead: np.ndarray, window_s: float
) -> None:
    """Centres of each track's ``lead`` rows from the parabola fitted (least squares) to
    its smoothed centres over its first ``window_s`` seconds after them (at least 3
    rows), and the velocities of the whole track again ``np.gradient`` of its centres,
    so that track and velocity still agree; in place (:func:`place_on_parabola`).
    ``bub``: rows ``time_s, x, y, z, vx, vy, vz``, each track's rows in time order."""
    place_on_parabola(bub, seg, lead, window_s, velocity=True)


def track_segments(
    table: pd.DataFrame, positions: list[int], bub: np.ndarray, w: np.ndarray
) -> np.ndarray:
    """(rows,) id of the track each row of ``table`` belongs to.

    Row (t, b) and row (t + 1, q) are one track when ``b`` continues as ``q``
    (:func:`~surfphase.fit.binding.track_continues`, both ways); a merge, a split or
    the nucleation region ends it. ``positions``: each row's frame position t;
    ``bub``, ``w``: (F, N) surfel bubble ids (−1 unbound) and centroid weights.
    """
    at = {(t, int(b)): r for r, (t, b) in enumerate(zip(positions, table["bubble"], strict=True))}
    seg = np.arange(len(table))
    for (t, b), r in sorted(at.items()):  # in time order: a track's id propagates
        if b == 0 or t + 1 >= len(bub):
            continue
        q = binding.track_continues(bub[t], bub[t + 1], w[t], w[t + 1], b)
        if q is not None and int(q) != 0 and (t + 1, int(q)) in at:
            seg[at[(t + 1, int(q))]] = seg[r]
    return seg


#: Largest lag-1 autocorrelation of a parabola's residuals that :func:`quadratic_t`
#: credits (its variance then at most tripled): from a handful of samples the estimate
#: is too rough to trust further.
CURVATURE_MAX_RHO = 0.5


def quadratic_t(times: np.ndarray, values: np.ndarray) -> float:
    """The largest |t-statistic| of the quadratic coefficient, over the columns of
    (n, D) ``values`` against (n,) ``times`` (s), of a least-squares parabola per column
    (its residuals give the noise); 0 with fewer than 5 samples.

    The residuals' variance is taken as serially correlated: multiplied by ``(1 + ρ) /
    (1 − ρ)``, the variance inflation of a mean of AR(1) noise, with ``ρ`` their lag-1
    autocorrelation clipped to [0, :data:`CURVATURE_MAX_RHO`]. A silhouette's centre
    errs with the bubble's shape modes, slowly against a high frame rate (at 6,750–
    10,000 fps the same error spans several frames), and white-noise standard errors
    then call that drift a significant curvature. Uncorrelated residuals (ρ ≤ 0) leave
    the statistic as it was."""
    n = len(times)
    if n < 5:
        return 0.0
    x = (np.asarray(times, np.float64) - np.mean(times)) / max(float(np.ptp(times)), 1e-30)
    X = np.stack([np.ones(n), x, x * x], axis=1)
    y = np.asarray(values, np.float64).reshape(n, -1)
    beta = np.linalg.lstsq(X, y, rcond=None)[0]
    res = y - X @ beta
    ss = (res**2).sum(axis=0)
    rho = (res[1:] * res[:-1]).sum(axis=0) / np.maximum(ss, 1e-300)
    rho = np.clip(rho, 0.0, CURVATURE_MAX_RHO)
    var = float(np.linalg.inv(X.T @ X)[2, 2]) * ss / (n - 3) * (1.0 + rho) / (1.0 - rho)
    return float(np.max(np.abs(beta[2]) / np.sqrt(np.maximum(var, 1e-300))))


#: Fewest rows of a track for :func:`smooth_tracks`' outlier pass: with fewer, the median
#: residual is no scale of the centres' noise.
OUTLIER_MIN_ROWS = 7


def smooth_tracks(
    table: pd.DataFrame,
    seg: np.ndarray,
    window_s: float,
    order: int,
    end_window_s: float = 0.0,
    end_t: float = 0.0,
    blend_window_s: float = 0.0,
    blend_order: int = 2,
    outlier_k: float = 0.0,
    reproj_px: float = 0.0,
) -> None:
    """Replace each track's centroids and velocities by a moving polynomial fit, in place.

    Along each track (``seg``, rows in time order, uniformly sampled), the centroid
    ``x y z`` is smoothed by a moving polynomial (``scipy.signal.savgol_filter`` of order
    ``order`` over ``window_s`` seconds, made an odd number of frames and capped at the
    track; ``mode="interp"`` fits the ends), the track smoothing of particle-tracking
    codes, and ``vx vy vz`` is ``np.gradient`` of the smoothed track (central
    differences, one-sided at its ends: the ground truth's own convention). So the
    reported centroids and velocities agree by construction. Tracks of ``order + 1``
    frames or fewer, and the nucleation region (bubble 0), are left as they are.

    A low order over the last window of a track lags an accelerating bubble (the
    line's slope is the velocity of the window's middle): with ``end_window_s`` > 0, at
    each end of a track whose centre is significantly curved over its first / last
    ``end_window_s`` seconds (the parabola's quadratic coefficient more than ``end_t``
    standard errors from 0 in some axis, :func:`quadratic_t`), the half window of rows
    at that end takes a moving parabola over ``end_window_s`` (``savgol_filter`` of
    order 2) instead; not on a track shorter than ``end_window_s``, whose ends are its
    whole (the test would weigh the curvature of all of it).

    With ``blend_window_s`` > 0 the track is the mean of that smoothing and a second
    moving polynomial of order ``blend_order`` over ``blend_window_s`` seconds (capped at
    the track likewise; left out where the track is too short for it): one linear
    smoother whose kernel is the mean of the two, a short low-order window that follows
    a bubble's changes and a long higher-order one that averages more of its noise. On
    a track shorter than ``blend_window_s`` that polynomial is one fit over the whole
    track, and is used only where the track's curvature is significant
    (:func:`quadratic_t` of the whole track more than ``end_t``): at 7,500–10,000 fps a
    2–3 ms track's curvature is mostly its silhouette centres' bias, and a parabola
    through it gives a bubble at constant speed a velocity that drifts 0.03–0.07 m/s
    over the track.

    With ``outlier_k`` > 0, on a track of at least :data:`OUTLIER_MIN_ROWS` rows, a
    centre farther from that smoothed track than ``outlier_k`` times the track's median
    distance (m, 3D) is an outlier (a frame where a view's silhouette was damaged: its
    two views then disagree, but within the mask stage's gates): it is replaced by its
    smoothed value and the track smoothed again, so one bad frame does not bend the
    velocities of its neighbours. A moving polynomial is a least-squares fit, which one
    gross error pulls over its whole window.

    With ``reproj_px`` > 0 and a ``reproj_px`` column in ``table`` (the anchors': how far
    apart, in pixels, a centre's two views put it), every moving polynomial above is a
    weighted least-squares fit, a centre's weight ``1 / (1 + (e / reproj_px)²)`` for its
    disagreement ``e``: a centre whose views disagree by ``reproj_px`` counts as twice
    as noisy as one whose views agree. Where a view's silhouette is damaged (by the
    plate beside it, by a neighbour), its centroid is off and the two views no longer
    meet: over the benchmark's triangulated centres the error grows with the
    disagreement, from 0.011 r_eq (median) below 0.1 px to 0.03 r_eq at 0.3–0.5 px and
    0.056 r_eq above (CHANGELOG.md, session 47).
    """
    if order < 1:
        raise ValueError(f"fit: track_order must be >= 1, got {order}")
    if reproj_px < 0:
        raise ValueError(f"fit: track_reproj_px must be >= 0 (0: off), got {reproj_px}")
    xyz, vel = ["x", "y", "z"], ["vx", "vy", "vz"]
    ends, blend = (end_window_s, end_t), (blend_window_s, blend_order)
    for s in np.unique(seg):
        rows = np.flatnonzero(seg == s)
        rows = rows[np.argsort(table["time_s"].to_numpy()[rows])]
        if len(rows) <= order + 1 or int(table["bubble"].iloc[rows[0]]) == 0:
            continue
        t = table["time_s"].to_numpy()[rows]
        p = table[xyz].to_numpy(np.float64)[rows]
        w = None
        if reproj_px > 0 and "reproj_px" in table.columns:
            w = centre_weights(table["reproj_px"].to_numpy(np.float64)[rows], reproj_px)
        smooth = _smooth_track(t, p, window_s, order, ends, blend, w)
        if smooth is None:
            continue
        if outlier_k > 0 and len(rows) >= OUTLIER_MIN_ROWS:
            r = np.linalg.norm(p - smooth, axis=1)
            out = r > outlier_k * float(np.median(r))
            if out.any():
                p[out] = smooth[out]
                smooth = _smooth_track(t, p, window_s, order, ends, blend, w)
        table.loc[table.index[rows], xyz] = smooth
        table.loc[table.index[rows], vel] = np.gradient(smooth, t, axis=0)


def centre_weights(reproj: np.ndarray, reproj_px: float) -> np.ndarray:
    """(n,) weights of a track's centres in its smoothing from their (n,) disagreements
    ``reproj`` (pixels; NaN, a centre placed rather than measured: 0):
    ``1 / (1 + (reproj / reproj_px)²)`` (:func:`smooth_tracks`)."""
    e = np.nan_to_num(np.asarray(reproj, dtype=np.float64), nan=0.0)
    return 1.0 / (1.0 + (e / float(reproj_px)) ** 2)


def _smooth_track(
    t: np.ndarray,
    p: np.ndarray,
    window_s: float,
    order: int,
    ends: tuple[float, float],
    blend: tuple[float, int],
    weights: np.ndarray | None = None,
) -> np.ndarray | None:
    """One track's smoothed (n, 3) centres (m) from its (n,) times (s) and (n, 3)
    centres, as :func:`smooth_tracks` describes (``ends``: ``(end_window_s, end_t)``,
    ``blend``: ``(blend_window_s, blend_order)``, ``weights``: (n,) the centres'
    weights, None: equal); ``None`` when the window holds no more than ``order``
    frames."""
    (end_window_s, end_t), (blend_window_s, blend_order) = ends, blend
    dt = float(np.median(np.diff(t)))
    win = savgol_window(window_s / dt, order, len(t))
    if win <= order:
        return None
    smooth = moving_polynomial(p, win, order, weights)
    # A track shorter than the end window has no end apart from its middle: the test
    # would weigh the curvature of all of it, which its centres' shape-mode biases
    # give as much as an acceleration does.
    if end_window_s > 0 and order < 2 and len(t) * dt >= end_window_s * (1.0 - 1e-9):
        w2 = savgol_window(end_window_s / dt, 2, len(t))
        if w2 >= 5:
            para = moving_polynomial(p, w2, 2, weights)
            n, h = len(t), win // 2
            for rs, fit in ((slice(0, h), slice(0, w2)), (slice(n - h, n), slice(n - w2, n))):
                if quadratic_t(t[fit], p[fit]) > end_t:
                    smooth[rs] = para[rs]
    # A track shorter than the blend window takes one polynomial over all of it, whose
    # curvature, like the end test's above, is as much the centres' bias as an
    # acceleration: there only where that curvature is significant (end_t).
    short = len(t) * dt < blend_window_s * (1.0 - 1e-9)
    if blend_window_s > 0 and (not short or end_t <= 0 or quadratic_t(t, p) > end_t):
        w3 = savgol_window(blend_window_s / dt, int(blend_order), len(t))
        if w3 >= int(blend_order) + 2:  # fewer frames: the polynomial is the data
            long = moving_polynomial(p, w3, int(blend_order), weights)
            smooth = 0.5 * (smooth + long)
    return smooth


def track_rules(p: Mapping) -> tuple[float, float, float, int, float, float]:
    """:func:`smooth_tracks`' arguments after the window and order, from the fit's
    settings: ``(track_end_window_s, track_end_t, track_blend_window_s,
    track_blend_order, track_outlier_k, track_reproj_px)``."""
    return (
        float(p["track_end_window_s"]),
        float(p["track_end_t"]),
        float(p["track_blend_window_s"]),
        int(p["track_blend_order"]),
        float(p["track_outlier_k"]),
        float(p["track_reproj_px"]),
    )


def load_surfels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``surfels.npz`` into a dict of arrays."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no surfels.npz")
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def render_surfels(
    surfels: dict[str, np.ndarray],
    frame: int,
    cameras: Sequence[Camera],
    device: str | torch.device = "cpu",
    backgrounds: np.ndarray | None = None,
) -> np.ndarray:
    """Render frame index ``frame`` (0-based position in the file) of ``surfels`` into
    ``cameras`` over ``backgrounds`` ((C, H, W, D) images; default the constant
    ``surfels["background"]``); returns (C, H, W, D) float32 in [0, 1]."""
    import torch

    from surfphase.render import over_background

    dev = torch.device(device)
    rgb, alpha = rasterize_frame(surfels, frame, cameras, dev)
    bg = surfels["background"] if backgrounds is None else backgrounds
    rgb = over_background(rgb, alpha, torch.as_tensor(np.asarray(bg, np.float32), device=dev))
    return rgb.clamp(0, 1).cpu().numpy()


def _to_png(img: np.ndarray) -> np.ndarray:
    a = np.clip(img, 0, 1)
    if a.shape[-1] == 1:
        a = a[..., 0]
    return (a * 255 + 0.5).astype(np.uint8)


def write_outputs(out_dir: Path, records, data, p: dict, background, extent: float, device):
    """Write surfels.npz, bubbles.csv, curves.csv, renders/, summary.json; return summary."""
    import cv2
    import torch

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    F = len(records)
    times = data.times[:F]
    frames = data.frame_indices[:F]
    arrays = stack_records(records, extent)
    arrays["velocity"] = surfel_velocities(arrays["means"], arrays["alive"], times)
    arrays["frame"] = frames
    arrays["time_s"] = times
    arrays["bg_images"] = np.asarray(background, np.float32)
    arrays["background"] = np.median(arrays["bg_images"], axis=(0, 1, 2)).astype(np.float32)
    arrays["extent"] = np.float64(extent)

    # Renders of the input views: observed | rendered.
    tmp_dir = out_dir / ".renders.part"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    tmp_dir.mkdir(parents=True)
    pick = sorted(set(np.linspace(0, F - 1, max(int(p["render_frames"]), 1)).round().astype(int)))
    for t in pick:
        rgb = render_surfels(arrays, t, data.cameras, device, arrays["bg_images"])
        obs = data.images(t)
        for c, cam in enumerate(data.cameras):
            pair = np.concatenate([obs[c], rgb[c]], axis=1)
            img = _to_png(pair)
            if img.ndim == 3:
                img = img[..., ::-1]
            cv2.imwrite(str(tmp_dir / f"frame{int(frames[t]):05d}_{cam.name}.png"), img)
    final = out_dir / "renders"
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp_dir, final)

    rules = track_rules(p)
    if p["anchor_centres"] and data.anchors is not None:
        table = anchored_table(
            bubble_table(arrays, times, frames),
            data.anchors[data.anchors["frame"].isin(frames)],  # ``frames``: those fitted
            data.nucleation_frames(),
            float(p["track_window_s"]),
            int(p["track_order"]),
            int(p["min_track_frames"]),
            F,
            rules,
            float(p["track_min_visible"]),
            int(p["track_gap_frames"]),
        )
    else:
        table = bubble_table(
            arrays, times, frames, float(p["track_window_s"]), int(p["track_order"]), rules
        )
    atomic_write_text(out_dir / "bubbles.csv", table.to_csv(index=False))
    curves = pd.DataFrame([row for r in records for row in r["curves"]])
    atomic_write_text(out_dir / "curves.csv", curves.to_csv(index=False))

    secs = [r["seconds_optimise"] for r in records]
    iters = [r["iters"] for r in records]
    summary = {
        "session": data.session,
        "frames": F,
        "cameras": [c.name for c in data.cameras],
        "width": data.width,
        "height": data.height,
        "extent_m": extent,
        "use_sdf": bool(p["use_sdf"]),
        "guidance": bool(p["guidance"]),
        "n_surfels": [int(r["means"].shape[0]) for r in records],
        "psnr_per_frame": [r["psnr"] for r in records],
        "psnr_mean": float(np.mean([np.mean(r["psnr"]) for r in records])),
        "spawned": {int(r["frame"]): r["spawned"] for r in records if r["spawned"]},
        "reseeded": {
            int(r["frame"]): sorted(int(b) for b in r["reseeded"])
            for r in records
            if r.get("reseeded")
        },
        "seconds_per_frame": [r["seconds"] for r in records],
        "seconds_first_frame": secs[0],
        "seconds_per_later_frame": float(np.mean(secs[1:])) if F > 1 else None,
        "seconds_per_iter": float(np.sum(secs) / max(np.sum(iters), 1)),
        "threads": torch.get_num_threads(),
        "device": str(device),
        # The CPU kernels PyTorch and MKL ran (import surfphase pins them: the fit's
        # bits depend on them).
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "mkl_cbwr": os.environ.get("MKL_CBWR", ""),
        "platform": platform_record(),
    }
    atomic_write_json(out_dir / "summary.json", summary)
    with atomic_path(out_dir / "surfels.npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return summary
