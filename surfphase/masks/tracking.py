"""Tracking of one view's free instances through time (step 3 of
:mod:`surfphase.masks.associate`): constant-velocity mask prediction, IoU matching,
coasting of hidden tracks, and the ``merge`` / ``split`` / ``detach`` events.

A view's instances are the rows of :func:`surfphase.masks.associate.instance_table`
(frame, local index, centroid in pixels) with the label stack they come from
((T, H, W) int, −1 background, 0..n−1 instance index within the frame).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import ndimage as ndi
from scipy.optimize import linear_sum_assignment

#: A track's last sighting: (frame, mask rows, mask columns, centroid (x, y) px,
#: velocity (px/frame)).
Sighting = tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass
class Tracks:
    """Per-view tracks: ``track`` id for each (frame, local) and recorded events."""

    track_of: dict[tuple[int, int], int] = field(default_factory=dict)
    events: list[tuple[int, str, list[int], list[int]]] = field(default_factory=list)
    n: int = 0
    #: Merged track → the track whose instance it continues (the one that covered
    #: the hidden tracks), so a merge the other view refutes can be undone.
    continues: dict[int, int] = field(default_factory=dict)

    def new(self) -> int:
        self.n += 1
        return self.n - 1

    def copy(self) -> Tracks:
        """A copy whose tables can be changed without changing these."""
        return Tracks(dict(self.track_of), list(self.events), self.n, dict(self.continues))


def track_view(
    labels: np.ndarray, inst: pd.DataFrame, attached: set[tuple[int, int]], params: Mapping
) -> Tracks:
    """Track the free (non-attached) instances of one view through time.

    Every track predicts its mask in the next frame by shifting its last mask by its
    last displacement per frame (times the frames since it was last seen). Current
    instances are matched to the predictions by IoU (Hungarian, ``track_iou_min``).
    A track left unmatched *coasts* for up to ``coast_frames`` frames: a bubble
    hidden behind another in this view (their silhouettes fused into one instance)
    takes its id back when it reappears. Events:

    * ``merge`` — a track that stopped while its predicted mask lay under another
      track's instance and never came back within ``coast_frames``: from the frame
      it stopped, the covering instance is a new track (the merged bubble);
    * ``split`` — a new track born inside the previous mask of a track;
    * ``detach`` — a new track born touching the nucleation region (parent −1).

    Args:
        labels: (T, H, W) label stack of the view (−1 background).
        inst: this view's rows of :func:`surfphase.masks.associate.instance_table`.
        attached: ``(frame, local)`` of instances in the nucleation region.

    Returns:
        :class:`Tracks`; events are ``(frame, kind, parent tracks, child tracks)``.
    """
    tr = Tracks()
    by_frame = {t: g for t, g in inst.groupby("frame")}
    frac = params["event_overlap_frac"]
    coast = int(params["coast_frames"])
    last: dict[int, Sighting] = {}
    hidden_by: dict[int, tuple[int, int]] = {}  # track → (frame it vanished, covering track)
    for t in range(labels.shape[0]):
        cur = np.asarray(labels[t])
        rows = by_frame.get(t)
        free = [] if rows is None else [int(i) for i in rows.local if (t, int(i)) not in attached]
        n_cur = int(cur.max()) + 1
        cur_area = np.bincount(cur[cur >= 0].ravel(), minlength=max(n_cur, 1))
        cent = (
            {}
            if rows is None
            else {int(r.local): np.array([r.cx, r.cy]) for r in rows.itertuples()}
        )
        cands = [k for k, v in last.items() if t - v[0] <= coast]
        ov, pred_area = _predicted_overlaps(last, cands, cur, free, t)
        assigned = _match_tracks(last, cands, free, ov, pred_area, cur_area, t, params)
        prev = (
            np.asarray(labels[t - 1]) if t > 0 else None,
            [loc for (f, loc) in attached if f == t - 1],
        )
        _start_tracks(tr, assigned, last, cands, free, ov, cur, cur_area, prev, t, frac)
        _note_hidden(hidden_by, assigned, cands, free, ov, pred_area, cur_area, t, frac)
        _settle_merges(tr, hidden_by, assigned, last, t, coast, t == labels.shape[0] - 1)
        _remember(tr, last, assigned, cur, cent, t)
    tr.events.sort(key=lambda e: e[0])
    return tr


def _predicted_overlaps(
    last: Mapping[int, Sighting], cands: Sequence[int], cur: np.ndarray, free: Sequence[int],
    t: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Each candidate track's mask shifted to frame ``t`` against the free instances
    of ``cur``: ((K, N) overlapping pixels, (K,) predicted area in the image, ≥ 1)."""
    h, w = cur.shape
    n_cur = int(cur.max()) + 1
    ov = np.zeros((len(cands), len(free)), np.int64)
    pred_area = np.zeros(len(cands), np.int64)
    for r, k in enumerate(cands):
        f0, ys, xs, _, vel = last[k]
        d = vel * (t - f0)
        yy = np.round(ys + d[1]).astype(int)
        xx = np.round(xs + d[0]).astype(int)
        ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        pred_area[r] = max(int(ok.sum()), 1)
        hit = cur[yy[ok], xx[ok]]
        cnt = np.bincount(hit[hit >= 0], minlength=max(n_cur, 1))
        ov[r] = cnt[free] if free else []
    return ov, pred_area


def _match_tracks(
    last: Mapping[int, Sighting], cands: Sequence[int], free: Sequence[int], ov: np.ndarray,
    pred_area: np.ndarray, cur_area: np.ndarray, t: int, params: Mapping,
) -> dict[int, int]:  # fmt: skip
    """``{local: track}`` of the free instances matched to a candidate track by IoU
    (Hungarian; at least ``track_iou_min``)."""
    assigned: dict[int, int] = {}
    if cands and free:
        ca = cur_area[free]
        iou = ov / np.maximum(pred_area[:, None] + ca[None] - ov, 1)
        # A track seen in the previous frame is a surer match than one coasting.
        gap = np.array([t - last[k][0] for k in cands], np.float64)
        rr, cc = linear_sum_assignment(-iou * 0.5 ** (gap[:, None] - 1))
        for r, c in zip(rr, cc, strict=True):
            if iou[r, c] >= params["track_iou_min"]:
                assigned[free[c]] = cands[r]
    return assigned


def _start_tracks(
    tr: Tracks, assigned: dict[int, int], last: Mapping[int, Sighting], cands: Sequence[int],
    free: Sequence[int], ov: np.ndarray, cur: np.ndarray, cur_area: np.ndarray,
    prev: tuple[np.ndarray | None, list[int]], t: int, frac: float,
) -> None:  # fmt: skip
    """A new track for each free instance left unmatched (into ``assigned``); born
    inside a track's previous mask it is a split, touching the previous frame's
    attached instances (``prev``: labels, their locals) a detach."""
    prev_lab, prev_attached = prev
    for c, loc in enumerate(free):
        if loc in assigned:
            continue
        tid = tr.new()
        assigned[loc] = tid
        mask = cur == loc
        # Born inside a track's previous mask: a split; on the plate: a detach.
        if cands:
            cover = ov[:, c] / max(int(cur_area[loc]), 1)
            r = int(np.argmax(cover))
            if cover[r] >= frac and last[cands[r]][0] == t - 1:
                tr.events.append((t, "split", [cands[r]], [tid]))
                continue
        if prev_attached and _touches(prev_lab, prev_attached, mask):
            tr.events.append((t, "detach", [-1], [tid]))


def _note_hidden(
    hidden_by: dict[int, tuple[int, int]], assigned: Mapping[int, int], cands: Sequence[int],
    free: Sequence[int], ov: np.ndarray, pred_area: np.ndarray, cur_area: np.ndarray, t: int,
    frac: float,
) -> None:  # fmt: skip
    """Tracks lost at frame ``t`` whose predicted mask lies under an instance: hidden by
    that instance's track; tracks seen again are no longer hidden (an occlusion)."""
    by_track = {tid: loc for loc, tid in assigned.items()}
    for r, k in enumerate(cands):
        if k in by_track or k in hidden_by or not free:
            continue
        c = int(np.argmax(ov[r]))
        if ov[r, c] >= frac * min(pred_area[r], cur_area[free[c]]):
            hidden_by[k] = (t, assigned[free[c]])
    for k in list(hidden_by):
        if k in by_track:
            del hidden_by[k]  # it came back: an occlusion, not a merge


def _settle_merges(
    tr: Tracks, hidden_by: dict[int, tuple[int, int]], assigned: dict[int, int],
    last: dict[int, Sighting], t: int, coast: int, final: bool,
) -> None:  # fmt: skip
    """Make a merge of each track hidden for ``coast`` frames (or still hidden at the
    ``final`` frame), earliest first."""
    while True:
        due = [k for k, (ff, _) in hidden_by.items() if t - ff >= coast or final]
        if not due:
            break
        k = min(due, key=lambda q: (hidden_by[q][0], q))
        _merge(tr, hidden_by, assigned, last, k)


def _merge(
    tr: Tracks, hidden_by: dict[int, tuple[int, int]], assigned: dict[int, int],
    last: dict[int, Sighting], k: int,
) -> None:  # fmt: skip
    """Hidden track ``k`` merged into the track that covered it: from the frame it
    vanished, that track's instances, sightings and events belong to a new track."""
    f, other = hidden_by.pop(k)
    merged = tr.new()
    tr.continues[merged] = other
    for key, tid in tr.track_of.items():
        if tid == other and key[0] >= f:
            tr.track_of[key] = merged
    for loc, tid in assigned.items():
        if tid == other:
            assigned[loc] = merged
    if other in last:
        last[merged] = last.pop(other)
    for kk, (ff, oo) in list(hidden_by.items()):
        if oo == other and ff >= f:
            hidden_by[kk] = (ff, merged)
    # The merged blob may itself have hidden later behind another track.
    if other in hidden_by and hidden_by[other][0] >= f:
        hidden_by[merged] = hidden_by.pop(other)
    tr.events = [
        (
            ef,
            kind,
            [merged if (q == other and ef >= f) else q for q in par],
            [merged if (q == other and ef >= f) else q for q in kids],
        )
        for ef, kind, par, kids in tr.events
    ]
    tr.events.append((f, "merge", [k, other], [merged]))


def _remember(
    tr: Tracks, last: dict[int, Sighting], assigned: Mapping[int, int], cur: np.ndarray,
    cent: Mapping[int, np.ndarray], t: int,
) -> None:  # fmt: skip
    """Record frame ``t``'s instances in their tracks, and each track's sighting
    (mask, centroid, velocity in pixels per frame)."""
    for loc, tid in assigned.items():
        tr.track_of[(t, loc)] = tid
        ys, xs = np.nonzero(cur == loc)
        c = cent[loc]
        vel = np.zeros(2)
        if tid in last and last[tid][0] < t:
            vel = (c - last[tid][3]) / (t - last[tid][0])
        last[tid] = (t, ys, xs, c, vel)


def _touches(prev: np.ndarray, prev_locals: Sequence[int], mask: np.ndarray) -> bool:
    """Whether ``mask`` overlaps (or is 1 px from) any of the previous instances."""
    grown = ndi.binary_dilation(mask, iterations=1)
    return bool(np.isin(prev[grown], list(prev_locals)).any())
