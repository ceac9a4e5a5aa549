"""Association of per-frame instances into bubbles: across views and through time.

Instances come from a segmentation backend as per-camera label stacks
(frames × H × W, −1 background, 0..n−1 instance index within the frame).

1. **Across views, per frame.** The rule of the method: the same 3D bubble has a
   similar image height in both views. With calibrated (undistorted) cameras this
   is made exact by the epipolar constraint: the top, bottom and centroid of a
   bubble's silhouette in one view lie near the epipolar lines of the other view's.
   The cost of a pair is the mean symmetric epipolar distance of those three points
   (without cameras, the mean difference of their image rows); pairs are chosen by
   the Hungarian algorithm and gated.
2. **Nucleation region.** A paired instance whose silhouette bottom triangulates to
   within ``nucleation_height`` metres of the heated plate (y = 0) is attached to the
   plate: it belongs to bubble 0, the nucleation region.
3. **Through time, per view.** Free instances are tracked frame to frame: each
   track's mask is shifted by its last displacement (constant velocity) and matched
   to the next frame's instances by mask IoU (Hungarian). An instance covering two
   or more tracks' predicted masks is a *merge*; two or more instances covering one
   track's is a *split*; both end the old tracks and start new ones, and are
   recorded as events. A track starting on the nucleation region is a *detach*.
4. **Tracks into bubbles.** Two tracks of different views are linked when they
   were paired in enough of their common frames; links are made strongest first,
   never joining two tracks of one view that coexist in time. Each linked group is
   one bubble; ids 1, 2, … in order of first appearance.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import ndimage as ndi
from scipy.optimize import linear_sum_assignment

from surfphase.cameras import Camera, triangulate

#: Parameters of :func:`associate` (config.yaml ``masks.associate``).
ASSOCIATE_DEFAULTS: dict = {
    # Gate of the cross-view pair cost, fraction of the image height.
    "view_gate_frac": 0.04,
    # An attached bubble's silhouette bottom is within this height of the plate, metres.
    "nucleation_height": 2.5e-4,
    # Without cameras: attached when the bottom is within this many rows (fraction of
    # the height) of the lowest silhouette bottom seen in the session.
    "nucleation_margin_frac": 0.02,
    # Frame-to-frame: minimum IoU of a track's predicted mask with the next instance.
    "track_iou_min": 0.2,
    # Merge/split: an overlap counts when it covers this fraction of the smaller mask.
    "event_overlap_frac": 0.25,
    # Cross-view link: paired in at least this fraction of the common frames.
    "link_frac": 0.3,
}

INSTANCE_COLUMNS = [
    "frame", "camera", "local", "area", "cx", "cy", "x0", "y0", "x1", "y1", "score",
    "top_u", "top_v", "bot_u", "bot_v",
]  # fmt: skip


def instance_table(labels: np.ndarray, scores: Sequence[np.ndarray], camera: str) -> pd.DataFrame:
    """Per-instance geometry of a label stack.

    Args:
        labels: (T, H, W) int, −1 background, 0..n_t−1 instance index per frame.
        scores: per frame, (n_t,) backend confidence of each instance.
        camera: camera name for the table.

    Returns:
        One row per instance: ``frame, camera, local`` (index in its frame), ``area``
        (pixels), centroid ``cx, cy``, inclusive box ``x0, y0, x1, y1``, ``score`` and
        the silhouette's topmost and bottommost points (``top_u, top_v``,
        ``bot_u, bot_v``: mean column of the extreme row), all in pixels.
    """
    rows = []
    for t in range(labels.shape[0]):
        lab = np.asarray(labels[t])
        n = int(lab.max()) + 1
        if n <= 0:
            continue
        for i, sl in enumerate(ndi.find_objects(lab + 1, max_label=n)):
            if sl is None:
                continue
            m = lab[sl] == i
            ys, xs = np.nonzero(m)
            ys = ys + sl[0].start
            xs = xs + sl[1].start
            top, bot = ys.min(), ys.max()
            sc = scores[t][i] if len(scores[t]) > i else np.nan
            rows.append((t, camera, i, ys.size, xs.mean(), ys.mean(), xs.min(), top, xs.max(),
                         bot, float(sc), xs[ys == top].mean(), float(top),
                         xs[ys == bot].mean(), float(bot)))
    return pd.DataFrame(rows, columns=INSTANCE_COLUMNS)


def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """(3, 3) F with ``x_b^T F x_a = 0`` for undistorted pixels of ``cam_a``/``cam_b``."""
    R = cam_b.R @ cam_a.R.T
    t = cam_b.t - R @ cam_a.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    return np.linalg.inv(cam_b.K).T @ E @ np.linalg.inv(cam_a.K)


def symmetric_epipolar_distance(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Mean distance (pixels) of ``xb`` to the epipolar line of ``xa`` and vice versa.

    ``xa`` (N, 2), ``xb`` (M, 2) → (N, M).
    """
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    la = ha @ F.T  # lines in b: F x_a
    lb = hb @ F  # lines in a: F^T x_b
    num = np.abs(hb @ la.T).T  # (N, M) = |x_b · F x_a|
    da = num / np.hypot(la[:, 0], la[:, 1])[:, None]
    db = num / np.hypot(lb[:, 0], lb[:, 1])[None, :]
    return 0.5 * (da + db)


def pair_cost(inst_a: pd.DataFrame, inst_b: pd.DataFrame, cams: tuple[Camera, Camera] | None
              ) -> np.ndarray:
    """(N, M) cross-view cost in pixels between instances of one frame in views a and b."""
    feats = [("top_u", "top_v"), ("bot_u", "bot_v"), ("cx", "cy")]
    cost = np.zeros((len(inst_a), len(inst_b)))
    if cams is not None:
        F = fundamental_matrix(*cams)
        for fu, fv in feats:
            cost += symmetric_epipolar_distance(
                F, inst_a[[fu, fv]].to_numpy(float), inst_b[[fu, fv]].to_numpy(float))
    else:
        for _, fv in feats:
            cost += np.abs(inst_a[fv].to_numpy(float)[:, None] - inst_b[fv].to_numpy(float)[None])
    return cost / len(feats)


def pair_views(inst: pd.DataFrame, cam_a: str, cam_b: str, height: int,
               cams: tuple[Camera, Camera] | None, params: Mapping) -> pd.DataFrame:
    """Per frame, Hungarian pairs of instances of ``cam_a`` and ``cam_b``.

    Returns a table ``frame, local_a, local_b, cost`` (cost in pixels).
    """
    gate = params["view_gate_frac"] * height
    out = []
    ga = dict(tuple(inst[inst.camera == cam_a].groupby("frame")))
    gb = dict(tuple(inst[inst.camera == cam_b].groupby("frame")))
    for t in sorted(set(ga) & set(gb)):
        a, b = ga[t], gb[t]
        c = pair_cost(a, b, cams)
        rows, cols = linear_sum_assignment(np.where(c <= gate, c, 1e6))
        for r, k in zip(rows, cols, strict=True):
            if c[r, k] <= gate:
                out.append((t, int(a.local.iloc[r]), int(b.local.iloc[k]), float(c[r, k])))
    return pd.DataFrame(out, columns=["frame", "local_a", "local_b", "cost"])


@dataclass
class Tracks:
    """Per-view tracks: ``track`` id for each (frame, local) and recorded events."""

    track_of: dict[tuple[int, int], int] = field(default_factory=dict)
    events: list[tuple[int, str, list[int], list[int]]] = field(default_factory=list)
    n: int = 0

    def new(self) -> int:
        self.n += 1
        return self.n - 1


def _shifted_overlap(prev: np.ndarray, prev_ids: Sequence[int], shifts: Sequence[np.ndarray],
                     cur: np.ndarray, n_cur: int) -> np.ndarray:
    """(P, n_cur) pixel counts of previous masks, shifted, falling on current instances."""
    h, w = cur.shape
    out = np.zeros((len(prev_ids), n_cur), np.int64)
    for r, (i, d) in enumerate(zip(prev_ids, shifts, strict=True)):
        ys, xs = np.nonzero(prev == i)
        ys = np.round(ys + d[1]).astype(int)
        xs = np.round(xs + d[0]).astype(int)
        ok = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
        hit = cur[ys[ok], xs[ok]]
        hit = hit[hit >= 0]
        out[r] = np.bincount(hit, minlength=n_cur)[:n_cur]
    return out


def track_view(labels: np.ndarray, inst: pd.DataFrame, attached: set[tuple[int, int]],
               params: Mapping) -> Tracks:
    """Track the free (non-attached) instances of one view through time.

    Args:
        labels: (T, H, W) label stack of the view (−1 background).
        inst: this view's rows of :func:`instance_table`.
        attached: ``(frame, local)`` of instances in the nucleation region.

    Returns:
        :class:`Tracks`; events are ``(frame, kind, parent tracks, child tracks)``
        with kind ``merge``, ``split`` or ``detach`` (parent ``-1`` = bubble 0).
    """
    tr = Tracks()
    by_frame = {t: g for t, g in inst.groupby("frame")}
    last_pos: dict[int, np.ndarray] = {}
    vel: dict[int, np.ndarray] = {}
    frac = params["event_overlap_frac"]
    prev_frame_tracks: list[tuple[int, int]] = []
    for t in range(labels.shape[0]):
        cur_rows = by_frame.get(t)
        cur = np.asarray(labels[t])
        n_cur = int(cur.max()) + 1
        free = [] if cur_rows is None else [
            int(i) for i in cur_rows.local if (t, int(i)) not in attached]
        cur_area = np.bincount(cur[cur >= 0].ravel(), minlength=max(n_cur, 1))
        cent = {} if cur_rows is None else {
            int(r.local): np.array([r.cx, r.cy]) for r in cur_rows.itertuples()}
        prev_tracks = prev_frame_tracks  # (local in t − 1, track)
        assigned: dict[int, int] = {}
        if prev_tracks and free:
            prev = np.asarray(labels[t - 1])
            shifts = [vel.get(tid, np.zeros(2)) for _, tid in prev_tracks]
            ov = _shifted_overlap(prev, [p for p, _ in prev_tracks], shifts, cur, n_cur)
            prev_area = np.array([(prev == p).sum() for p, _ in prev_tracks])
            ov = ov[:, free]
            ca = cur_area[free]
            iou = ov / np.maximum(prev_area[:, None] + ca[None] - ov, 1)
            small = np.minimum(prev_area[:, None], ca[None])
            cover = ov / np.maximum(small, 1) >= frac
            # Merges: a current instance covering ≥ 2 tracks; splits: a track ≥ 2 instances.
            merged_cols = {j for j in range(len(free)) if cover[:, j].sum() >= 2}
            split_rows = {i for i in range(len(prev_tracks)) if cover[i].sum() >= 2}
            for j in merged_cols:
                parents = [prev_tracks[i][1] for i in np.flatnonzero(cover[:, j])]
                child = tr.new()
                assigned[free[j]] = child
                tr.events.append((t, "merge", parents, [child]))
            for i in split_rows:
                kids = [free[j] for j in np.flatnonzero(cover[i]) if free[j] not in assigned]
                if len(kids) < 2:
                    continue
                children = []
                for k in kids:
                    assigned[k] = tr.new()
                    children.append(assigned[k])
                tr.events.append((t, "split", [prev_tracks[i][1]], children))
            rows_ok = [i for i in range(len(prev_tracks)) if i not in split_rows
                       and not any(cover[i, j] for j in merged_cols)]
            cols_ok = [j for j in range(len(free)) if free[j] not in assigned]
            if rows_ok and cols_ok:
                sub = iou[np.ix_(rows_ok, cols_ok)]
                rr, cc = linear_sum_assignment(-sub)
                for r, c in zip(rr, cc, strict=True):
                    if sub[r, c] >= params["track_iou_min"]:
                        assigned[free[cols_ok[c]]] = prev_tracks[rows_ok[r]][1]
        prev_attached = [loc for (f, loc) in attached if f == t - 1]
        for loc in free:
            if loc in assigned:
                continue
            tid = tr.new()
            assigned[loc] = tid
            if prev_attached and _touches(np.asarray(labels[t - 1]), prev_attached, cur == loc):
                tr.events.append((t, "detach", [-1], [tid]))
        prev_frame_tracks = sorted(assigned.items())
        for loc, tid in assigned.items():
            tr.track_of[(t, loc)] = tid
            c = cent[loc]
            vel[tid] = c - last_pos[tid] if tid in last_pos else np.zeros(2)
            last_pos[tid] = c
    return tr


def _touches(prev: np.ndarray, prev_locals: Sequence[int], mask: np.ndarray) -> bool:
    """Whether ``mask`` overlaps (or is 1 px from) any of the previous instances."""
    grown = ndi.binary_dilation(mask, iterations=1)
    return bool(np.isin(prev[grown], list(prev_locals)).any())


def _attached_pairs(inst: pd.DataFrame, pairs: pd.DataFrame, cam_a: str, cam_b: str,
                    cams: tuple[Camera, Camera] | None, height: int, params: Mapping
                    ) -> set[tuple[str, int, int]]:
    """(camera, frame, local) of instances attached to the plate (nucleation region)."""
    out: set[tuple[str, int, int]] = set()
    ia = inst[inst.camera == cam_a].set_index(["frame", "local"])
    ib = inst[inst.camera == cam_b].set_index(["frame", "local"])
    if cams is not None:
        if len(pairs) == 0:
            return out
        ua = ia.loc[list(zip(pairs.frame, pairs.local_a, strict=True)), ["bot_u", "bot_v"]]
        ub = ib.loc[list(zip(pairs.frame, pairs.local_b, strict=True)), ["bot_u", "bot_v"]]
        X = triangulate(list(cams), [ua.to_numpy(float), ub.to_numpy(float)])
        low = X[:, 1] < params["nucleation_height"]
        for (t, la, lb), lw in zip(pairs[["frame", "local_a", "local_b"]].itertuples(index=False),
                                   low, strict=True):
            if lw:
                out.add((cam_a, int(t), int(la)))
                out.add((cam_b, int(t), int(lb)))
        return out
    margin = params["nucleation_margin_frac"] * height
    for cam in (cam_a, cam_b):
        rows = inst[inst.camera == cam]
        if len(rows) == 0:
            continue
        lowest = rows.bot_v.max()
        for r in rows.itertuples():
            if r.bot_v >= lowest - margin:
                out.add((cam, int(r.frame), int(r.local)))
    return out


def associate(
    labels: Mapping[str, np.ndarray],
    scores: Mapping[str, Sequence[np.ndarray]],
    cameras: Mapping[str, Camera] | None,
    params: Mapping | None = None,
) -> tuple[dict[str, np.ndarray], pd.DataFrame, pd.DataFrame]:
    """Give every instance a bubble id, consistent across views and time.

    Args:
        labels: ``{camera: (T, H, W) int}`` instance labels per frame (−1 background).
            Views are taken in the mapping's order; the first two are associated
            (further views are tracked on their own).
        scores: ``{camera: [ (n_t,) confidence per frame ]}``.
        cameras: undistorted cameras of those frames (same pixel grid), or ``None``.
        params: overrides of :data:`ASSOCIATE_DEFAULTS`.

    Returns:
        bubble_labels: ``{camera: (T, H, W) int32}``, −1 background, 0 nucleation
        region, ≥ 1 bubble ids;
        instances: table ``frame, camera, bubble, area, cx, cy, x0, y0, x1, y1, score``;
        events: table ``frame, camera, event, parents, children`` (bubble ids joined
        by ``+``; parent 0 of a ``detach`` is the nucleation region).
    """
    p = {**ASSOCIATE_DEFAULTS, **(params or {})}
    names = list(labels)
    if not names:
        raise ValueError("no camera to associate")
    height = next(iter(labels.values())).shape[1]
    inst = pd.concat([instance_table(labels[c], scores[c], c) for c in names],
                     ignore_index=True)
    attached: set[tuple[str, int, int]] = set()
    pairs = pd.DataFrame(columns=["frame", "local_a", "local_b", "cost"])
    cam_pair = None
    if len(names) >= 2:
        a, b = names[:2]
        if cameras is not None and a in cameras and b in cameras:
            cam_pair = (cameras[a], cameras[b])
        pairs = pair_views(inst, a, b, height, cam_pair, p)
        attached = _attached_pairs(inst, pairs, a, b, cam_pair, height, p)
    tracks = {}
    for c in names:
        att = {(t, loc) for (cc, t, loc) in attached if cc == c}
        tracks[c] = track_view(labels[c], inst[inst.camera == c], att, p)
    # Global track keys: (camera, track).
    parent = {}

    def find(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    frames_of: dict[tuple[str, int], set[int]] = {}
    for c in names:
        for (t, _loc), tid in tracks[c].track_of.items():
            frames_of.setdefault((c, tid), set()).add(t)
    for k in frames_of:
        parent[k] = k
    if len(names) >= 2 and len(pairs):
        a, b = names[:2]
        votes: dict[tuple, int] = {}
        for t, la, lb in pairs[["frame", "local_a", "local_b"]].itertuples(index=False):
            ka = tracks[a].track_of.get((int(t), int(la)))
            kb = tracks[b].track_of.get((int(t), int(lb)))
            if ka is None or kb is None:
                continue
            key = ((a, ka), (b, kb))
            votes[key] = votes.get(key, 0) + 1
        members: dict = {k: [k] for k in frames_of}
        for (ka, kb), v in sorted(votes.items(), key=lambda kv: -kv[1]):
            common = len(frames_of[ka] & frames_of[kb])
            if v < max(1, p["link_frac"] * common):
                continue
            ra, rb = find(ka), find(kb)
            if ra == rb or _conflict(members[ra], members[rb], frames_of):
                continue
            parent[rb] = ra
            members[ra] = members[ra] + members.pop(rb)
    # Bubble ids in order of first appearance (then camera order, then centroid x).
    first: dict = {}
    for c in names:
        rows = inst[inst.camera == c]
        for r in rows.itertuples():
            tid = tracks[c].track_of.get((int(r.frame), int(r.local)))
            if tid is None:
                continue
            g = find((c, tid))
            key = (int(r.frame), names.index(c), float(r.cx))
            if g not in first or key < first[g]:
                first[g] = key
    bubble_of_group = {g: i + 1 for i, g in enumerate(sorted(first, key=first.get))}
    out_labels: dict[str, np.ndarray] = {}
    bubble_col = np.full(len(inst), -1, np.int64)
    for c in names:
        lab = np.asarray(labels[c])
        out = np.full(lab.shape, -1, np.int32)
        sel = np.flatnonzero(inst.camera.to_numpy() == c)
        for row in sel:
            t, loc = int(inst.frame.iat[row]), int(inst.local.iat[row])
            if (c, t, loc) in attached:
                bid = 0
            else:
                bid = bubble_of_group[find((c, tracks[c].track_of[(t, loc)]))]
            bubble_col[row] = bid
            out[t][lab[t] == loc] = bid
        out_labels[c] = out
    inst = inst.assign(bubble=bubble_col)
    instances = inst[["frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1",
                      "score"]].sort_values(["frame", "camera", "bubble"], kind="stable")
    ev_rows = []
    for c in names:
        for t, kind, par, kids in tracks[c].events:
            pb = [0 if q < 0 else bubble_of_group[find((c, q))] for q in par]
            kb = [bubble_of_group[find((c, q))] for q in kids]
            ev_rows.append((t, c, kind, "+".join(map(str, pb)), "+".join(map(str, kb))))
    events = pd.DataFrame(ev_rows, columns=["frame", "camera", "event", "parents", "children"])
    return out_labels, instances.reset_index(drop=True), events


def _conflict(ga: list, gb: list, frames_of: Mapping) -> bool:
    """Whether joining groups ``ga`` and ``gb`` puts two coexisting tracks of one view together."""
    for ka in ga:
        for kb in gb:
            if ka[0] == kb[0] and frames_of[ka] & frames_of[kb]:
                return True
    return False
