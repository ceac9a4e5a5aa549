"""Merges as one decision for both views (step 4 of :mod:`surfphase.masks.associate`):
the merges each view's tracking saw (:mod:`surfphase.masks.tracking`) are matched across
the views, given one frame, made where a view missed them and undone where the other
view refutes them (:func:`reconcile_merges`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy import ndimage as ndi

from surfphase.masks.tracking import Tracks


def lobe_frames(merge_lobe_s: float, fps: float | None) -> int:
    """Frames of ``merge_lobe_s`` seconds at ``fps`` (rounded, at least 1; 1 without fps)."""
    if fps is None or not fps > 0:
        return 1
    return max(1, int(round(float(merge_lobe_s) * float(fps))))


def onset_frames(merge_onset_s: float, fps: float | None) -> int:
    """Whole frames of ``merge_onset_s`` seconds at ``fps`` (rounded down; 0 without
    fps): the frames by which a merge's departure can show after its contact frame
    beyond the one :func:`_merge_frame` always allows."""
    if fps is None or not fps > 0:
        return 0
    return int(np.floor(float(merge_onset_s) * float(fps) + 1e-9))


def _track_frames(tr: Tracks) -> dict[int, set[int]]:
    """Frames in which each track of one view has an instance."""
    out: dict[int, set[int]] = {}
    for (t, _loc), k in tr.track_of.items():
        out.setdefault(k, set()).add(t)
    return out


def _merge_groups(
    tr: Tracks, frames: Mapping[int, set[int]], lobe: int
) -> dict[int, tuple[int, set[int]]]:
    """Merges of one view by merged track: ``{child: (frame, parent tracks)}``.

    A blob that swallowed several tracks in one frame is recorded by
    :func:`track_view` as a chain of merges through intermediate tracks left with
    no frame; they are one merge here, of the parents that have frames. So is a chain
    through the neck of two fusing lobes (:func:`_join_neck_chains`, within ``lobe``
    frames).
    """
    groups: dict[int, tuple[int, set[int]]] = {}
    for f, kind, par, kids in tr.events:
        if kind != "merge":
            continue
        for m in kids:
            if m in frames:
                f0, ps = groups.get(m, (f, set()))
                groups[m] = (min(f0, f), ps | set(par))
    groups = {
        m: (f, {q for q in ps if q in frames and q != m})
        for m, (f, ps) in groups.items()
        if any(q in frames and q != m for q in ps)
    }
    return _join_neck_chains(tr, groups, lobe)


def _join_neck_chains(
    tr: Tracks, groups: dict[int, tuple[int, set[int]]], lobe: int
) -> dict[int, tuple[int, set[int]]]:
    """Join the merges of ``groups`` (``{child: (frame, parents)}`` of one view) that
    are one merge of two lobes through their neck.

    Where two lobes fuse, the segmenter may cut the neck between them off one lobe
    (a *split*), the neck then joins the other lobe (a merge into an intermediate
    track) and that joins the first lobe (a second merge). Those are one merge of the
    lobes, first seen at the first of the two: merge ``m2`` with a parent ``m1`` that
    is itself merged at most ``lobe`` frames before, from a parent split off another
    of ``m2``'s parents within ``lobe`` frames of ``m2``, becomes one merge of all
    their parents (the intermediate track among them, so that its instances join the
    merged track too). Two merges in a row without such a neck piece stay two.
    """
    split_from = {
        k: (f, set(par)) for f, kind, par, kids in tr.events if kind == "split" for k in kids
    }
    out = dict(groups)
    joined = True
    while joined:
        joined = False
        for m2, (f2, p2) in sorted(out.items()):
            for m1 in sorted(p2 & set(out)):
                f1, p1 = out[m1]
                neck = any(
                    s in split_from
                    and split_from[s][0] >= f2 - lobe
                    and split_from[s][1] & (p2 - {m1})
                    for s in p1
                )
                if neck and 0 <= f2 - f1 <= lobe:
                    out[m2] = (min(f1, f2), (p1 | p2 | {m1}) - {m2})
                    del out[m1]
                    joined = True
                    break
            if joined:
                break
    return out


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

    * a chain of merges through the neck of two fusing lobes — a piece cut off one
      lobe joins the other, which then joins the first, within ``merge_lobe_s`` — is
      one merge of the lobes (:func:`_join_neck_chains`);
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
      one: the two lobes of a bubble that already merged;
    * but not before the frame before the lobes' centroid distance, in a view, departs
      from its straight-line trend (``merge_trend_frames``, ``merge_departure``), less
      the whole frames of ``merge_onset_s`` (:func:`onset_frames`: the lobes take
      about that long to slide together measurably): two bubbles about to touch
      also show as touching lobes (the liquid film between them is dark),
      approaching steadily, while merged lobes slide together faster.

    From the merge frame on, the parents' instances belong to the merged track in
    both views, so the merged bubble never shares an id with a parent.

    Args:
        tracks: ``{camera: Tracks}`` of :func:`~surfphase.masks.tracking.track_view` for ``cam_a`` and ``cam_b``.
        labels: ``{camera: (T, H, W) int}`` instance labels (−1 background).
        pairs: :func:`pair_views` table of ``cam_a`` and ``cam_b``.
        params: :data:`ASSOCIATE_DEFAULTS` keys ``coast_frames``, ``merge_lobe_s``,
            ``merge_trend_frames``, ``merge_departure``, ``merge_onset_s``.
        fps: the session's frame rate (frames per second), for ``merge_lobe_s`` and
            ``merge_onset_s``.

    Returns:
        New ``{camera: Tracks}`` for the two views (the inputs are not modified).
    """
    tr = {c: tracks[c].copy() for c in (cam_a, cam_b)}
    other_view = {cam_a: cam_b, cam_b: cam_a}
    coast = int(params["coast_frames"])
    lobe = lobe_frames(params["merge_lobe_s"], fps)
    trend = (int(params["merge_trend_frames"]), float(params["merge_departure"]))
    onset = onset_frames(params["merge_onset_s"], fps)
    pair_rows = list(pairs[["frame", "local_a", "local_b"]].itertuples(index=False))
    done: set[tuple[str, int]] = set()
    for _ in range(sum(len(t.events) for t in tr.values()) + 1):
        frames = {c: _track_frames(tr[c]) for c in tr}
        groups = {c: _merge_groups(tr[c], frames[c], lobe) for c in tr}
        todo = [(f, c, m, ps) for c in tr for m, (f, ps) in groups[c].items() if (c, m) not in done]
        if not todo:
            break
        f_v, v, m, par_v = min(todo, key=lambda x: (x[0], x[1] != cam_a, x[2]))
        done.add((v, m))
        w = other_view[v]
        votes = _pair_votes(tr, pair_rows, cam_a, cam_b)
        par_w = {q for q in (_partner(votes, v, p) for p in par_v) if q is not None}
        pm = _partner(votes, v, m)
        parents: dict[str, set[int]] = {v: set(par_v)}
        child = {v: m}
        f, f_last = f_v, f_v
        m2 = _same_merge(groups[w], done, w, f_v, coast, pm, par_w)
        if m2 is not None:
            done.add((w, m2))
            f2, ps2 = groups[w][m2]
            parents[w], child[w] = set(ps2), m2
            f, f_last = min(f_v, f2), max(f_v, f2)
        elif pm is not None and pm in par_w and len(par_w) >= 2:
            rest = par_w - {pm}
            if max(max(frames[w][q]) for q in rest) > f_v + 1:
                # The other view still sees the bubbles apart: an occlusion here.
                _undo_merge(tr[v], m, frames[v])
                continue
            m2 = tr[w].new()
            done.add((w, m2))
            parents[w], child[w] = {pm} | rest, m2
        f = _merge_frame(tr, labels, parents, child, f, f_last, lobe, trend, onset)
        _apply_merge(tr, parents, child, f)
    return tr


def _pair_votes(
    tr: Mapping[str, Tracks], pair_rows: Sequence[tuple], cam_a: str, cam_b: str
) -> dict[tuple[str, int], dict[int, int]]:
    """``{(camera, track): {track of the other view: frames paired}}``."""
    votes: dict[tuple[str, int], dict[int, int]] = {}
    for t, la, lb in pair_rows:
        ka = tr[cam_a].track_of.get((int(t), int(la)))
        kb = tr[cam_b].track_of.get((int(t), int(lb)))
        if ka is None or kb is None:
            continue
        va, vb = votes.setdefault((cam_a, ka), {}), votes.setdefault((cam_b, kb), {})
        va[kb] = va.get(kb, 0) + 1
        vb[ka] = vb.get(ka, 0) + 1
    return votes


def _partner(votes: Mapping[tuple[str, int], Mapping[int, int]], c: str, k: int) -> int | None:
    """The other view's track most often paired with track ``k`` of view ``c``
    (the smallest id among ties), or None."""
    vs = votes.get((c, k))
    return None if not vs else max(sorted(vs), key=vs.get)


def _same_merge(
    groups_w: Mapping[int, tuple[int, set[int]]], done: set[tuple[str, int]], w: str,
    f_v: int, coast: int, pm: int | None, par_w: set[int],
) -> int | None:  # fmt: skip
    """The merge of view ``w`` that is the same as one at frame ``f_v`` of the other
    view (its merged track is the partner ``pm``, or two of its parents are partners
    ``par_w``, within ``coast`` frames), the nearest in time; None without one."""
    same = [
        (abs(f2 - f_v), m2)
        for m2, (f2, ps2) in groups_w.items()
        if (w, m2) not in done and abs(f2 - f_v) <= coast and (m2 == pm or len(ps2 & par_w) >= 2)
    ]
    return min(same)[1] if same else None


def _undo_merge(tr: Tracks, m: int, frames: Mapping[int, set[int]]) -> None:
    """Undo merge ``m`` of one view (an occlusion): its blob keeps the id of the
    track it continues (the first of its chain that has frames)."""
    root = tr.continues.get(m)
    while root is not None and root not in frames:
        root = tr.continues.get(root)
    if root is not None:
        tr.events = [e for e in tr.events if not (e[1] == "merge" and m in e[3])]
        _relabel(tr, {m}, root, 0)


def _joined(
    tr: Mapping[str, Tracks], labels: Mapping[str, np.ndarray], parents: Mapping[str, set[int]],
    child: Mapping[str, int], g: int,
) -> tuple[bool, int]:  # fmt: skip
    """Whether the bubbles touch in every view at frame g; most instances."""
    most = 0
    for c, ps in parents.items():
        ks = ps | {child[c]}
        locs = [loc for (t, loc), k in tr[c].track_of.items() if t == g and k in ks]
        if not locs or not _connected(np.asarray(labels[c][g]), locs):
            return False, most
        most = max(most, len(locs))
    return True, most


def _merge_frame(
    tr: Mapping[str, Tracks], labels: Mapping[str, np.ndarray], parents: Mapping[str, set[int]],
    child: Mapping[str, int], f: int, f_last: int, lobe: int, trend: tuple[int, float],
    onset: int,
) -> int:  # fmt: skip
    """The frame of a merge first seen between ``f`` and ``f_last``: the first from
    which the parents touch in every view, dated back over up to ``lobe`` frames where
    they show as two touching lobes, but not before the frame before the lobes depart
    from the parents' approach in a view (``trend``: ``(merge_trend_frames,
    merge_departure)``, :func:`_departure`), less ``onset`` frames (:func:`onset_frames`)."""
    first = f
    # Not merged while a view sees the parents apart (the first fusion was an
    # occlusion in the other view) ...
    while f < f_last and not _joined(tr, labels, parents, child, f)[0]:
        f += 1
    # ... and merged already where they show as two touching lobes ...
    for g in range(f - 1, max(f - 1 - lobe, -1), -1):
        ok, most = _joined(tr, labels, parents, child, g)
        if not (ok and most >= 2):
            break
        f = g
    # ... unless they still approach as before: bubbles about to touch are lobes too.
    if f + 1 < first:
        deps = [_departure(tr[c], labels[c], parents[c], f, first, *trend) for c in parents]
        if any(g is not None for g in deps):
            f = max(f, min(g for g in deps if g is not None) - 1 - onset)
    return f


def _pair_distance(lab: np.ndarray, locs: Sequence[Sequence[int]]) -> tuple[float, float] | None:
    """Distance (px) between the centroids of two sets of instances ``locs`` (local
    labels) in one (H, W) label image, and their summed area-equivalent radii (px);
    None unless both have pixels."""
    frame = np.asarray(lab)
    cents, radii = [], []
    for ls in locs:
        ys, xs = np.nonzero(np.isin(frame, ls))
        if not len(ys):
            return None
        cents.append((xs.mean(), ys.mean()))
        radii.append(np.sqrt(len(ys) / np.pi))
    return float(np.hypot(*np.subtract(*cents))), float(sum(radii))


def _departure(
    tr: Tracks, lab: np.ndarray, parents: set[int], start: int, first: int,
    trend_frames: int, depart: float,
) -> int | None:  # fmt: skip
    """The first frame in ``(start, first)`` at which two parents' centroid distance in
    one view falls below the straight line through it over the previous
    ``trend_frames`` frames (at least 3 of them) by more than ``depart`` × their summed
    radii and 3 residual SDs: the lobes slide together faster than the bubbles
    approached. The two parents seen in most frames before ``first`` are followed;
    None without a departure or without two parents seen."""
    seen = dict.fromkeys(parents, 0)
    locs_at: dict[tuple[int, int], list[int]] = {}  # (frame, track): its instances
    for (t, loc), k in tr.track_of.items():
        if k in seen and t < first:
            seen[k] += 1
            locs_at.setdefault((t, k), []).append(loc)
    pair = sorted(seen, key=lambda q: (-seen[q], q))[:2]
    if len(pair) < 2 or not all(seen[q] for q in pair):
        return None
    series = {}
    for g in range(max(0, start - trend_frames), first):
        locs = [locs_at.get((g, q)) for q in pair]
        if all(locs) and (d := _pair_distance(lab[g], locs)) is not None:
            series[g] = d
    for g in range(start + 1, first):
        prev = [h for h in series if g - trend_frames <= h < g]
        if g not in series or len(prev) < 3:
            continue
        t = np.array(prev, float)
        d = np.array([series[h][0] for h in prev])
        coef = np.polyfit(t, d, 1)
        sd = float(np.std(d - np.polyval(coef, t), ddof=2))
        dist, radii = series[g]
        if dist < np.polyval(coef, g) - max(3.0 * sd, depart * radii):
            return g
    return None


def _apply_merge(
    tr: Mapping[str, Tracks], parents: Mapping[str, set[int]], child: Mapping[str, int], f: int
) -> None:
    """From frame ``f`` on, each view's parents belong to its merged track, with one
    ``merge`` event at ``f``."""
    for c, ps in parents.items():
        tr[c].events = [e for e in tr[c].events if not (e[1] == "merge" and child[c] in e[3])]
        _relabel(tr[c], ps, child[c], f)
        tr[c].events.append((f, "merge", sorted(ps), [child[c]]))
        tr[c].events.sort(key=lambda e: e[0])
