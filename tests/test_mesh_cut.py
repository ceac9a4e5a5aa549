"""Silhouettes the image border cuts, completed for the hull (surfphase.mesh.cut),
against the same spheres seen whole by an uncut view."""

from __future__ import annotations

import numpy as np
from test_mesh_hull import CENTRE, _rig, _sphere_labels

from surfphase.masks.anchors import outline_ellipse, visible_outline
from surfphase.masks.params import ANCHOR_DEFAULTS
from surfphase.mesh.cut import completed_view, cut_shapes

SPHERES = {3: (CENTRE + [-1.5e-3, 0, 0], 1e-3), 5: (CENTRE + [1.5e-3, 0.5e-3, 0], 0.6e-3)}


def _whole_ellipse(lab: np.ndarray, b: int):
    m = (lab == b).astype(np.float64)
    return outline_ellipse(visible_outline(m, lab, lab, b, ring_px=0)[0])


def _hull_volume(cams, labels, p, b: int) -> float:
    """Enclosed volume (m³) of bubble ``b``'s hull mesh from two views' labels."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame

    v, f, ids = hull_mesh_frame(cams, labels, p)
    mine = ids == b
    keep = mine[f].all(axis=1)
    return abs(signed_volume(v[mine], (np.cumsum(mine) - 1)[f[keep]]))


def _volume_ratios(cams, labels, p, b: int, grown_cam, grown, bare) -> tuple[float, float]:
    """Hull volumes of region ``b`` with view 0 the grown view, completed (``grown``) and
    not (``bare``), over the volume from the uncut views ``labels``."""

    def volume(cam0, lab0):
        return _hull_volume([cam0, cams[1]], [lab0, labels[1]], p, b)

    ref = volume(cams[0], labels[0])
    return volume(grown_cam, grown) / ref, volume(grown_cam, bare) / ref


def _cut_at(lab: np.ndarray, x0: int) -> np.ndarray:
    """``lab`` with its first ``x0`` columns cut off."""
    return np.ascontiguousarray(lab[:, x0:])


def test_a_cut_silhouette_gets_its_tracks_shape_or_a_circle():
    """Sphere 3 (30 px radius) with its left 30 % or 55 % cut off: with a frame where
    the view shows it whole, its shape is that one moved onto the visible outline, the
    whole silhouette's ellipse within 0.3 px (centre and semi-axes); without one, the
    circle fitted to its visible outline (within 0.5 px), or nothing with ``circles``
    off. A bubble not cut gets none; a piece in the corner whose outline is a straight
    line gets none."""
    cam = _rig()[0]
    whole = _sphere_labels(cam, SPHERES)
    e = _whole_ellipse(whole, 3)
    cols = np.flatnonzero((whole == 3).any(axis=0))
    rules = dict(ANCHOR_DEFAULTS)
    for frac in (0.3, 0.55):
        x0 = int(cols[0] + frac * len(cols))
        cut = _cut_at(whole, x0)
        before = np.roll(np.where(whole == 3, 3, -1), 40, axis=1)  # 40 px further right
        labels = np.stack([_cut_at(before, x0), cut])
        alone = cut[None]
        for got in (cut_shapes(labels, 1, rules), cut_shapes(alone, 0, rules, circles=True)):
            assert set(got) == {3}
            tol = 0.3 if got[3][2] != got[3][3] else 0.5
            np.testing.assert_allclose(got[3][0] + x0, e[0], atol=tol)
            np.testing.assert_allclose(got[3][1], e[1], atol=tol)
            np.testing.assert_allclose(sorted(got[3][2:4]), sorted(e[2:4]), atol=tol)
        assert cut_shapes(alone, 0, rules, circles=False) == {}
    corner = np.full((60, 80), -1, np.int32)
    vv, uu = np.mgrid[0:60, 0:80]
    corner[uu + vv < 12] = 4
    assert cut_shapes(corner[None], 0, rules, circles=True) == {}


def test_completed_hull_has_the_volume_of_the_whole_view():
    """Sphere 3 cut 35 % by view 0's right border: its hull mesh from the view completed
    by the circle fitted to its outline
    has the volume and centre of the mesh from the uncut view (within 3 % and 0.02 r),
    where the cut view's alone is 42 % short; sphere 5 (not cut) is unchanged."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    cams = _rig()
    labels = [_sphere_labels(c, SPHERES) for c in cams]
    p = mesh_params({"surface": "hull"})
    cols = np.flatnonzero((labels[0] == 3).any(axis=0))
    x1 = int(cols[-1] + 1 - 0.35 * len(cols))
    cut_cam = cams[0].cropped(0, 0, x1, cams[0].height)
    cut_lab = np.ascontiguousarray(labels[0][:, :x1])
    assert cut_shapes(cut_lab[None], 0, ANCHOR_DEFAULTS) == {}  # no whole frame, no circles
    shapes = cut_shapes(cut_lab[None], 0, ANCHOR_DEFAULTS, circles=True)
    grown_cam, grown = completed_view(cut_cam, cut_lab, shapes)
    m = (grown.shape[1] - cut_lab.shape[1]) // 2
    np.testing.assert_array_equal(grown[m:-m, m:-m], cut_lab)  # the frame itself kept
    assert (grown[:, -m:] == 3).any() and not (grown[:, :m] >= 0).any()

    def volumes(cam0, lab0):
        v, f, ids = hull_mesh_frame([cam0, cams[1]], [lab0, labels[1]], p)
        out = {}
        for b in (3, 5):
            mine = ids == b
            keep = mine[f].all(axis=1)
            vb, fb = v[mine], (np.cumsum(mine) - 1)[f[keep]]
            out[b] = (abs(signed_volume(vb, fb)), 0.5 * (vb.min(0) + vb.max(0)))
        return out

    ref, done, bare = (
        volumes(cams[0], labels[0]),
        volumes(grown_cam, grown),
        volumes(cut_cam, cut_lab),
    )
    assert abs(done[3][0] / ref[3][0] - 1) < 0.03, done[3][0] / ref[3][0]
    assert np.linalg.norm(done[3][1] - ref[3][1]) < 0.02 * 1e-3
    assert bare[3][0] / ref[3][0] < 0.7, bare[3][0] / ref[3][0]
    assert abs(done[5][0] / ref[5][0] - 1) < 1e-9


def test_a_cut_bubbles_open_core_is_its_own_in_the_completed_view():
    """Sphere 3 cut 35 % by view 0's right border, its mask a ring: a bright core of
    half its radius, which the border cuts open, is left out (no hole filling closes
    it). Completed by the circle on its outline, the core inside the frame is the
    bubble's again and the hull has the volume of the uncut view's within 3 % (the ring
    completed outside the frame only: 30 % short); sphere 5 and the background
    outside the circle are untouched."""
    from surfphase.mesh.stage import mesh_params

    cams = _rig()
    labels = [_sphere_labels(c, SPHERES) for c in cams]
    p = mesh_params({"surface": "hull"})
    rows, cols = (np.flatnonzero((labels[0] == 3).any(axis=k)) for k in (1, 0))
    x1 = int(cols[-1] + 1 - 0.35 * len(cols))
    cut_cam = cams[0].cropped(0, 0, x1, cams[0].height)
    ring = np.ascontiguousarray(labels[0][:, :x1])
    vv, uu = np.mgrid[0 : ring.shape[0], 0 : ring.shape[1]]
    cu, cv, r = 0.5 * (cols[0] + cols[-1]), 0.5 * (rows[0] + rows[-1]), 0.5 * len(cols)
    core = (ring == 3) & ((uu - cu) ** 2 + (vv - cv) ** 2 < (0.5 * r) ** 2)
    assert core[:, -1].any()  # open to the border
    ring[core] = -1
    shapes = cut_shapes(ring[None], 0, ANCHOR_DEFAULTS, circles=True)
    grown_cam, grown = completed_view(cut_cam, ring, shapes)
    m = (grown.shape[1] - ring.shape[1]) // 2
    inner = grown[m:-m, m:-m]
    assert (inner[core] == 3).all()
    assert (inner[~core] == ring[~core]).all()  # nothing else inside the frame changed
    bare = grown.copy()
    bare[m:-m, m:-m] = ring

    done, short = _volume_ratios(cams, labels, p, 3, grown_cam, grown, bare)
    assert abs(done - 1) < 0.03
    assert short < 0.8


def test_the_mesh_stage_grows_the_views_of_a_cut_frame_with_the_masks_rules(tmp_path):
    """``frame_views`` grows a view whose bubble the border cuts (and leaves the other
    as it is) with ``complete_cut``, and hands the labels over unchanged without it;
    the rules are the masks folder's ``masks.json`` ``anchors`` settings over the
    defaults (``min_visible_tracked`` above 1: no shapes)."""
    import json

    from surfphase.mesh.stage import _Session, frame_views, masks_anchor_rules, mesh_params

    cams = _rig()
    labels = [_sphere_labels(c, SPHERES) for c in cams]
    cols = np.flatnonzero((labels[0] == 3).any(axis=0))
    x1 = int(cols[-1] + 1 - 0.35 * len(cols))
    inputs = [cams[0].cropped(0, 0, x1, cams[0].height), cams[1]]
    stacks = [np.ascontiguousarray(labels[0][None, :, :x1]), labels[1][None]]
    (tmp_path / "masks.json").write_text(json.dumps({"params": {"anchors": {"ring_px": 2}}}))
    rules = masks_anchor_rules(tmp_path)
    assert rules["ring_px"] == 2 and rules["max_shape_rms"] == ANCHOR_DEFAULTS["max_shape_rms"]
    p = mesh_params({"surface": "hull"})
    s = _Session({}, inputs, "s", p, "cpu", "k", [0], stacks, None, rules)
    views, labs = frame_views(s, 0, [{}, {}])
    assert labs[0].shape[1] > x1 and (labs[0] == 3).sum() > (stacks[0][0] == 3).sum()
    assert views[0].width == labs[0].shape[1]
    assert np.array_equal(labs[1], stacks[1][0]) and views[1] is cams[1]  # not cut
    off = _Session({}, inputs, "s", p, "cpu", "k", [0], stacks, None, None)
    views, labs = frame_views(off, 0, [{}, {}])
    assert np.array_equal(labs[0], stacks[0][0]) and views[0] is inputs[0]
    never = _Session({}, inputs, "s", p, "cpu", "k", [0], stacks, None,
                     {**rules, "min_visible_tracked": 1.5})  # fmt: skip
    assert np.array_equal(frame_views(never, 0, [{}, {}])[1][0], stacks[0][0])


def test_a_bubble_mostly_outside_gets_the_circle_its_track_gave_it():
    """Sphere 3 (30 px radius) leaving the frame on the left, never whole: 60 % inside,
    then 20 % and 10 % (under ``min_visible_tracked``, 25 %). With
    ``tracked_circles`` the last two get a circle of the radius the first frame's fit
    gave it, placed on their visible outline: centre within 1 px of the whole
    silhouette's, radius within 0.5 px; without it, nothing."""
    cam = _rig()[0]
    whole = _sphere_labels(cam, SPHERES)
    e = _whole_ellipse(whole, 3)
    r_true = float(np.sqrt(e[2] * e[3]))
    cols = np.flatnonzero((whole == 3).any(axis=0))
    rules = dict(ANCHOR_DEFAULTS)
    # The same frame grid throughout: the bubble moves left by the cut it gets.
    stack = []
    for frac in (0.4, 0.8, 0.9):
        x0 = int(cols[0] + frac * len(cols))
        shifted = np.full_like(whole, -1)
        shifted[:, : whole.shape[1] - x0] = whole[:, x0:]
        shifted[shifted == 5] = -1
        stack.append(shifted)
    stack = np.stack(stack)
    shifts = [int(cols[0] + f * len(cols)) for f in (0.4, 0.8, 0.9)]
    for t in (1, 2):
        assert cut_shapes(stack, t, rules, circles=True) == {}
        got = cut_shapes(stack, t, rules, circles=True, tracked_circles=True)
        assert set(got) == {3}
        u, v, a, b, _ = got[3]
        assert abs(a - r_true) < 0.5 and a == b
        assert np.hypot(u - (e[0] - shifts[t]), v - e[1]) < 1.0, (u, v, e[0] - shifts[t], e[1])


def test_a_cut_bubble_without_a_shape_gets_the_image_of_its_sphere():
    """Sphere 3 with 80 % of its silhouette cut off by view 0's right border (too little
    for the tracked circle rules): the circle :func:`sphere_shapes` draws from the
    sphere (centre, radius) is its exact image (analytic: f·r / depth about the
    centre's projection, which here is beyond the border); it completes the hull to
    within 4 % of the uncut view's volume. A sphere 30 % too small for the visible part,
    or one already shaped, or a bubble not cut, gets none."""
    from surfphase.mesh.stage import mesh_params, sphere_shapes

    cams = _rig()
    labels = [_sphere_labels(c, SPHERES) for c in cams]
    cols = np.flatnonzero((labels[0] == 3).any(axis=0))
    x1 = int(cols[0] + 0.2 * len(cols))
    cut_cam = cams[0].cropped(0, 0, x1, cams[0].height)
    cut_lab = np.ascontiguousarray(labels[0][:, :x1])
    got = sphere_shapes(cut_cam, cut_lab, SPHERES, set())
    assert set(got) == {3}
    X, r = SPHERES[3]
    uv = cut_cam.project(X[None], distort=False)[0]
    rho = np.sqrt(cut_cam.K[0, 0] * cut_cam.K[1, 1]) * r / cut_cam.world_to_camera(X[None])[0, 2]
    np.testing.assert_allclose(got[3], (uv[0], uv[1], rho, rho, 0.0), rtol=1e-12)
    assert uv[0] > x1  # its centre beyond the border
    small = {3: (X, 0.7 * r)}
    assert sphere_shapes(cut_cam, cut_lab, small, set()) == {}
    assert sphere_shapes(cut_cam, cut_lab, SPHERES, {3}) == {}

    p = mesh_params({"surface": "hull"})
    grown_cam, grown = completed_view(cut_cam, cut_lab, got)

    def volume(cam0, lab0):
        return _hull_volume([cam0, cams[1]], [lab0, labels[1]], p, 3)

    ref = volume(cams[0], labels[0])
    assert abs(volume(grown_cam, grown) / ref - 1) < 0.04


def test_a_leaving_bubble_whose_sliver_the_labels_lost_gets_the_image_of_its_sphere():
    """Sphere 3 leaving view 0 on the left with a sliver of 2-3 pixel columns that the
    view's labels no longer hold (a continued centre, ``masks: anchors: continue_s``):
    :func:`sphere_shapes` draws its exact image all the same, which completes the hull
    to within 4 % of the uncut view's volume; once its circle is wholly outside the
    frame, none."""
    from surfphase.mesh.stage import mesh_params, sphere_shapes

    cams = _rig()
    labels = [_sphere_labels(c, SPHERES) for c in cams]
    X, r = SPHERES[3]
    cols = np.flatnonzero((labels[0] == 3).any(axis=0))
    x0 = int(cols[-1] - 2)  # the frame starts 2-3 columns before the silhouette's end
    cut_cam = cams[0].cropped(x0, 0, cams[0].width - x0, cams[0].height)
    cut_lab = np.ascontiguousarray(labels[0][:, x0:])
    cut_lab[cut_lab == 3] = -1  # the sliver lost
    got = sphere_shapes(cut_cam, cut_lab, {3: SPHERES[3]}, set())
    uv = cut_cam.project(X[None], distort=False)[0]
    rho = np.sqrt(cut_cam.K[0, 0] * cut_cam.K[1, 1]) * r / cut_cam.world_to_camera(X[None])[0, 2]
    np.testing.assert_allclose(got[3], (uv[0], uv[1], rho, rho, 0.0), rtol=1e-12)
    p = mesh_params({"surface": "hull"})
    grown_cam, grown = completed_view(cut_cam, cut_lab, got)
    ref = _hull_volume([cams[0], cams[1]], [labels[0], labels[1]], p, 3)
    assert abs(_hull_volume([grown_cam, cams[1]], [grown, labels[1]], p, 3) / ref - 1) < 0.04
    gone = cams[0].cropped(int(cols[-1] + 2), 0, 20, cams[0].height)
    assert sphere_shapes(gone, np.full((gone.height, 20), -1), {3: SPHERES[3]}, set()) == {}
    # Sphere 5's image ends 0.011 px inside a frame of its first 60 columns: no pixel
    # centre in it (its leftmost point is right of column 59, the last; the mask stage
    # saw it at a finer grid), yet it is drawn.
    from surfphase.masks.anchors import sphere_image

    edge = cams[0].cropped(0, 0, 60, cams[0].height)
    u, v, rho = sphere_image(edge, *SPHERES[5])
    assert 59.4 < u - rho < 59.5
    got = sphere_shapes(edge, np.full((edge.height, 60), -1), {5: SPHERES[5]}, set())
    np.testing.assert_allclose(got[5], (u, v, rho, rho, 0.0), rtol=1e-12)


def test_a_circle_meets_the_frame_where_it_overlaps_its_pixels_area():
    """:func:`circle_meets_frame` against brute force: 400 random circles around a
    7×5 image, each sampled on a 0.02 px grid of its disc for a point within the
    pixels' area (−0.5 to W − 0.5, H − 0.5); circles within 0.04 px of touching it
    are left out."""
    from surfphase.masks.anchors import circle_meets_frame

    rng = np.random.default_rng(3)
    h, w = 5, 7
    checked = 0
    for _ in range(400):
        u, v, rho = rng.uniform(-5, 11), rng.uniform(-5, 9), rng.uniform(0.2, 3)
        du = u - np.clip(u, -0.5, w - 0.5)
        dv = v - np.clip(v, -0.5, h - 0.5)
        if abs(np.hypot(du, dv) - rho) < 0.04:
            continue
        g = np.arange(-rho, rho + 1e-9, 0.02)
        x, y = np.meshgrid(u + g, v + g)
        disc = np.hypot(x - u, y - v) <= rho
        inside = (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
        assert circle_meets_frame(u, v, rho, (h, w)) == bool((disc & inside).any())
        checked += 1
    assert checked > 380


def test_an_oblate_bubble_cut_at_the_top_takes_its_sphere_before_a_fitted_circle():
    """An oblate silhouette (semi-axes 24 px across, 15 px up) with its top 40 % cut off
    by the frame and no whole shape in its track: the circle fitted to its visible
    (lower) arc is too large and centred above the bubble (the bottom's radius of
    curvature is a²/b), so the completed silhouette is over 1.5 times the ellipse's
    area (2.1 here); given the image of its sphere (the true centre, the equal-area
    radius √(ab)), that circle is taken, and the completed silhouette has the ellipse's
    area within 10 % (inside the frame it keeps the ellipse's wider visible part)."""
    a, b = 24.0, 15.0
    vv, uu = np.mgrid[0:80, 0:90]
    whole = np.where(((uu - 45.0) / a) ** 2 + ((vv - 30.0) / b) ** 2 <= 1, 2, -1)
    row0 = int(np.ceil(30.0 - b + 0.4 * 2 * b))  # the frame's top border
    lab = np.ascontiguousarray(whole[row0:]).astype(np.int32)
    uc, vc = 45.0, 30.0 - row0
    labels = lab[None]
    rules = dict(ANCHOR_DEFAULTS)
    r = float(np.sqrt(a * b))
    sphere = {2: (uc, vc, r, r, 0.0)}
    fitted = cut_shapes(labels, 0, rules, circles=True)
    taken = cut_shapes(labels, 0, rules, circles=True, spheres=sphere)
    assert taken == sphere
    assert fitted[2][2] > a and fitted[2][1] < vc - 1.0
    cam = _rig()[0].cropped(0, 0, lab.shape[1], lab.shape[0])
    for shape, lo, hi in ((fitted, 1.5, 9.0), (taken, 0.95, 1.10)):
        _, grown = completed_view(cam, lab, shape)
        assert lo < (grown == 2).sum() / (np.pi * a * b) < hi


def test_a_nucleation_piece_the_bottom_border_cuts_is_completed_by_its_circle():
    """Sphere 3 as a piece of the nucleation region (id 0, which has no track), cut 35 %
    by view 0's bottom border (a bubble on a plate just below the frame), its mask a
    ring whose bright core the border opens. Its circle, fitted to the outline of the
    piece filled as if the border closed it, completes it: the hull has the volume of
    the uncut view's within 3 % (without it: 30 % short), the core inside the frame is
    the piece's again, sphere 5 is untouched, and a piece the border does not cut gets
    no circle."""
    from surfphase.mesh.cut import nucleation_cut_shapes
    from surfphase.mesh.stage import mesh_params

    cams = _rig()
    labels = [np.where(lab == 3, 0, lab) for lab in (_sphere_labels(c, SPHERES) for c in cams)]
    p = mesh_params({"surface": "hull"})
    rows, cols = (np.flatnonzero((labels[0] == 0).any(axis=k)) for k in (1, 0))
    y1 = int(rows[-1] + 1 - 0.35 * len(rows))
    cut_cam = cams[0].cropped(0, 0, cams[0].width, y1)
    ring = labels[0][:y1].copy()
    vv, uu = np.mgrid[0 : ring.shape[0], 0 : ring.shape[1]]
    cu, cv, r = 0.5 * (cols[0] + cols[-1]), 0.5 * (rows[0] + rows[-1]), 0.5 * len(rows)
    core = (ring == 0) & ((uu - cu) ** 2 + (vv - cv) ** 2 < (0.5 * r) ** 2)
    assert core[-1].any()  # open to the border
    ring[core] = -1
    assert nucleation_cut_shapes(labels[1], ANCHOR_DEFAULTS) == []  # whole there
    pieces = nucleation_cut_shapes(ring, ANCHOR_DEFAULTS)
    assert len(pieces) == 1
    assert abs(pieces[0][2] / r - 1) < 0.05 and abs(pieces[0][1] - cv) < 1.0
    grown_cam, grown = completed_view(cut_cam, ring, {}, pieces)
    m = (grown.shape[1] - ring.shape[1]) // 2
    inner = grown[m:-m, m:-m]
    assert (inner[core] == 0).all()
    assert (inner[~core] == ring[~core]).all()
    assert (grown == 5).sum() == (ring == 5).sum()
    bare = grown.copy()
    bare[bare == 0] = -1
    bare[m:-m, m:-m] = ring

    done, short = _volume_ratios(cams, labels, p, 0, grown_cam, grown, bare)
    assert abs(done - 1) < 0.03
    assert short < 0.8
