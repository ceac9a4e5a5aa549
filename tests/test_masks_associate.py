"""Association across views and time on a two-view movie of spheres drawn here."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from test_masks_scene import rig, rising, write_ingest

from surfphase.masks.associate import (
    ASSOCIATE_DEFAULTS,
    Tracks,
    associate,
    free_continuations,
    fundamental_matrix,
    reconcile_merges,
    symmetric_epipolar_distance,
)
from surfphase.masks.classical import segment_frame
from surfphase.masks.merges import _join_neck_chains


def _segment(folder, cams):
    labels, scores = {}, {}
    for c in cams:
        st = np.load(folder / f"{c}.npy")
        out = [segment_frame(f) for f in st]
        labels[c] = np.stack([o[0] for o in out])
        scores[c] = [o[1] for o in out]
    return labels, scores


def _ids(truth, labels, k):
    """Predicted id covering most of truth sphere k, per frame (None when absent)."""
    out = []
    for t in range(truth.shape[0]):
        g = truth[t] == k
        if g.sum() < 6:
            out.append(None)
            continue
        v, c = np.unique(labels[t][g], return_counts=True)
        out.append(int(v[np.argmax(c)]))
    return out


def test_fundamental_matrix_against_projections():
    cams = rig(128)
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.004, 0.0, -0.002], [0.004, 0.012, 0.002], size=(20, 3))
    ua = cams["cam0"].project(X, distort=False)
    ub = cams["cam1"].project(X, distort=False)
    F = fundamental_matrix(cams["cam0"], cams["cam1"])
    d = symmetric_epipolar_distance(F, ua, ub)
    assert np.abs(np.diag(d)).max() < 1e-6
    # Points at other heights are far from each other's epipolar lines.
    off = d[~np.eye(20, dtype=bool)]
    assert np.median(off) > 3.0


SPHERES = [
    # Attached to the plate and growing: the nucleation region, bubble 0.
    lambda t: (np.array([-0.0025, 0.0006 + 0.00003 * t, 0.0]), 0.0006 + 0.00003 * t),
    rising(0.002, 0.002, 0.0, 0.0008),
    rising(-0.0005, 0.006, 0.001, 0.001),
    # Two at the same height, different sizes and depths.
    rising(-0.003, 0.010, 0.0, 0.0007),
    rising(0.003, 0.0101, -0.001, 0.001),
]


@pytest.mark.parametrize("use_cameras", [True, False])
def test_ids_agree_across_views_and_frames(tmp_path, use_cameras):
    truth = write_ingest(tmp_path, SPHERES, 10)
    labels, scores = _segment(tmp_path, truth)
    cams = rig(128) if use_cameras else None
    out, inst, events = associate(labels, scores, cams)
    ids = {c: [_ids(truth[c], out[c], k) for k in range(len(SPHERES))] for c in truth}
    # The attached sphere is bubble 0 in every frame of both views.
    assert set(ids["cam0"][0]) == {0} and set(ids["cam1"][0]) == {0}
    seen = set()
    for k in range(1, len(SPHERES)):
        a, b = ids["cam0"][k], ids["cam1"][k]
        assert a == b, k  # same id in both views, every frame
        assert len(set(a)) == 1 and a[0] >= 1  # one id through time
        seen.add(a[0])
    assert len(seen) == len(SPHERES) - 1  # distinct bubbles
    assert list(inst.columns) == [
        "frame",
        "camera",
        "bubble",
        "area",
        "cx",
        "cy",
        "x0",
        "y0",
        "x1",
        "y1",
        "score",
    ]
    assert len(events) == 0


def test_merge_is_recorded_and_gets_a_new_id(tmp_path):
    """Two spheres meet at frame 5 and go on as one larger sphere."""

    def left(t):
        if t >= 5:
            return None
        return np.array([-0.0018 + 0.0003 * t, 0.006, 0.0]), 0.0008

    def right(t):
        if t >= 5:
            return None
        return np.array([0.0018 - 0.0003 * t, 0.006, 0.0]), 0.0008

    def merged(t):
        if t < 5:
            return None
        return np.array([0.0, 0.006 + 0.0001 * (t - 5), 0.0]), 0.001

    truth = write_ingest(tmp_path, [left, right, merged], 16)
    labels, scores = _segment(tmp_path, truth)
    out, inst, events = associate(labels, scores, rig(128))
    ids = {c: [_ids(truth[c], out[c], k) for k in range(3)] for c in truth}
    for c in truth:
        a, b, m = ids[c]
        assert len(set(a[:4])) == 1 and len(set(b[:4])) == 1 and a[0] != b[0]
        assert len(set(m[6:])) == 1 and m[-1] not in (a[0], b[0])
    merges = events[events.event == "merge"]
    assert len(merges) >= 1
    row = merges.iloc[0]
    assert str(ids["cam0"][2][-1]) in row.children.split("+")
    assert set(row.parents.split("+")) & {str(ids["cam0"][0][0]), str(ids["cam0"][1][0])}


def test_plate_image_marks_the_nucleation_region_without_cameras(tmp_path):
    truth = write_ingest(tmp_path, SPHERES[:3], 4)
    labels, scores = _segment(tmp_path, truth)
    plates = {}
    for c, tr in truth.items():
        rows = np.nonzero((tr == 0).any(axis=(0, 2)))[0]
        plate = np.zeros(tr.shape[1:], bool)
        plate[rows.max() + 1 :] = True  # the plate's image starts under the attached sphere
        plates[c] = plate
    params = {"nucleation_margin_frac": 0.0}  # the fallback alone would not catch it
    out, _, _ = associate(labels, scores, None, params, plates)
    for c in truth:
        assert set(_ids(truth[c], out[c], 0)) == {0}
        assert 0 not in _ids(truth[c], out[c], 1) + _ids(truth[c], out[c], 2)


def _disk(h, w, cy, cx, r):
    yy, xx = np.mgrid[0:h, 0:w]
    return (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r


def _merging_pair(fuse: dict[str, int], lobes_from: int, n: int = 10, size: int = 64):
    """Label stacks of two blobs that merge, drawn by hand (no segmenter).

    Blob A rises slowly, blob B (below it) faster, until they touch: from frame
    ``lobes_from`` the two are one bubble, drawn as two overlapping disks; a view
    shows it as one instance from frame ``fuse[view]`` on and, before that, as the
    two lobes cut apart along the row between them (touching instances), as a
    segmenter that splits touching bubbles does. Before ``lobes_from`` the blobs are
    apart (a gap of at least 2 px). The views differ only in columns, so without
    cameras they pair by image rows. Returns ``{view: (n, size, size) int32}``.
    """
    out = {}
    for view, x_off in (("cam0", 0), ("cam1", 6)):
        lab = np.full((n, size, size), -1, np.int32)
        for t in range(n):
            ya = 30.0 - t
            if t < lobes_from:
                gap = 2 * (lobes_from - t) + 1  # px between the silhouettes
                a = _disk(size, size, ya, 28 + x_off, 5)
                b = _disk(size, size, ya + 10 + gap, 30 + x_off, 5)
                lab[t][a], lab[t][b] = 0, 1
                continue
            # The merged bubble: two overlapping lobes drawing together, then one disk.
            k = t - lobes_from
            d = max(8.0 - 3 * k, 0.0)
            union = _disk(size, size, ya, 28 + x_off, 5) | _disk(size, size, ya + d, 30 + x_off, 5)
            if t >= fuse[view]:
                lab[t][union] = 0
            else:
                cut = int(round(ya + d / 2))
                rows = np.arange(size)[:, None]
                lab[t][union & (rows <= cut)] = 0
                lab[t][union & (rows > cut)] = 1
        out[view] = lab
    return out


def _no_plate(labels):
    """No heated plate in view: no instance is the nucleation region."""
    return {c: np.zeros(lab.shape[1:], bool) for c, lab in labels.items()}


def _blob_ids(lab: np.ndarray) -> list[set[int]]:
    """The set of ids on the foreground of each frame."""
    return [set(np.unique(f[f >= 0]).tolist()) for f in lab]


@pytest.mark.parametrize(
    ("fuse", "lobes_from", "merge_frame"),
    [
        # Fused at frame 4 in both views; apart at frame 3.
        ({"cam0": 4, "cam1": 4}, 4, 4),
        # Fused at 4 in view 0 but one frame later in view 1: merged at 4 in both.
        ({"cam0": 4, "cam1": 5}, 4, 4),
        # The same, the other way round.
        ({"cam0": 5, "cam1": 4}, 4, 4),
        # Merged at 3, seen as touching lobes there in both views, fused at 4 and 5.
        ({"cam0": 4, "cam1": 5}, 3, 3),
    ],
)
def test_merge_switches_id_at_the_same_frame_in_both_views(fuse, lobes_from, merge_frame):
    labels = _merging_pair(fuse, lobes_from)
    scores = {c: [np.ones(int(f.max()) + 1) for f in lab] for c, lab in labels.items()}
    out, _, events = associate(labels, scores, None, plates=_no_plate(labels))
    ids = {c: _blob_ids(out[c]) for c in out}
    before = ids["cam0"][0]
    assert len(before) == 2 and 0 not in before
    merged = ids["cam0"][-1]
    assert len(merged) == 1 and not merged & before
    for c in out:
        # Both parents up to the frame before the merge, the merged id from it on,
        # the lobes of a young merged bubble included.
        assert all(ids[c][t] == before for t in range(merge_frame)), (c, ids[c])
        assert all(ids[c][t] == merged for t in range(merge_frame, 10)), (c, ids[c])
    merges = events[events.event == "merge"]
    assert sorted(merges.camera) == ["cam0", "cam1"]
    assert set(merges.frame) == {merge_frame}
    (m,) = merged
    for r in merges.itertuples():
        assert r.children == str(m)
        assert set(map(int, r.parents.split("+"))) == before


def test_fusion_in_one_view_that_the_other_view_refutes_is_no_merge():
    """View 0 sees bubble B pass behind bubble A for good; view 1 sees both apart."""
    n, size = 10, 64
    labels = {}
    for view, xb in (("cam0", 30), ("cam1", 46)):
        lab = np.full((n, size, size), -1, np.int32)
        for t in range(n):
            a = _disk(size, size, 20, 30, 7)
            b = _disk(size, size, 36 - 2 * min(t, 6), xb, 4)
            if view == "cam0" and t >= 5:
                lab[t][a | b] = 0  # B hidden behind A: one silhouette
            else:
                lab[t][a] = 0
                lab[t][b & ~a] = 1
        labels[view] = lab
    scores = {c: [np.ones(int(f.max()) + 1) for f in lab] for c, lab in labels.items()}
    out, _, events = associate(labels, scores, None, plates=_no_plate(labels))
    a_ids = {c: {int(out[c][t][20, 30]) for t in range(n)} for c in out}
    assert a_ids["cam0"] == a_ids["cam1"] and len(a_ids["cam0"]) == 1  # A keeps its id
    (a_id,) = a_ids["cam0"]
    b_ids = {int(out["cam1"][t][36 - 2 * min(t, 6), 46]) for t in range(n)}
    assert len(b_ids) == 1 and a_id not in b_ids
    assert (events.event == "merge").sum() == 0


def test_a_merge_missed_by_one_view_is_made_there_at_the_same_frame():
    """View 1's tracker let the fused blob carry on as bubble A and just lost B."""
    labels = _merging_pair({"cam0": 4, "cam1": 4}, 4)
    n = labels["cam0"].shape[0]
    # View 0: A (track 0) and B (track 1) merge into track 2 at frame 4.
    t0 = Tracks(n=3, continues={2: 0})
    t1 = Tracks(n=2)  # view 1: A (track 0) goes on through the fusion, B (1) stops
    for t in range(n):
        if t < 4:
            t0.track_of[(t, 0)], t0.track_of[(t, 1)] = 0, 1
            t1.track_of[(t, 0)], t1.track_of[(t, 1)] = 0, 1
        else:
            t0.track_of[(t, 0)] = 2
            t1.track_of[(t, 0)] = 0
    t0.events.append((4, "merge", [1, 0], [2]))
    rows = [(t, 0, 0, 0.0) for t in range(n)] + [(t, 1, 1, 0.0) for t in range(4)]
    pairs = pd.DataFrame(rows, columns=["frame", "local_a", "local_b", "cost"])
    out = reconcile_merges(
        {"cam0": t0, "cam1": t1}, labels, pairs, "cam0", "cam1", ASSOCIATE_DEFAULTS
    )
    after = {out["cam1"].track_of[(t, 0)] for t in range(4, n)}
    assert len(after) == 1 and not after & {0, 1}  # a new track from frame 4 on
    assert {out["cam1"].track_of[(t, 0)] for t in range(4)} == {0}
    (m1,) = after
    assert [e for e in out["cam1"].events if e[1] == "merge"] == [(4, "merge", [0, 1], [m1])]
    assert [e for e in out["cam0"].events if e[1] == "merge"] == [(4, "merge", [0, 1], [2])]
    assert t1.track_of[(5, 0)] == 0 and t1.events == []  # the inputs are left alone


def _approaching_pair(n: int = 14, size: int = 72) -> dict[str, np.ndarray]:
    """Two disks (radius 8 px) approaching at 1 px per frame, drawn by hand.

    Centroid distance ``D``: 24 − t px. From frame 6 (D 18, a 2 px gap) a film joins
    the silhouettes, cut apart along the middle row (touching instances, as a
    segmenter gives two bubbles about to touch); the approach goes on as before. From
    frame 9 the lobes slide together faster (D 13, then 10), and from frame 11 each
    view shows one blob. Returns ``{view: (n, size, size) int32}``.
    """
    dist = {t: 24 - t for t in range(9)} | {9: 13, 10: 10}
    out = {}
    rows, cols = np.arange(size)[:, None], np.arange(size)[None, :]
    for view, x_off in (("cam0", 0), ("cam1", 6)):
        lab = np.full((n, size, size), -1, np.int32)
        for t in range(n):
            ya, xa, d = 30 - t, 28 + x_off, dist.get(t, 0)
            union = _disk(size, size, ya, xa, 8) | _disk(size, size, ya + d, xa, 8)
            if t >= 11:
                lab[t][union] = 0
                continue
            if t >= 6:  # the film (then the neck) between the silhouettes
                union |= (rows >= ya) & (rows <= ya + d) & (abs(cols - xa) <= 1)
            lab[t][union & (2 * rows <= 2 * ya + d)] = 0
            lab[t][union & (2 * rows > 2 * ya + d)] = 1
        out[view] = lab
    return out


@pytest.mark.parametrize(
    ("departure", "fps", "merge_frame"),
    [(0.02, 1000, 8), (10.0, 1000, 6), (0.02, 6000, 8), (0.02, 7000, 7), (0.02, 20000, 6)],
)
def test_bubbles_approaching_as_touching_lobes_merge_when_the_approach_speeds_up(
    departure, fps, merge_frame
):
    """Touching silhouettes alone date the merge at frame 6 (10 ms of look-back
    reaches it); the steady approach through frames 6–8 dates it one frame before the
    lobes leave that trend (frame 9), and one frame earlier for each whole frame of
    the default ``merge_onset_s`` (0.15 ms: none at 1000 or 6000 fps, one at 7000 fps),
    but never before the lobes touch (three would at 20,000 fps: frame 5). With a departure threshold
    of 10 × the radii nothing departs, and the look-back alone decides."""
    labels = _approaching_pair()
    scores = {c: [np.ones(int(f.max()) + 1) for f in lab] for c, lab in labels.items()}
    params = {"merge_lobe_s": 0.01, "merge_departure": departure}
    out, _, events = associate(labels, scores, None, params, plates=_no_plate(labels), fps=fps)
    ids = {c: _blob_ids(out[c]) for c in out}
    before, merged = ids["cam0"][0], ids["cam0"][-1]
    assert len(before) == 2 and len(merged) == 1 and not merged & before
    for c in out:
        assert all(ids[c][t] == before for t in range(merge_frame)), (c, ids[c])
        assert all(ids[c][t] == merged for t in range(merge_frame, 14)), (c, ids[c])
    assert set(events[events.event == "merge"].frame) == {merge_frame}


def test_a_free_bubble_fused_in_the_other_view_does_not_land_on_the_plate():
    """Spheres seen by the two-view rig over 6 frames, labels from their projections:
    A (0.5 mm) rises 0.12 mm a frame, its bottom 1.5 mm above the plate; B is 3 mm
    behind it along cam1's ray, so cam1 shows the two as one silhouette, made one
    instance there in frames 2–3. There neither view has a partner for A; call it
    attached (as the on-plate rule would). Paired in frames 0, 1, 4 and 5, where the
    views agree on it, A is free in 2–3 as well, and so is cam1's fused instance, which
    continues A and B. Specks S, one per view, paired by chance about 0.7 mm above the plate
    in frame 1 (centres and sizes that are no one sphere's) free nothing: S's unpaired
    continuation stays attached. With A paired on the plate, cam0's A stays attached."""
    from test_masks_scene import draw_view

    from surfphase.masks.associate import bottom_heights, instance_table

    cams = rig(128)
    c0, c1 = cams["cam0"], cams["cam1"]
    ray1 = c1.view_dir / np.linalg.norm(c1.view_dir)
    a0 = np.array([0.0, 2.0e-3, 0.0])

    def spheres(t):
        a = a0 + [0.0, 1.2e-4 * t, 0.0]
        return {"A": (a, 0.5e-3), "B": (a + 3e-3 * ray1, 0.5e-3)}

    n, size = 6, 128
    lab = {c: np.full((n, size, size), -1, np.int32) for c in cams}
    local: dict = {}
    for t in range(n):
        for c, cam in cams.items():
            sph = spheres(t)
            _, truth = draw_view(cam, list(sph.values()), seed=t)
            names = list(sph)
            fused = c == "cam1" and t in (2, 3)
            for k, name in enumerate(names):
                lab[c][t][truth == k] = 0 if fused else k
                local[c, t, name] = 0 if fused else k
            # Specks of different sizes at the images of two points 4 mm apart.
            pt = np.array([[(-2e-3, 2e-3)[c == "cam1"], 1.5e-3, 0.0]])
            u, v = np.round(cam.project(pt, distort=False)[0]).astype(int)
            half = (1, 2)[c == "cam1"]
            lab[c][t][v - half : v + half + 1, u - half : u + half + 1] = 2
            local[c, t, "S"] = 2
    scores = {c: [np.ones(3)] * n for c in cams}
    inst = pd.concat([instance_table(lab[c], scores[c], c) for c in cams], ignore_index=True)
    rows = [(t, local["cam0", t, nm], local["cam1", t, nm], 0.1)
            for t in range(n) for nm in (["A", "B"] if t not in (2, 3) else [])]  # fmt: skip
    rows.append((1, 2, 2, 0.1))  # the specks, paired by chance
    pairs = pd.DataFrame(rows, columns=["frame", "local_a", "local_b", "cost"])
    heights = bottom_heights(inst, pairs, "cam0", "cam1", (c0, c1))
    assert heights[-1] > ASSOCIATE_DEFAULTS["nucleation_height"]
    assert heights[:-1].min() > 1e-3
    hidden = {("cam0", t, local["cam0", t, "A"]) for t in (2, 3)}
    hidden |= {("cam1", t, 0) for t in (2, 3)}
    specks = {(c, t, 2) for c in cams for t in (0, 2)}

    def freed(h):
        return free_continuations(
            lab, inst, pairs, h, hidden | specks, (c0, c1), ("cam0", "cam1"), ASSOCIATE_DEFAULTS
        )

    assert freed(heights) == hidden
    on_plate = np.where(np.arange(len(heights)) < len(heights) - 1, 0.0, heights)
    assert freed(on_plate) == set()


@pytest.mark.parametrize(("lift_mm", "core"), [(0.0, False), (0.4, False), (0.0, True)])
def test_a_bubble_the_bottom_border_cuts_has_the_bottom_of_its_circle(lift_mm, core):
    """A 0.6 mm sphere whose bottom is ``lift_mm`` above the plate, seen by the two-view
    rig at 512 px (18 px radius), each view cut a fifth of the sphere's image radius
    below its centre's row: the plate lies below the frame, the image's bottom border
    cuts the silhouettes and their lowest rows triangulate 0.3 mm or more above the
    sphere's bottom, a bubble on the plate then called free. The bottoms of the
    circles of the cut outlines triangulate to the sphere's bottom (analytic) within
    0.04 mm, and to the whole silhouettes' bottoms within 0.03 mm (a pixel there is
    0.033 mm): on the plate, the nucleation region; 0.4 mm above it, free. With
    ``core``, each cut silhouette is a ring whose bright core (half its radius) the
    border opens: filled as if the border closed it, its outer outline gives the same
    circle."""
    from test_masks_scene import draw_view

    from surfphase.cameras import triangulate
    from surfphase.masks.associate import border_bottom, bottom_heights, instance_table

    cams = rig(512)
    r = 0.6e-3
    X = np.array([0.0, r + lift_mm * 1e-3, 0.0])
    whole, cut = {}, {}
    for c, cam in cams.items():
        _, truth = draw_view(cam, [(X, r)], seed=0)
        ((_, v),) = cam.project(X[None], distort=False)
        rp = cam.K[0, 0] * r / cam.world_to_camera(X[None])[0, 2]
        keep = int(v + 0.2 * rp)
        whole[c] = np.where(truth == 0, 0, -1)[None]
        cut[c] = whole[c][:, :keep].copy()
        if core:
            ((u, _),) = cam.project(X[None], distort=False)
            vv, uu = np.mgrid[0:keep, 0 : truth.shape[1]]
            hole = (uu - u) ** 2 + (vv - v) ** 2 < (0.5 * rp) ** 2
            assert hole[-1].any()  # open to the border
            cut[c][0][hole] = -1
        ys, xs = np.nonzero(cut[c][0] == 0)
        assert ys.max() == keep - 1  # the border cuts it
        assert border_bottom(ys, xs, (keep, truth.shape[1]), 0.08)[1] > keep - 1 + 0.5 * rp
        ys, xs = np.nonzero(whole[c][0] == 0)
        assert border_bottom(ys, xs, truth.shape, 0.08) is None  # not cut: no circle
    pairs = pd.DataFrame([(0, 0, 0, 0.1)], columns=["frame", "local_a", "local_b", "cost"])
    pair = (cams["cam0"], cams["cam1"])

    def heights(labels):
        inst = pd.concat(
            [instance_table(labels[c], [np.ones(1)], c) for c in cams], ignore_index=True
        )
        rows = [inst[inst.camera == c][["bot_u", "bot_v"]].to_numpy(float) for c in cams]
        border = triangulate(list(pair), rows)[0, 1]
        return bottom_heights(inst, pairs, "cam0", "cam1", pair)[0], border

    h_cut, h_border = heights(cut)
    h_whole, _ = heights(whole)
    lift = lift_mm * 1e-3
    assert h_border > lift + 0.3e-3
    assert abs(h_cut - lift) < 0.04e-3
    assert abs(h_cut - h_whole) < 0.03e-3
    low = ASSOCIATE_DEFAULTS["nucleation_height"]
    assert bool(h_cut < low) == (lift_mm == 0.0)
    assert h_border > low


def _neck_tracks(labels: dict[str, np.ndarray], neck: bool) -> dict[str, Tracks]:
    """Hand-made tracks of :func:`_approaching_pair`'s views (A instance 0, B 1, one
    blob from frame 11), as a tracker leaves them when the segmenter cuts the neck
    between fusing lobes off A at frame 9 (``neck``): the piece (track 2) joins B at
    frame 10 (track 3), which joins A at 11 (track 4). Without ``neck``: A and B go
    on as tracks 0 and 1 up to frame 10 and merge into track 2 at 11."""
    out = {}
    for view, lab in labels.items():
        tr = Tracks(n=5 if neck else 3)
        for t in range(lab.shape[0]):
            locs = sorted(int(q) for q in np.unique(lab[t][lab[t] >= 0]))
            for loc in locs:
                if t >= 11:
                    k = 4 if neck else 2
                elif neck and t == 10 and loc == 1:
                    k = 3
                else:
                    k = loc
                tr.track_of[(t, loc)] = k
        if neck:
            tr.events = [(9, "split", [0], [2]), (10, "merge", [1, 2], [3]),
                         (11, "merge", [0, 3], [4])]  # fmt: skip
            tr.continues = {3: 1, 4: 0}
        else:
            tr.events = [(11, "merge", [0, 1], [2])]
            tr.continues = {2: 0}
        out[view] = tr
    return out


def test_a_neck_cut_off_between_fusing_lobes_is_one_merge_dated_as_without_it():
    """The segmenter cuts the neck between two fusing lobes off lobe A (frame 9); the
    piece joins lobe B (frame 10), which joins A (frame 11). That is one merge of A and
    B, dated as the same lobes without the piece are (frame 8: one frame before the
    lobes leave their steady approach, as in the test above), not two merges dated from
    the piece's first frame (9 and 10, or later)."""
    plain = _approaching_pair()
    labels = {c: lab.copy() for c, lab in plain.items()}
    for lab in labels.values():
        for t in (9, 10):
            ys, xs = np.nonzero(lab[t] >= 0)
            mid, col = int(round(ys.mean())), int(round(xs.mean()))
            band = np.zeros(lab.shape[1:], bool)
            band[mid - 1 : mid + 2, col - 1 : col + 2] = True  # the neck, 3 × 3 px
            lab[t][band & (lab[t] >= 0)] = 2 if t == 9 else 1
    n = labels["cam0"].shape[0]
    params = {**ASSOCIATE_DEFAULTS, "merge_lobe_s": 0.01}

    def merge_events(tracks, labs):
        rows = [
            (t, loc, loc, 0.0)
            for t in range(n)
            for loc in np.unique(labs["cam0"][t][labs["cam0"][t] >= 0])
        ]
        pairs = pd.DataFrame(rows, columns=["frame", "local_a", "local_b", "cost"])
        out = reconcile_merges(tracks, labs, pairs, "cam0", "cam1", params, fps=1000)
        return {c: [e for e in out[c].events if e[1] == "merge"] for c in out}, out

    reference, _ = merge_events(_neck_tracks(plain, neck=False), plain)
    assert reference["cam0"] == reference["cam1"] == [(8, "merge", [0, 1], [2])]
    got, out = merge_events(_neck_tracks(labels, neck=True), labels)
    for c in ("cam0", "cam1"):
        assert got[c] == [(8, "merge", [0, 1, 2, 3], [4])], got[c]
        # From the merge on, every instance is the merged bubble's, the piece's too.
        assert {k for (t, _), k in out[c].track_of.items() if t >= 8} == {4}
        assert {k for (t, _), k in out[c].track_of.items() if t < 8} == {0, 1}


def test_two_merges_in_a_row_without_a_neck_piece_stay_two():
    """Three bubbles: A and B merge (frame 4), then C joins the merged one (frame 6),
    with no piece split off: :func:`_join_neck_chains` leaves them two merges."""
    tr = Tracks(n=5)
    tr.events = [(4, "merge", [0, 1], [3]), (6, "merge", [3, 2], [4])]
    groups = {3: (4, {0, 1}), 4: (6, {3, 2})}
    assert _join_neck_chains(tr, groups, lobe=10) == groups
    # With B born as a piece split off C two frames earlier, they are one.
    tr.events.insert(0, (2, "split", [2], [1]))
    assert _join_neck_chains(tr, groups, lobe=10) == {4: (4, {0, 1, 2, 3})}
    # ... but not when the piece is older than the look-back.
    assert _join_neck_chains(tr, groups, lobe=3) == groups
