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
   plate: it belongs to bubble 0, the nucleation region. Where the image's bottom
   border cuts a silhouette (a plate just below the frame), this test takes the bottom
   of the circle its outline lies on (:func:`border_bottom`): the border is no
   bubble's bottom (the dating below keeps the silhouettes' own bottoms: a track whose
   outlines fit a circle in some frames only would mix the two). A bubble that rises out of it
   slowly in frames is free from the knee of the hinge (resting, then rising) fitted to
   its bottom heights over the attached frames it continues and its first frames
   (:mod:`surfphase.masks.detach`): the attached frames after the knee become its own,
   and so do the attached ones continuing its track whose bottoms keep to the rise. A
   track continued by bottoms back at the resting level never left: it is attached.
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

import numpy as np
import pandas as pd
from scipy import ndimage as ndi
from scipy.optimize import linear_sum_assignment

from surfphase.cameras import Camera, triangulate
from surfphase.masks import detach
from surfphase.masks.anchors import circle_fit, lowest_point
from surfphase.masks.classical import fill_holes_to_border
from surfphase.masks.merges import lobe_frames, reconcile_merges
from surfphase.masks.params import ANCHOR_DEFAULTS, ASSOCIATE_DEFAULTS
from surfphase.masks.tracking import Tracks, track_view

__all__ = [
    "ASSOCIATE_DEFAULTS",
    "Tracks",
    "associate",
    "fundamental_matrix",
    "instance_table",
    "lobe_frames",
    "pair_cost",
    "pair_views",
    "reconcile_merges",
    "symmetric_epipolar_distance",
    "track_view",
]


INSTANCE_COLUMNS = [
    "frame", "camera", "local", "area", "cx", "cy", "x0", "y0", "x1", "y1", "score",
    "top_u", "top_v", "bot_u", "bot_v", "low_u", "low_v",
]  # fmt: skip


def border_bottom(
    ys: np.ndarray, xs: np.ndarray, shape: tuple[int, int], max_rms: float
) -> tuple[float, float] | None:
    """The bottom of a silhouette that the image's bottom border cuts.

    The silhouette's pixels ``ys, xs`` (rows, columns) reach the last row of an image
    of ``shape`` (H, W): its lowest row is the border, not the bubble's bottom (a
    bubble on a plate just below the frame). Its outer outline pixels off the image's
    border (the silhouette filled as if the border closed it: a ring open there holds
    its core) are fitted with a circle (:func:`~surfphase.masks.anchors.circle_fit`); the
    circle's lowest point ``(u, v)`` (pixels, v ≥ the last row; the circle widened by
    half a pixel, the outline pixels' centres lying that far inside the silhouette's
    edge, so that a whole disc's bottom is its lowest pixel's centre) is the bottom,
    where the outline's rms distance to the circle is at most ``max_rms`` of its radius.
    None where the silhouette does not reach the last row, or the fit fails that test.
    """
    h, w = shape
    if ys.size == 0 or int(ys.max()) < h - 1:
        return None
    y0, x0, x1 = int(ys.min()), int(xs.min()), int(xs.max())
    m = np.zeros((h - y0, x1 - x0 + 1), bool)
    m[ys - y0, xs - x0] = True
    # A backlit bubble's bright core that the border opens is no hole of its ring:
    # closed along the border, the ring is filled, and only its outer edge is fitted.
    m = fill_holes_to_border(m, (y0 == 0, True, x0 == 0, x1 == w - 1))
    ey, ex = np.nonzero(m & ~ndi.binary_erosion(m))
    ey, ex = ey + y0, ex + x0
    keep = (ey > 0) & (ey < h - 1) & (ex > 0) & (ex < w - 1)
    pts = np.c_[ex[keep], ey[keep]].astype(np.float64)
    fit = circle_fit(pts)
    if fit is None:
        return None
    u, v, r = fit
    rms = float(np.sqrt(np.mean((np.linalg.norm(pts - (u, v), axis=1) - r) ** 2)))
    if rms > max_rms * r:
        return None
    return u, max(v + r + 0.5, float(h - 1))


def instance_table(
    labels: np.ndarray,
    scores: Sequence[np.ndarray],
    camera: str,
    cut_rms: float = ANCHOR_DEFAULTS["max_sphere_rms"],
) -> pd.DataFrame:
    """Per-instance geometry of a label stack.

    Args:
        labels: (T, H, W) int, −1 background, 0..n_t−1 instance index per frame.
        scores: per frame, (n_t,) backend confidence of each instance.
        camera: camera name for the table.
        cut_rms: :func:`border_bottom`'s ``max_rms`` (``masks: anchors:
            max_sphere_rms``).

    Returns:
        One row per instance: ``frame, camera, local`` (index in its frame), ``area``
        (pixels), centroid ``cx, cy``, inclusive box ``x0, y0, x1, y1``, ``score``,
        the silhouette's topmost and bottommost points (``top_u, top_v``: mean column
        of the top row; ``bot_u, bot_v``: sub-pixel, the vertex of the parabola through
        its bottom outline, :func:`~surfphase.masks.anchors.lowest_point`, within a
        quarter of its height of the lowest row) and the bubble's bottom ``low_u,
        low_v`` (``bot_u, bot_v``, or where the image's bottom border cuts the
        silhouette the :func:`border_bottom` of its outline), all in pixels.
    """
    rows = []
    shape = labels.shape[1:]
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
            low = lowest_point(ys, xs, max((bot - top) / 4.0, 1.0))
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
                    *low,
                    *(border_bottom(ys, xs, shape, cut_rms) or low),
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


def _on_plate(inst: pd.DataFrame, plates: Mapping[str, np.ndarray]) -> set[tuple[str, int, int]]:
    """Instances whose lowest pixel rests on the plate's image (its static region): the
    pixel under the lowest row (the sub-pixel bottom ``bot_v`` rounded to its row)."""
    out: set[tuple[str, int, int]] = set()
    for r in inst.itertuples():
        plate = plates.get(r.camera)
        if plate is None:
            continue
        v = min(int(round(r.bot_v)) + 1, plate.shape[0] - 1)
        u = min(max(int(round(r.bot_u)), 0), plate.shape[1] - 1)
        if plate[v, u]:
            out.add((r.camera, int(r.frame), int(r.local)))
    return out


def bottom_heights(
    inst: pd.DataFrame,
    pairs: pd.DataFrame,
    cam_a: str,
    cam_b: str,
    cams: tuple[Camera, Camera],
    cut: bool = True,
) -> np.ndarray:
    """(P,) lab height y (m) of each pair's triangulated bubble bottoms (``low_u,
    low_v`` of :func:`instance_table`, or with ``cut`` False the silhouettes' own
    ``bot_u, bot_v``; the rows of ``pairs``, a :func:`pair_views` table)."""
    if len(pairs) == 0:
        return np.zeros(0)
    ia = inst[inst.camera == cam_a].set_index(["frame", "local"])
    ib = inst[inst.camera == cam_b].set_index(["frame", "local"])
    cols = ["low_u", "low_v"] if cut else ["bot_u", "bot_v"]
    ua = ia.loc[list(zip(pairs.frame, pairs.local_a, strict=True)), cols]
    ub = ib.loc[list(zip(pairs.frame, pairs.local_b, strict=True)), cols]
    return triangulate(list(cams), [ua.to_numpy(float), ub.to_numpy(float)])[:, 1]


def _attached_pairs(
    inst: pd.DataFrame,
    pairs: pd.DataFrame,
    cam_a: str,
    cam_b: str,
    cams: tuple[Camera, Camera] | None,
    height: int,
    params: Mapping,
    plates: Mapping[str, np.ndarray] | None = None,
    heights: np.ndarray | None = None,
) -> set[tuple[str, int, int]]:
    """(camera, frame, local) of instances attached to the plate (nucleation region).

    Paired instances (with cameras): the silhouette bottoms triangulate to within
    ``nucleation_height`` of y = 0 (``heights``: the pairs' :func:`bottom_heights`,
    computed here when not given). Unpaired ones (an attached bubble hidden or
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
    if cams is not None:
        if len(pairs) == 0:
            return out
        if heights is None:
            heights = bottom_heights(inst, pairs, cam_a, cam_b, cams)
        low = heights < params["nucleation_height"]
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


def free_continuations(
    labels: Mapping[str, np.ndarray],
    inst: pd.DataFrame,
    pairs: pd.DataFrame,
    heights: np.ndarray,
    attached: set[tuple[str, int, int]],
    cameras: tuple[Camera, Camera],
    names: tuple[str, str],
    params: Mapping,
    agree: Mapping | None = None,
) -> set[tuple[str, int, int]]:
    """The attached instances that are a free bubble hidden or fused in the other view.

    An instance the other view has no partner for is called attached when its bottom
    rests on the plate's image (:func:`_attached_pairs`). A free bubble just above the
    plate can rest there too (a view from above sees the plate's top behind it) while
    the other view fuses it with a neighbour. Such an unpaired instance is free when it
    continues, in its own view, a free instance of the frame before or after: one
    paired across the views whose bottom triangulates at least ``nucleation_height``
    above the plate and whose two silhouettes are one bubble's by the mask stage's
    rule (:func:`surfphase.masks.anchors.views_agree` on their centroids and areas: not
    two specks of the plate's edge paired by chance), or one freed so; continues = mask
    IoU at least ``track_iou_min``. A bubble does not land back on the plate in the
    frames it is hidden.

    Args:
        labels: ``{camera: (T, H, W) int}`` instance labels (−1 background).
        inst: the :func:`instance_table` rows of both views.
        pairs: the :func:`pair_views` table of the views ``names``.
        heights: (P,) the pairs' :func:`bottom_heights` (m).
        attached: (camera, frame, local) of the attached instances.
        cameras: the two views' undistorted cameras.
        names: the two views' camera names.
        params: ``nucleation_height`` (m) and ``track_iou_min``.
        agree: ``masks: anchors:`` settings of :func:`views_agree` (default
            :data:`~surfphase.masks.params.ANCHOR_DEFAULTS`).

    Returns:
        The instances of ``attached`` to free.
    """
    from surfphase.masks.anchors import pair_agreement, views_agree

    agree = {**ANCHOR_DEFAULTS, **(agree or {})}
    cam_a, cam_b = names
    low = float(params["nucleation_height"])
    geom = inst.set_index(["camera", "frame", "local"])[["cx", "cy", "area"]]
    paired: set[tuple[str, int, int]] = set()
    free: set[tuple[str, int, int]] = set()
    for (t, la, lb), h in zip(
        pairs[["frame", "local_a", "local_b"]].itertuples(index=False), heights, strict=True
    ):
        ka, kb = (cam_a, int(t), int(la)), (cam_b, int(t), int(lb))
        paired |= {ka, kb}
        if h >= low:
            _, rep, ratio, r_px = pair_agreement(
                cameras, tuple(geom.loc[ka].to_numpy(float)), tuple(geom.loc[kb].to_numpy(float))
            )
            if views_agree(rep, ratio, r_px, agree):
                free |= {ka, kb}
    hidden = sorted(k for k in attached if k not in paired)
    masks = {k: np.asarray(labels[k[0]][k[1]]) == k[2] for k in hidden}
    known = set(free)  # free pairs, and the hidden instances freed so far

    def continues_free(key: tuple[str, int, int]) -> bool:
        cam, t, _ = key
        lab, mask = labels[cam], masks[key]
        for u in (t - 1, t + 1):
            if not 0 <= u < lab.shape[0]:
                continue
            other = np.asarray(lab[u])
            for j in np.unique(other[mask]):
                if j >= 0 and (cam, u, int(j)) in known:
                    m2 = other == j
                    if (mask & m2).sum() >= params["track_iou_min"] * (mask | m2).sum():
                        return True
        return False

    changed = True
    while changed:  # a chain of hidden frames frees from its free end
        changed = False
        for key in hidden:
            if key not in known and continues_free(key):
                known.add(key)
                changed = True
    return known.intersection(hidden)


def associate(
    labels: Mapping[str, np.ndarray],
    scores: Mapping[str, Sequence[np.ndarray]],
    cameras: Mapping[str, Camera] | None,
    params: Mapping | None = None,
    plates: Mapping[str, np.ndarray] | None = None,
    fps: float | None = None,
    anchor_params: Mapping | None = None,
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
        anchor_params: ``masks: anchors:`` settings of the views' agreement on a bubble
            (:func:`free_continuations`) and of the circle of a silhouette the image's
            bottom border cuts (``max_sphere_rms``, :func:`border_bottom`); default
            their defaults.

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
    cut_rms = float({**ANCHOR_DEFAULTS, **(anchor_params or {})}["max_sphere_rms"])
    inst = pd.concat(
        [instance_table(labels[c], scores[c], c, cut_rms) for c in names], ignore_index=True
    )
    attached: set[tuple[str, int, int]] = set()
    pairs = pd.DataFrame(columns=["frame", "local_a", "local_b", "cost"])
    cam_pair, hts = None, None
    if len(names) >= 2:
        a, b = names[:2]
        if cameras is not None and a in cameras and b in cameras:
            cam_pair = (cameras[a], cameras[b])
        pairs = pair_views(inst, a, b, height, cam_pair, p)
        if cam_pair is not None:
            hts = bottom_heights(inst, pairs, a, b, cam_pair)
        attached = _attached_pairs(inst, pairs, a, b, cam_pair, height, p, plates, hts)
        if cam_pair is not None:
            attached -= free_continuations(
                labels, inst, pairs, hts, attached, cam_pair, (a, b), p, anchor_params
            )
    tracks = _track_views(labels, inst, names, attached, p)
    if cam_pair is not None and attached:
        keys = detach.pair_keys(pairs, names[0], names[1])
        seen = bottom_heights(inst, pairs, names[0], names[1], cam_pair, cut=False)
        heights = {k: float(h) for (ka, kb), h in zip(keys, seen, strict=True) for k in (ka, kb)}
        partner = {ka: kb for ka, kb in keys} | {kb: ka for ka, kb in keys}
        two = {c: tracks[c] for c in names[:2]}
        freed, landed = detach.detachments(labels, two, heights, partner, attached, fps, p)
        if freed or landed:
            attached = (attached - freed) | landed
            tracks = _track_views(labels, inst, names, attached, p)
    if len(names) >= 2:
        tracks.update(reconcile_merges(tracks, labels, pairs, names[0], names[1], p, fps))
    groups = _link_tracks(tracks, names, pairs, p)
    bubble_of_group = _bubble_ids(inst, tracks, names, groups)
    out_labels, bubble_col = _bubble_labels(labels, inst, tracks, names, attached, groups,
                                            bubble_of_group)  # fmt: skip
    inst = inst.assign(bubble=bubble_col)
    instances = inst[
        ["frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1", "score"]
    ].sort_values(["frame", "camera", "bubble"], kind="stable")
    events = _event_table(tracks, names, groups, bubble_of_group)
    return out_labels, instances.reset_index(drop=True), events


def _track_views(
    labels: Mapping[str, np.ndarray], inst: pd.DataFrame, names: Sequence[str],
    attached: set[tuple[str, int, int]], p: Mapping,
) -> dict[str, Tracks]:  # fmt: skip
    """Every view's :func:`track_view` of its free instances."""
    out = {}
    for c in names:
        att = {(t, loc) for (cc, t, loc) in attached if cc == c}
        out[c] = track_view(labels[c], inst[inst.camera == c], att, p)
    return out


class _Groups:
    """Union-find over global track keys ``(camera, track)``, with each group's members
    and the frames of every track."""

    def __init__(self, frames_of: dict[tuple[str, int], set[int]]):
        self.frames_of = frames_of
        self.parent = {k: k for k in frames_of}
        self.members: dict = {k: [k] for k in frames_of}

    def find(self, k):
        parent = self.parent
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    def join(self, ka, kb) -> None:
        """Join the groups of ``ka`` and ``kb`` unless that puts two coexisting tracks of
        one view together."""
        ra, rb = self.find(ka), self.find(kb)
        if ra == rb or _conflict(self.members[ra], self.members[rb], self.frames_of):
            return
        self.parent[rb] = ra
        self.members[ra] = self.members[ra] + self.members.pop(rb)


def _link_tracks(
    tracks: Mapping[str, Tracks], names: Sequence[str], pairs: pd.DataFrame, p: Mapping
) -> _Groups:
    """Tracks of the first two views linked into groups (bubbles): a link when paired in
    at least ``link_frac`` of their common frames, strongest first."""
    frames_of: dict[tuple[str, int], set[int]] = {}
    for c in names:
        for (t, _loc), tid in tracks[c].track_of.items():
            frames_of.setdefault((c, tid), set()).add(t)
    groups = _Groups(frames_of)
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
        for (ka, kb), v in sorted(votes.items(), key=lambda kv: -kv[1]):
            common = len(frames_of[ka] & frames_of[kb])
            if v < max(1, p["link_frac"] * common):
                continue
            groups.join(ka, kb)
    return groups


def _bubble_ids(
    inst: pd.DataFrame, tracks: Mapping[str, Tracks], names: Sequence[str], groups: _Groups
) -> dict:
    """``{group root: bubble id}``, ids 1, 2, … in order of first appearance (then
    camera order, then centroid x)."""
    first: dict = {}
    for c in names:
        rows = inst[inst.camera == c]
        for r in rows.itertuples():
            tid = tracks[c].track_of.get((int(r.frame), int(r.local)))
            if tid is None:
                continue
            g = groups.find((c, tid))
            key = (int(r.frame), names.index(c), float(r.cx))
            if g not in first or key < first[g]:
                first[g] = key
    return {g: i + 1 for i, g in enumerate(sorted(first, key=first.get))}


def _bubble_labels(
    labels: Mapping[str, np.ndarray], inst: pd.DataFrame, tracks: Mapping[str, Tracks],
    names: Sequence[str], attached: set[tuple[str, int, int]], groups: _Groups,
    bubble_of_group: Mapping,
) -> tuple[dict[str, np.ndarray], np.ndarray]:  # fmt: skip
    """``{camera: (T, H, W) int32}`` bubble labels (0 for attached instances) and the
    (N,) bubble id of each row of ``inst``."""
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
                bid = bubble_of_group[groups.find((c, tracks[c].track_of[(t, loc)]))]
            bubble_col[row] = bid
            out[t][lab[t] == loc] = bid
        out_labels[c] = out
    return out_labels, bubble_col


def _event_table(
    tracks: Mapping[str, Tracks], names: Sequence[str], groups: _Groups, bubble_of_group: Mapping
) -> pd.DataFrame:
    """The views' events in bubble ids: ``frame, camera, event, parents, children``."""

    def bubble_id(c: str, q: int) -> int:
        if q < 0:
            return 0
        return bubble_of_group.get(groups.find((c, q)), -1) if (c, q) in groups.parent else -1

    ev_rows = []
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
    return pd.DataFrame(ev_rows, columns=["frame", "camera", "event", "parents", "children"])


def _conflict(ga: list, gb: list, frames_of: Mapping) -> bool:
    """Whether joining groups ``ga`` and ``gb`` puts two coexisting tracks of one view together."""
    for ka in ga:
        for kb in gb:
            if ka[0] == kb[0] and frames_of[ka] & frames_of[kb]:
                return True
    return False
