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
   to the next frame's instances by mask IoU (Hungarian). A track hidden behind
   another (silhouettes fused in this view) coasts a few frames and takes its id
   back when it reappears; one that never does has *merged* into the track that
   covered it, which carries on. A new track born inside a track's previous mask is
   a *split*; one born on the nucleation region is a *detach*. Events are recorded.
4. **Merges, one decision for both views.** A merge is an event of the 3D bubbles:
   the merges seen by each view are matched across the views and given one frame,
   a merge one view missed is made there too, one the other view refutes (it still
   sees the bubbles apart) is undone as an occlusion, and a merge is dated back over
   the frame(s) where the young merged bubble still shows as two touching lobes
   (:func:`reconcile_merges`). The merged bubble gets its own id in both views.
5. **Tracks into bubbles.** Two tracks of different views are linked when they
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
from surfphase.masks.params import ASSOCIATE_DEFAULTS


def lobe_frames(merge_lobe_s: float, fps: float | None) -> int:
    """Frames of ``merge_lobe_s`` seconds at ``fps`` (rounded, at least 1; 1 without fps)."""
    if fps is None or not fps > 0:
        return 1
    return max(1, int(round(float(merge_lobe_s) * float(fps))))


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
            rows.append(
                (
                    t,
                    camera,
                    i,
                    ys.size,
                    xs.mean(),
                    ys.mean(),
                    xs.min(),
                    top,
                    xs.max(),
                    bot,
                    float(sc),
                    xs[ys == top].mean(),
                    float(top),
                    xs[ys == bot].mean(),
                    float(bot),
                )
            )
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


def pair_cost(
    inst_a: pd.DataFrame, inst_b: pd.DataFrame, cams: tuple[Camera, Camera] | None
) -> np.ndarray:
    """(N, M) cross-view cost in pixels between instances of one frame in views a and b."""
    feats = [("top_u", "top_v"), ("bot_u", "bot_v"), ("cx", "cy")]
    cost = np.zeros((len(inst_a), len(inst_b)))
    if cams is not None:
        F = fundamental_matrix(*cams)
        for fu, fv in feats:
            cost += symmetric_epipolar_distance(
                F, inst_a[[fu, fv]].to_numpy(float), inst_b[[fu, fv]].to_numpy(float)
            )
    else:
        for _, fv in feats:
            cost += np.abs(inst_a[fv].to_numpy(float)[:, None] - inst_b[fv].to_numpy(float)[None])
    return cost / len(feats)


def pair_views(
    inst: pd.DataFrame,
    cam_a: str,
    cam_b: str,
    height: int,
    cams: tuple[Camera, Camera] | None,
    params: Mapping,
) -> pd.DataFrame:
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
    #: Merged track → the track whose instance it continues (the one that covered
    #: the hidden tracks), so a merge the other view refutes can be undone.
    continues: dict[int, int] = field(default_factory=dict)

    def new(self) -> int:
        self.n += 1
        return self.n - 1


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
        inst: this view's rows of :func:`instance_table`.
        attached: ``(frame, local)`` of instances in the nucleation region.

    Returns:
        :class:`Tracks`; events are ``(frame, kind, parent tracks, child tracks)``.
    """
    tr = Tracks()
    by_frame = {t: g for t, g in inst.groupby("frame")}
    frac = params["event_overlap_frac"]
    coast = int(params["coast_frames"])
    h, w = labels.shape[1:]
    # Per track: last frame seen, last mask pixels (ys, xs), last centroid, velocity.
    last: dict[int, tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
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
        assigned: dict[int, int] = {}
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
        if cands and free:
            ca = cur_area[free]
            iou = ov / np.maximum(pred_area[:, None] + ca[None] - ov, 1)
            # A track seen in the previous frame is a surer match than one coasting.
            gap = np.array([t - last[k][0] for k in cands], np.float64)
            rr, cc = linear_sum_assignment(-iou * 0.5 ** (gap[:, None] - 1))
            for r, c in zip(rr, cc, strict=True):
                if iou[r, c] >= params["track_iou_min"]:
                    assigned[free[c]] = cands[r]
        prev_lab = np.asarray(labels[t - 1]) if t > 0 else None
        prev_attached = [loc for (f, loc) in attached if f == t - 1]
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
        by_track = {tid: loc for loc, tid in assigned.items()}
        # Tracks lost this frame: note which instance covers their predicted mask.
        for r, k in enumerate(cands):
            if k in by_track or k in hidden_by or not free:
                continue
            c = int(np.argmax(ov[r]))
            if ov[r, c] >= frac * min(pred_area[r], cur_area[free[c]]):
                hidden_by[k] = (t, assigned[free[c]])
        for k in list(hidden_by):
            if k in by_track:
                del hidden_by[k]  # it came back: an occlusion, not a merge
        while True:
            # Hidden for good (or still hidden when the video ends), earliest first.
            due = [
                k for k, (ff, _) in hidden_by.items() if t - ff >= coast or t == labels.shape[0] - 1
            ]
            if not due:
                break
            k = min(due, key=lambda q: (hidden_by[q][0], q))
            f, other = hidden_by.pop(k)
            # A merge: from frame f on, the surviving instance is a new bubble.
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
        for loc, tid in assigned.items():
            tr.track_of[(t, loc)] = tid
            ys, xs = np.nonzero(cur == loc)
            c = cent[loc]
            vel = np.zeros(2)
            if tid in last and last[tid][0] < t:
                vel = (c - last[tid][3]) / (t - last[tid][0])
            last[tid] = (t, ys, xs, c, vel)
    tr.events.sort(key=lambda e: e[0])
    return tr


def _track_frames(tr: Tracks) -> dict[int, set[int]]:
    """Frames in which each track of one view has an instance."""
    out: dict[int, set[int]] = {}
    for (t, _loc), k in tr.track_of.items():
        out.setdefault(k, set()).add(t)
    return out


def _merge_groups(tr: Tracks, frames: Mapping[int, set[int]]) -> dict[int, tuple[int, set[int]]]:
    """Merges of one view by merged track: ``{child: (frame, parent tracks)}``.

    A blob that swallowed several tracks in one frame is recorded by
    :func:`track_view` as a chain of merges through intermediate tracks left with
    no frame; they are one merge here, of the parents that have frames.
    """
    groups: dict[int, tuple[int, set[int]]] = {}
    for f, kind, par, kids in tr.events:
        if kind != "merge":
            continue
        for m in kids:
            if m in frames:
                f0, ps = groups.get(m, (f, set()))
                groups[m] = (min(f0, f), ps | set(par))
    return {
        m: (f, {q for q in ps if q in frames and q != m})
        for m, (f, ps) in groups.items()
        if any(q in frames and q != m for q in ps)
    }


def _connected(lab: np.ndarray, locals_: Sequence[int]) -> bool:
    """Whether instances ``locals_`` of one frame lie in one connected foreground region."""
    if len(locals_) <= 1:
        return True
    comp, _ = ndi.label(lab >= 0)
    ids = {int(comp[lab == loc].flat[0]) for loc in locals_}
    return len(ids) == 1


def _relabel(tr: Tracks, tracks_: set[int], child: int, start: int) -> None:
    """From frame ``start`` on, instances and events of ``tracks_`` belong to ``child``."""
    for key, k in tr.track_of.items():
        if key[0] >= start and k in tracks_:
            tr.track_of[key] = child
    tr.events = [
        (
            ef,
            kind,
            [child if (q in tracks_ and ef >= start) else q for q in par],
            [child if (q in tracks_ and ef >= start) else q for q in kids],
        )
        for ef, kind, par, kids in tr.events
    ]
    # A split or merge inside the relabelled tracks (a lobe cut off) is no event.
    tr.events = [e for e in tr.events if set(e[3]) - set(e[2])]


def reconcile_merges(
    tracks: Mapping[str, Tracks],
    labels: Mapping[str, np.ndarray],
    pairs: pd.DataFrame,
    cam_a: str,
    cam_b: str,
    params: Mapping,
    fps: float | None = None,
) -> dict[str, Tracks]:
    """Make each merge one decision for both views, dated at the same frame.

    Per-view tracking sees a merge when one blob has swallowed two tracks; the two
    views see it at different frames (a young merged bubble is two touching lobes
    that the segmenter may still cut apart in one view), or one view misses it (the
    vanished track's prediction fell beside the blob). A merge is an event of the
    3D bubbles, so, taking the merges of both views in order of frame:

    * the same merge in the other view (a merge there whose merged track is paired
      with this one's, or whose parents are paired with two of this one's, within
      ``coast_frames``) is combined with it, at the first frame from which the
      parents touch (one connected foreground region) in both views, between the
      earlier and the later fusion;
    * a merge missed by the other view — the parents are paired there with two
      or more tracks, the merged blob with one of them that carries on while the
      others stop by the next frame — is made there too: that track is cut at the
      merge frame and its continuation is a new track;
    * a merge refuted by the other view — a parent's partner there is still seen
      apart two frames after it — is an occlusion in this view: it is undone, the
      blob keeps the id of the track it continues;
    * the merge is then dated back over up to ``merge_lobe_s`` seconds
      (:func:`lobe_frames` at ``fps``) of frames in which
      the parents' silhouettes touch in every view and are cut apart in at least
      one: the two lobes of a bubble that already merged.

    From the merge frame on, the parents' instances belong to the merged track in
    both views, so the merged bubble never shares an id with a parent.

    Args:
        tracks: ``{camera: Tracks}`` of :func:`track_view` for ``cam_a`` and ``cam_b``.
        labels: ``{camera: (T, H, W) int}`` instance labels (−1 background).
        pairs: :func:`pair_views` table of ``cam_a`` and ``cam_b``.
        params: :data:`ASSOCIATE_DEFAULTS` keys ``coast_frames``, ``merge_lobe_s``.
        fps: the session's frame rate (frames per second), for ``merge_lobe_s``.

    Returns:
        New ``{camera: Tracks}`` for the two views (the inputs are not modified).
    """
    tr = {
        c: Tracks(
            dict(tracks[c].track_of), list(tracks[c].events), tracks[c].n, dict(tracks[c].continues)
        )
        for c in (cam_a, cam_b)
    }
    other_view = {cam_a: cam_b, cam_b: cam_a}
    coast = int(params["coast_frames"])
    lobe = lobe_frames(params["merge_lobe_s"], fps)
    pair_rows = list(pairs[["frame", "local_a", "local_b"]].itertuples(index=False))
    done: set[tuple[str, int]] = set()
    for _ in range(sum(len(t.events) for t in tr.values()) + 1):
        frames = {c: _track_frames(tr[c]) for c in tr}
        groups = {c: _merge_groups(tr[c], frames[c]) for c in tr}
        todo = [(f, c, m, ps) for c in tr for m, (f, ps) in groups[c].items() if (c, m) not in done]
        if not todo:
            break
        f_v, v, m, par_v = min(todo, key=lambda x: (x[0], x[1] != cam_a, x[2]))
        done.add((v, m))
        w = other_view[v]
        votes: dict[tuple[str, int], dict[int, int]] = {}
        for t, la, lb in pair_rows:
            ka = tr[cam_a].track_of.get((int(t), int(la)))
            kb = tr[cam_b].track_of.get((int(t), int(lb)))
            if ka is None or kb is None:
                continue
            va, vb = votes.setdefault((cam_a, ka), {}), votes.setdefault((cam_b, kb), {})
            va[kb] = va.get(kb, 0) + 1
            vb[ka] = vb.get(ka, 0) + 1

        def partner(c: str, k: int, votes=votes) -> int | None:
            vs = votes.get((c, k))
            return None if not vs else max(sorted(vs), key=vs.get)

        par_w = {q for q in (partner(v, p) for p in par_v) if q is not None}
        pm = partner(v, m)
        same = [
            (abs(f2 - f_v), m2)
            for m2, (f2, ps2) in groups[w].items()
            if (w, m2) not in done
            and abs(f2 - f_v) <= coast
            and (m2 == pm or len(ps2 & par_w) >= 2)
        ]
        parents: dict[str, set[int]] = {v: set(par_v)}
        child = {v: m}
        f, f_last = f_v, f_v
        if same:
            m2 = min(same)[1]
            done.add((w, m2))
            f2, ps2 = groups[w][m2]
            parents[w], child[w] = set(ps2), m2
            f, f_last = min(f_v, f2), max(f_v, f2)
        elif pm is not None and pm in par_w and len(par_w) >= 2:
            rest = par_w - {pm}
            if max(max(frames[w][q]) for q in rest) > f_v + 1:
                # The other view still sees the bubbles apart: an occlusion here.
                root = tr[v].continues.get(m)
                while root is not None and root not in frames[v]:
                    root = tr[v].continues.get(root)
                if root is not None:
                    tr[v].events = [e for e in tr[v].events if not (e[1] == "merge" and m in e[3])]
                    _relabel(tr[v], {m}, root, 0)
                continue
            m2 = tr[w].new()
            done.add((w, m2))
            parents[w], child[w] = {pm} | rest, m2

        def joined(g: int, parents=parents, child=child) -> tuple[bool, int]:
            """Whether the bubbles touch in every view at frame g; most instances."""
            most = 0
            for c, ps in parents.items():
                ks = ps | {child[c]}
                locs = [loc for (t, loc), k in tr[c].track_of.items() if t == g and k in ks]
                if not locs or not _connected(np.asarray(labels[c][g]), locs):
                    return False, most
                most = max(most, len(locs))
            return True, most

        # Not merged while a view sees the parents apart (the first fusion was an
        # occlusion in the other view) ...
        while f < f_last and not joined(f)[0]:
            f += 1
        # ... and merged already where they show as two touching lobes.
        for g in range(f - 1, max(f - 1 - lobe, -1), -1):
            ok, most = joined(g)
            if not (ok and most >= 2):
                break
            f = g
        for c, ps in parents.items():
            tr[c].events = [e for e in tr[c].events if not (e[1] == "merge" and child[c] in e[3])]
            _relabel(tr[c], ps, child[c], f)
            tr[c].events.append((f, "merge", sorted(ps), [child[c]]))
            tr[c].events.sort(key=lambda e: e[0])
    return tr


def _touches(prev: np.ndarray, prev_locals: Sequence[int], mask: np.ndarray) -> bool:
    """Whether ``mask`` overlaps (or is 1 px from) any of the previous instances."""
    grown = ndi.binary_dilation(mask, iterations=1)
    return bool(np.isin(prev[grown], list(prev_locals)).any())


def _on_plate(inst: pd.DataFrame, plates: Mapping[str, np.ndarray]) -> set[tuple[str, int, int]]:
    """Instances whose lowest pixel rests on the plate's image (its static region)."""
    out: set[tuple[str, int, int]] = set()
    for r in inst.itertuples():
        plate = plates.get(r.camera)
        if plate is None:
            continue
        v = min(int(r.bot_v) + 1, plate.shape[0] - 1)
        u = min(max(int(round(r.bot_u)), 0), plate.shape[1] - 1)
        if plate[v, u]:
            out.add((r.camera, int(r.frame), int(r.local)))
    return out


def _attached_pairs(
    inst: pd.DataFrame,
    pairs: pd.DataFrame,
    cam_a: str,
    cam_b: str,
    cams: tuple[Camera, Camera] | None,
    height: int,
    params: Mapping,
    plates: Mapping[str, np.ndarray] | None = None,
) -> set[tuple[str, int, int]]:
    """(camera, frame, local) of instances attached to the plate (nucleation region).

    Paired instances (with cameras): the silhouette bottoms triangulate to within
    ``nucleation_height`` of y = 0. Unpaired ones (an attached bubble hidden or
    fused in the other view), and all of them without cameras: the bottom rests on
    the plate's image when ``plates`` gives it, else on the lowest silhouette bottom
    of the session (within ``nucleation_margin_frac`` of the height).
    """
    out: set[tuple[str, int, int]] = set()
    if plates:
        paired = set()
        if cams is not None:
            paired = {
                (cam_a, int(t), int(a)) for t, a in zip(pairs.frame, pairs.local_a, strict=True)
            }
            paired |= {
                (cam_b, int(t), int(b)) for t, b in zip(pairs.frame, pairs.local_b, strict=True)
            }
        out |= _on_plate(inst, plates) - paired
        if cams is None:
            return out
    ia = inst[inst.camera == cam_a].set_index(["frame", "local"])
    ib = inst[inst.camera == cam_b].set_index(["frame", "local"])
    if cams is not None:
        if len(pairs) == 0:
            return out
        ua = ia.loc[list(zip(pairs.frame, pairs.local_a, strict=True)), ["bot_u", "bot_v"]]
        ub = ib.loc[list(zip(pairs.frame, pairs.local_b, strict=True)), ["bot_u", "bot_v"]]
        X = triangulate(list(cams), [ua.to_numpy(float), ub.to_numpy(float)])
        low = X[:, 1] < params["nucleation_height"]
        for (t, la, lb), lw in zip(
            pairs[["frame", "local_a", "local_b"]].itertuples(index=False), low, strict=True
        ):
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
    plates: Mapping[str, np.ndarray] | None = None,
    fps: float | None = None,
) -> tuple[dict[str, np.ndarray], pd.DataFrame, pd.DataFrame]:
    """Give every instance a bubble id, consistent across views and time.

    Args:
        labels: ``{camera: (T, H, W) int}`` instance labels per frame (−1 background).
            Views are taken in the mapping's order; the first two are associated
            (further views are tracked on their own).
        scores: ``{camera: [ (n_t,) confidence per frame ]}``.
        cameras: undistorted cameras of those frames (same pixel grid), or ``None``.
        params: overrides of :data:`ASSOCIATE_DEFAULTS`.
        plates: optional ``{camera: (H, W) bool}`` image of the heated plate (the
            static structure of :func:`surfphase.masks.classical.static_background`),
            used for instances that cannot be triangulated.
        fps: the session's frame rate (frames per second), for time settings such as
            ``merge_lobe_s`` (without it they count one frame).

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
    inst = pd.concat([instance_table(labels[c], scores[c], c) for c in names], ignore_index=True)
    attached: set[tuple[str, int, int]] = set()
    pairs = pd.DataFrame(columns=["frame", "local_a", "local_b", "cost"])
    cam_pair = None
    if len(names) >= 2:
        a, b = names[:2]
        if cameras is not None and a in cameras and b in cameras:
            cam_pair = (cameras[a], cameras[b])
        pairs = pair_views(inst, a, b, height, cam_pair, p)
        attached = _attached_pairs(inst, pairs, a, b, cam_pair, height, p, plates)
    tracks = {}
    for c in names:
        att = {(t, loc) for (cc, t, loc) in attached if cc == c}
        tracks[c] = track_view(labels[c], inst[inst.camera == c], att, p)
    if len(names) >= 2:
        tracks.update(reconcile_merges(tracks, labels, pairs, names[0], names[1], p, fps))
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
    instances = inst[
        ["frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1", "score"]
    ].sort_values(["frame", "camera", "bubble"], kind="stable")
    ev_rows = []

    def bubble_id(c: str, q: int) -> int:
        return 0 if q < 0 else bubble_of_group.get(find((c, q)), -1) if (c, q) in parent else -1

    for c in names:
        for t, kind, par, kids in tracks[c].events:
            # Tracks with no frame left (renamed by a later merge) drop out.
            pb = [b for b in (bubble_id(c, q) for q in par) if b >= 0]
            kb = [b for b in (bubble_id(c, q) for q in kids) if b >= 0]
            # No event left, or none in 3D (a piece of one bubble, seen apart in this view),
            # or a merge/split whose parents all lost their frames to later renames.
            if not kb or set(kb) <= set(pb) or (kind != "detach" and not pb):
                continue
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
