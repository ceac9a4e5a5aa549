"""Dating a bubble's detachment from the rise of its silhouette bottom (step 2b of
:mod:`surfphase.masks.associate`).

A silhouette is first called attached when its bottom triangulates to within
``nucleation_height`` of the plate. That height must exceed the bottom's
triangulation error (about a pixel's footprint), so a bubble that rises slowly in
frames (a high frame rate, a slow bubble) stays "attached" for frames after it has
left the plate: at 10,000 fps and 0.1 m/s it rises 10 µm a frame, and 0.1 mm takes
ten frames.

So each new track that the tracker saw leave the nucleation region is followed back
through the attached instances it continues (in the same view, each overlapping the
next frame's silhouette), and forward over its first frames (``detach_fit_s``
seconds, at least ``detach_fit_min_frames``). The bottom heights of that chain are
fitted by a hinge, resting then rising at a steady speed
(:func:`left_plate_at`): its knee dates the moment the bubble left. The chain's
attached instances after that moment are the bubble already free, and so are their
other views' partners. Heights further below the plate than ``nucleation_height``
are left out of the fit: such a bottom is the edge of the plate's image, which hides
the bubble's, not the bubble's own. The hinge's knee is as good as the heights
around it, within about a frame.

A bubble does not land back on the plate. Where the track's last sighting is continued,
in the next frames, by attached instances (each overlapping the one before), each of
them is weighed against the hinge: a bottom nearer its rising line than its resting
level is the bubble still rising, too slowly yet for the height rule, and is freed
(the track carries on); one nearer the resting level means the bubble never left (the
heights that freed it were the triangulation's error: a small bubble growing on the
plate, its bottom hidden by the plate's image, the two views' lowest points then not
one point), and the track's sightings are given back to the nucleation region.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy import ndimage as ndi

from surfphase.masks.tracking import Tracks

#: An instance: (camera, frame, local index in its frame).
Key = tuple[str, int, int]


def fit_frames(fps: float | None, params: Mapping) -> int:
    """Frames of a new track's start the detachment line is fitted on:
    ``detach_fit_s`` × fps, at least ``detach_fit_min_frames`` (that many without fps)."""
    least = int(params["detach_fit_min_frames"])
    if not fps:
        return least
    return max(least, math.ceil(float(params["detach_fit_s"]) * float(fps) - 1e-9))


def hinge_fit(
    frames: np.ndarray, heights: np.ndarray, step: float = 0.05
) -> tuple[float, float, float] | None:
    """The hinge ``h = h0 + v · max(0, t − t0)`` (resting at the level ``h0`` the plate
    contact reads at, then rising at a steady ``v`` > 0) fitted to ``heights`` (K,)
    metres at ``frames`` (K,) by least squares: ``(t0, h0, v)``, ``t0`` in (fractional)
    frames, ``h0`` in m, ``v`` in m per frame.

    ``t0`` is searched every ``step`` frames from the first frame to the third-last,
    so at least two heights lie on the rising part; ``None`` with fewer than 3
    heights or no rise.
    """
    t = np.asarray(frames, np.float64)
    h = np.asarray(heights, np.float64)
    if len(t) < 3:
        return None
    ts = np.sort(t)
    grid = np.arange(ts[0], ts[-3] + 1e-9, step)
    x = np.maximum(0.0, t[None, :] - grid[:, None])  # (G, K)
    # Least squares of h on [1, x] for every t0 at once: v = cov(x, h) / var(x).
    xc = x - x.mean(1, keepdims=True)
    hc = h - h.mean()
    sxx, sxh = (xc * xc).sum(1), xc @ hc
    ok = (sxx > 0) & (sxh > 0)
    gain = np.where(ok, sxh**2 / np.where(ok, sxx, 1.0), -np.inf)
    k = int(np.argmax(gain))
    if not np.isfinite(gain[k]):
        return None
    v = float(sxh[k] / sxx[k])
    return float(grid[k]), float(h.mean() - v * x[k].mean()), v


def left_plate_at(frames: np.ndarray, heights: np.ndarray, step: float = 0.05) -> float | None:
    """The frame (fractional) a bubble's bottom leaves the plate: the knee ``t0`` of
    :func:`hinge_fit`, or ``None``."""
    fit = hinge_fit(frames, heights, step)
    return None if fit is None else fit[0]


def detachments(
    labels: Mapping[str, np.ndarray],
    tracks: Mapping[str, Tracks],
    pair_heights: Mapping[Key, float],
    partner: Mapping[Key, Key],
    attached: set[Key],
    fps: float | None,
    params: Mapping,
) -> tuple[set[Key], set[Key]]:
    """The attached instances that belong to a detached bubble already free, and the
    free ones of tracks that never left the plate.

    Args:
        labels: ``{camera: (T, H, W) int}`` instance labels (−1 background).
        tracks: ``{camera: Tracks}`` of the views, tracked with ``attached``.
        pair_heights: ``{instance: bottom height (m)}`` of every instance paired across
            the views (the triangulated silhouette bottom, lab y).
        partner: ``{instance: its pair in the other view}``.
        attached: the instances called attached by height.
        fps: frames per second, or ``None``.
        params: :data:`surfphase.masks.params.ASSOCIATE_DEFAULTS` keys
            ``detach_fit_s``, ``detach_fit_min_frames``, ``nucleation_height``.

    Returns:
        ``(freed, landed)``: the instances (of both views) to free, a subset of
        ``attached``; those to attach again, none of them in ``attached``.
    """
    n_fit = fit_frames(fps, params)
    low = -float(params["nucleation_height"])
    freed: set[Key] = set()
    landed: set[Key] = set()

    def with_partners(keys: list[Key]) -> set[Key]:
        return set(keys) | {o for k in keys if (o := partner.get(k)) is not None}

    for cam, tr in tracks.items():
        sightings: dict[int, list[tuple[int, int]]] = {}
        for (t, loc), tid in tr.track_of.items():
            sightings.setdefault(tid, []).append((t, loc))
        att_at: dict[int, list[int]] = {}
        for c, t, loc in attached:
            if c == cam:
                att_at.setdefault(t, []).append(loc)
        lab = labels[cam]
        for _t, kind, _par, kids in tr.events:
            if kind != "detach" or not kids or kids[0] not in sightings:
                continue
            track = sorted(sightings[kids[0]])
            seen = track[:n_fit]
            chain = _walk_back(lab, att_at, seen[0]) + _fill_gaps(lab, att_at, seen)
            # A bottom further below the plate than its triangulation error is not the
            # bubble's (the plate's image hides it): it does not date anything.
            pts = [
                (t, h)
                for t, loc in chain + seen
                if (h := pair_heights.get((cam, t, loc), -np.inf)) >= low
            ]
            fit = hinge_fit(np.array([q[0] for q in pts]), np.array([q[1] for q in pts]))
            if fit is None:
                continue
            t0, h0, v = fit
            after = _follow(lab, att_at, track[-1], range(track[-1][0] + 1, lab.shape[0]))
            rising = []
            for t, loc in after:
                h = pair_heights.get((cam, t, loc))
                if h is None or h < low:  # not paired, or hidden: nothing to weigh it by
                    break
                if h < h0 + 0.5 * v * (t - t0):  # nearer resting than rising: it landed
                    landed |= with_partners([(cam, tt, ll) for tt, ll in track])
                    rising = None
                    break
                rising.append((t, loc))
            if rising is None:
                continue
            freed |= with_partners([(cam, t, loc) for t, loc in chain if t > t0] +
                                   [(cam, t, loc) for t, loc in rising])  # fmt: skip
    return (freed & attached) - landed, landed - attached


def _overlapping(lab: np.ndarray, t: int, locals_: list[int], mask: np.ndarray) -> int | None:
    """The one of ``locals_`` in frame ``t`` overlapping the grown ``mask`` most, if any."""
    if not locals_:
        return None
    grown = ndi.binary_dilation(mask, iterations=1)
    hit = np.asarray(lab[t])[grown]
    counts = [int((hit == loc).sum()) for loc in locals_]
    k = int(np.argmax(counts))
    return locals_[k] if counts[k] > 0 else None


def _follow(
    lab: np.ndarray, att_at: Mapping[int, list[int]], start: tuple[int, int], frames: range
) -> list[tuple[int, int]]:
    """(frame, local) of the attached instances that continue the instance ``start``
    over ``frames`` in order, each overlapping the one before; up to the first frame
    without one."""
    out = []
    mask = np.asarray(lab[start[0]]) == start[1]
    for t in frames:
        loc = _overlapping(lab, t, att_at.get(t, []), mask)
        if loc is None:
            break
        out.append((t, loc))
        mask = np.asarray(lab[t]) == loc
    return out


def _walk_back(
    lab: np.ndarray, att_at: Mapping[int, list[int]], first: tuple[int, int]
) -> list[tuple[int, int]]:
    """(frame, local) of the attached instances before a track's ``first`` sighting
    that continue it back in time (each overlapping the next one)."""
    return _follow(lab, att_at, first, range(first[0] - 1, -1, -1))


def _fill_gaps(
    lab: np.ndarray, att_at: Mapping[int, list[int]], seen: list[tuple[int, int]]
) -> list[tuple[int, int]]:
    """(frame, local) of attached instances in the gaps of a track's first sightings
    ``seen`` that overlap its sighting before the gap."""
    out = []
    for (ta, la), (tb, _lb) in zip(seen[:-1], seen[1:], strict=True):
        out += _follow(lab, att_at, (ta, la), range(ta + 1, tb))
    return out


def pair_keys(pairs: pd.DataFrame, cam_a: str, cam_b: str) -> list[tuple[Key, Key]]:
    """The rows of a :func:`surfphase.masks.associate.pair_views` table as instance keys."""
    return [
        ((cam_a, int(t), int(a)), (cam_b, int(t), int(b)))
        for t, a, b in pairs[["frame", "local_a", "local_b"]].itertuples(index=False)
    ]
