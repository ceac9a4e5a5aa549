"""The classical two-view baseline experimentalists use: triangulate each bubble's 2D
mask centroid from the views that see it, then difference the 3D centroids over time.

Pixels per docs/conventions.md §4 (origin at the centre of the top-left pixel; ``u`` = column,
``v`` = row) and belong to the *undistorted* ingest frames, so the ingest cameras
(zero distortion) triangulate them directly. Velocities: central differences
``(c[k+1] − c[k−1]) / (t[k+1] − t[k−1])`` inside each bubble's run of consecutive
frames, one-sided at the run's ends, NaN for a run of one frame; ``t = frame / fps``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from surfphase.cameras import Camera, triangulate
from surfphase.tracks import savgol_window

#: A (frame, bubble) whose triangulated centroid reprojects farther than this from its
#: mask centroid in any view (pixels of the masks) is left out, as a classical two-view
#: pipeline rejects matches off the epipolar geometry: two views of one bubble agree to
#: a fraction of a pixel, a fragment or a merge whose views differ does not. On the
#: accuracy benchmark's 8 sessions (native masks, smoothed 8 ms / order 2) the mean
#: relative velocity error is 0.0363 / 0.0277 / 0.0281 / 0.0317 / 0.0767 at gates of
#: 0.25 / 0.5 / 0.75 / 1 / ≥ 3 px; 0.75 is near the best, away from the drop below 0.5.
MAX_REPROJ_PX = 0.75

#: Columns of the bubbles table (as the fit's ``bubbles.csv``), plus mask pixels.
BUBBLE_COLUMNS = ["frame", "time_s", "bubble", "x", "y", "z", "vx", "vy", "vz", "n_pixels"]


def mask_centroids(labels: np.ndarray) -> pd.DataFrame:
    """Centroids of every labelled region of a (T, H, W) int label stack.

    Returns ``index, bubble, u, v, area`` (``index`` = position in the stack; pixels;
    ``area`` in pixels); label −1 is background and skipped.
    """
    labels = np.asarray(labels)
    if labels.ndim != 3:
        raise ValueError(f"expected a (T, H, W) label stack, got shape {labels.shape}")
    H, W = labels.shape[1:]
    vv, uu = np.mgrid[0:H, 0:W]
    rows = []
    for k in range(labels.shape[0]):
        lab = np.asarray(labels[k]).ravel()
        fg = lab >= 0
        if not fg.any():
            continue
        ids, inv = np.unique(lab[fg], return_inverse=True)
        area = np.bincount(inv)
        su = np.bincount(inv, weights=uu.ravel()[fg])
        sv = np.bincount(inv, weights=vv.ravel()[fg])
        for i, b in enumerate(ids):
            rows.append((k, int(b), su[i] / area[i], sv[i] / area[i], int(area[i])))
    return pd.DataFrame(rows, columns=["index", "bubble", "u", "v", "area"])


def finite_difference(
    keys: np.ndarray, index: np.ndarray, times: np.ndarray, values: np.ndarray
) -> np.ndarray:
    """Time derivative of ``values`` along each key's runs of consecutive indices.

    Args:
        keys: (N,) track id of each sample (e.g. bubble id).
        index: (N,) integer frame position; a run is a stretch of consecutive positions.
        times: (N,) seconds.
        values: (N, D) quantity to differentiate.

    Returns:
        (N, D) derivative (units of ``values`` per second): central inside a run,
        one-sided at its ends, NaN for a run of one sample.
    """
    keys, index = np.asarray(keys), np.asarray(index, dtype=np.int64)
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64).reshape(len(keys), -1)
    out = np.full(values.shape, np.nan)
    order = np.lexsort((index, keys))
    k, i, t, x = keys[order], index[order], times[order], values[order]
    n = len(order)
    for j in range(n):
        prev = j > 0 and k[j - 1] == k[j] and i[j - 1] == i[j] - 1
        nxt = j + 1 < n and k[j + 1] == k[j] and i[j + 1] == i[j] + 1
        a = j - 1 if prev else j
        b = j + 1 if nxt else j
        if a != b:
            out[order[j]] = (x[b] - x[a]) / (t[b] - t[a])
    return out


def baseline_bubbles(
    cameras: Sequence[Camera],
    label_stacks: Sequence[np.ndarray],
    frame_indices: np.ndarray,
    fps: float,
    max_reproj_px: float | None = MAX_REPROJ_PX,
) -> pd.DataFrame:
    """Triangulated mask centroids and their finite-difference velocities.

    Args:
        cameras: the undistorted cameras of the label stacks (same order).
        label_stacks: per camera, a (T, H, W) int label stack (−1 background, ids shared
            across views and time).
        frame_indices: (T,) session frame index of each stack position.
        fps: frames per second.
        max_reproj_px: leave out a (frame, bubble ≥ 1) whose centroid reprojects farther
            than this (pixels) from its mask centroid in any view (None: keep all; the
            nucleation region, id 0, a patch of the plate rather than a body, is kept);
            velocities are differenced over the runs of consecutive frames kept.

    Returns:
        :data:`BUBBLE_COLUMNS`: for every (frame, bubble) seen in at least two views and
        consistent with them, the DLT-triangulated centroid (m, lab frame) and velocity
        (m/s); ``n_pixels`` sums the mask areas over the views.
    """
    if len(cameras) != len(label_stacks) or len(cameras) < 2:
        raise ValueError("baseline: need ≥ 2 cameras, one label stack each")
    frame_indices = np.asarray(frame_indices, dtype=np.int64)
    per_view = []
    for c, labs in enumerate(label_stacks):
        df = mask_centroids(labs)
        df["view"] = c
        per_view.append(df)
    allc = pd.concat(per_view, ignore_index=True)
    rows = []
    for (k, b), g in allc.groupby(["index", "bubble"], sort=True):
        if len(g) < 2:
            continue
        cams = [cameras[int(c)] for c in g["view"]]
        uvs = [g[["u", "v"]].to_numpy()[j : j + 1] for j in range(len(g))]
        X = triangulate(cams, uvs)[0]
        if max_reproj_px is not None and b >= 1:  # not the nucleation region (id 0)
            err = max(
                float(np.hypot(*(cam.project(X[None], distort=False)[0] - uv[0])))
                for cam, uv in zip(cams, uvs, strict=True)
            )
            if not err <= float(max_reproj_px):
                continue
        f = int(frame_indices[int(k)])
        rows.append((int(k), f, f / fps, int(b), *X, int(g["area"].sum())))
    tab = pd.DataFrame(
        rows, columns=["index", "frame", "time_s", "bubble", "x", "y", "z", "n_pixels"]
    )
    vel = finite_difference(
        tab["bubble"].to_numpy(), tab["index"].to_numpy(), tab["time_s"].to_numpy(),
        tab[["x", "y", "z"]].to_numpy(),
    )  # fmt: skip
    tab[["vx", "vy", "vz"]] = vel if len(tab) else np.zeros((0, 3))
    return tab[BUBBLE_COLUMNS].sort_values(["frame", "bubble"]).reset_index(drop=True)


def smoothed_velocity(
    keys: np.ndarray,
    index: np.ndarray,
    times: np.ndarray,
    values: np.ndarray,
    fps: float,
    window_s: float,
    order: int,
) -> np.ndarray:
    """Velocity along each track from a moving polynomial fit (Savitzky–Golay, ``deriv=1``).

    The track smoothing of particle-tracking codes (MyPTV; Lüthi et al. 2005): along
    each key's runs of consecutive indices, ``scipy.signal.savgol_filter`` of order
    ``order`` over a window of ``window_s`` seconds — ``round(window_s·fps)`` frames,
    made odd, at least ``order + 2`` — so one setting holds across frame rates. A run
    shorter than the window uses the longest odd window it holds (``mode="interp"``: the
    polynomial fitted to the run's first / last window gives its ends); a run of
    ``order + 1`` samples or fewer, and ``window_s = 0``, fall back to
    :func:`finite_difference`.

    Args:
        keys, index, times, values: as :func:`finite_difference` ((N,), (N,), (N,) s,
            (N, D)); ``times`` must be ``index / fps`` (uniform sampling).
        fps: frames per second.
        window_s: window length, seconds (0: no smoothing).
        order: polynomial order (≥ 1).

    Returns:
        (N, D) derivative of ``values`` per second.
    """
    from scipy.signal import savgol_filter

    if order < 1:
        raise ValueError(f"smoothing: polynomial order must be ≥ 1, got {order}")
    if window_s < 0 or fps <= 0:
        raise ValueError(f"smoothing: need window_s ≥ 0 and fps > 0, got {window_s}, {fps}")
    out = finite_difference(keys, index, times, values)
    if window_s == 0:
        return out
    keys, index = np.asarray(keys), np.asarray(index, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64).reshape(len(keys), -1)
    order_idx = np.lexsort((index, keys))
    k, i = keys[order_idx], index[order_idx]
    # Run boundaries: a new key or a gap in the index.
    start = np.r_[True, (k[1:] != k[:-1]) | (i[1:] != i[:-1] + 1)]
    bounds = np.r_[np.flatnonzero(start), len(order_idx)]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        win = savgol_window(window_s * fps, order, b - a)
        if win <= order + 1:
            continue
        rows = order_idx[a:b]
        out[rows] = savgol_filter(
            values[rows], win, order, deriv=1, delta=1.0 / fps, axis=0, mode="interp"
        )
    return out
