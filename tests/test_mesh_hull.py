"""The elliptic hull (surfphase.mesh.hull) against analytic bodies seen by two views."""

from __future__ import annotations

import numpy as np
import pytest

from surfphase.cameras import look_at
from surfphase.mesh.hull import closest_widths, elliptic_hull_distance, slice_ellipse
from surfphase.mesh.stage import silhouette_distance

CENTRE = np.array([0.0, 0.004, 0.0])


def _rig(angle_deg: float = 40.0, elevation_deg: float = 6.0):
    """Two 240² views 0.1 m from ``CENTRE``, ``angle_deg`` apart, ``elevation_deg`` up."""
    cams = []
    for k, az in enumerate((-angle_deg / 2, angle_deg / 2)):
        a, e = np.radians(az), np.radians(elevation_deg)
        eye = CENTRE + 0.1 * np.array([np.sin(a) * np.cos(e), np.sin(e), -np.cos(a) * np.cos(e)])
        cams.append(look_at(f"cam{k}", eye, CENTRE, 3000.0, 240, 240))
    return cams


def _labels(cam, semi: np.ndarray, rot: np.ndarray, centre: np.ndarray = CENTRE) -> np.ndarray:
    """(H, W) labels: 3 where the pixel centre's ray meets the ellipsoid
    ``|diag(1/semi) rotᵀ (X − centre)| ≤ 1``, else −1."""
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    pix = np.stack([uu, vv, np.ones_like(uu)], -1).reshape(-1, 3)
    d = pix @ np.linalg.inv(cam.K).T @ cam.R  # world ray directions
    S = np.diag(1 / semi) @ rot.T
    o = S @ (cam.center - centre)
    dd = d @ S.T
    A, B, C = (dd**2).sum(1), 2 * dd @ o, o @ o - 1
    hit = B**2 - 4 * A * C >= 0
    return np.where(hit, 3, -1).reshape(cam.height, cam.width).astype(np.int32)


def _grid(semi: np.ndarray, voxel: float = 4e-5):
    origin = CENTRE - 1.6 * semi.max()
    n = int(np.ceil(3.2 * semi.max() / voxel)) + 1
    axes = [origin[i] + voxel * np.arange(n) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return origin, (n, n, n), voxel, P


@pytest.mark.parametrize(
    ("semi", "tilt_deg", "tol"),
    [
        (np.array([1e-3, 1e-3, 1e-3]), 0.0, 0.08),  # sphere (voxel and pixel rounding: +2 %)
        (np.array([1.2e-3, 0.8e-3, 1.2e-3]), 0.0, 0.08),  # oblate, vertical axis
        (np.array([1.2e-3, 0.8e-3, 1.2e-3]), 25.0, 0.12),  # tilted: slices are ellipses
    ],
)
def test_elliptic_hull_is_the_body_where_the_visual_hull_is_not(semi, tilt_deg, tol):
    """Volume of the elliptic hull (d ≤ 0 inside the visual hull) within ``tol`` of the
    body's 4/3 π abc, and its extent along the bisector within ``tol`` of the body's,
    where the two-view visual hull is ≥ 15 % too large and long."""
    t = np.radians(tilt_deg)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])
    cams = _rig()
    labels = [_labels(c, semi, rot) for c in cams]
    origin, shape, voxel, P = _grid(semi)
    hull = silhouette_distance(origin, shape, voxel, cams, [lab >= 0 for lab in labels]).ravel()
    ell = elliptic_hull_distance(origin, shape, voxel, cams, labels).ravel()
    inside_hull = hull <= 0
    inside = inside_hull & (ell <= 0)
    body = np.linalg.norm((np.diag(1 / semi) @ rot.T @ (P - CENTRE).T).T, axis=1) <= 1
    v_true = 4 / 3 * np.pi * semi.prod()
    v_hull, v_ell = inside_hull.sum() * voxel**3, inside.sum() * voxel**3
    assert abs(v_ell / v_true - 1) < tol, (v_ell / v_true, v_hull / v_true)
    assert v_hull / v_true > 1.15
    bis = np.array([0.0, 0.0, 1.0])  # the views' bisector (horizontal)
    ext = lambda m: np.ptp(P[m] @ bis)  # noqa: E731
    assert abs(ext(inside) / ext(body) - 1) < tol
    assert ext(inside_hull) / ext(body) > 1.15
    # Voxels no view labels are not constrained.
    assert np.isneginf(ell[~inside_hull & (np.abs(P[:, 1] - CENTRE[1]) > 1.5 * semi[1])]).all()


def test_slice_ellipse_is_the_circle_when_the_strips_are_equal():
    """Two strips of equal half-width r through one point: the circle of radius r; unequal
    ones give supports r_k in their directions (checked by the support function)."""
    a = np.array([[1.0, 0.0], [np.cos(1.0), np.sin(1.0)]])
    p0 = np.array([0.3, -0.2])
    p, M = slice_ellipse(a, a @ p0, np.array([0.5, 0.5]))
    assert np.allclose(p, p0) and np.allclose(M, 0.25 * np.eye(2))
    p, M = slice_ellipse(a, a @ p0, np.array([0.5, 0.7]))
    assert np.allclose([a[0] @ M @ a[0], a[1] @ M @ a[1]], [0.25, 0.49])
    assert np.all(np.linalg.eigvalsh(M) > 0)
    assert slice_ellipse(np.array([[1.0, 0.0], [1.0, 1e-6]]), np.zeros(2), np.ones(2)) is None


def test_closest_widths_are_equal_within_the_tolerance_else_moved_towards_each_other():
    """Overlapping intervals: one width, the mean clipped into the overlap; apart: each
    moved by its own tolerance (analytic)."""
    assert np.allclose(closest_widths(np.array([1.0, 1.2]), np.array([0.15, 0.15])), [1.1, 1.1])
    # overlap [1.1, 1.15]: the mean 1.1 is inside it
    assert np.allclose(closest_widths(np.array([1.0, 1.2]), np.array([0.15, 0.1])), [1.1, 1.1])
    # overlap [1.15, 1.25]: the mean 1.1 clipped to 1.15
    assert np.allclose(closest_widths(np.array([1.0, 1.2]), np.array([0.25, 0.05])), [1.15, 1.15])
    assert np.allclose(closest_widths(np.array([1.0, 1.5]), np.array([0.1, 0.2])), [1.1, 1.3])
    assert np.allclose(closest_widths(np.array([1.5, 1.0]), np.array([0.0, 0.0])), [1.5, 1.0])


def test_a_sphere_a_few_pixels_across_is_not_elongated_by_its_pixels():
    """A sphere of 0.4 mm, 3 px in radius in two views 25° apart, at 10 sub-pixel
    positions, one view's silhouette a pixel narrower on one side (two segmentations
    differ by that much): taking the strips' widths as exact, the elliptic hull comes
    out elongated along the views' bisector (spread, the standard deviation of its
    inside voxels, > 1.3 times that across); with each half-width known to half a
    pixel, less than half as much too long and within 15 % of the sphere's 1 (the
    visual hull still cuts the section on the narrower strip's side), and within 10 %
    with both silhouettes whole, as without the tolerance."""
    semi = np.full(3, 4e-4)
    cams = []
    for k, az in enumerate((-12.5, 12.5)):
        a, e = np.radians(az), np.radians(5.0)
        eye = CENTRE + 0.1 * np.array([np.sin(a) * np.cos(e), np.sin(e), -np.cos(a) * np.cos(e)])
        cams.append(look_at(f"cam{k}", eye, CENTRE, 750.0, 64, 64))
    rng = np.random.default_rng(0)
    ratios = {(narrow, tol): [] for narrow in (True, False) for tol in (0.0, 0.5)}
    voxel = 5e-5
    n = int(3.2e-3 / voxel) + 1
    for _ in range(10):
        c = CENTRE + rng.uniform(-1e-4, 1e-4, 3)
        origin = c - 1.6e-3
        axes = [origin[i] + voxel * np.arange(n) for i in range(3)]
        P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        whole = [_labels(cam, semi, np.eye(3), centre=c) for cam in cams]
        narrower = whole[1].copy()
        for row in narrower:
            cols = np.flatnonzero(row >= 0)
            row[cols[-1:]] = -1
        for narrow in (True, False):
            labels = [whole[0], narrower if narrow else whole[1]]
            hull = silhouette_distance(origin, (n, n, n), voxel, cams, [lb >= 0 for lb in labels])
            for tol in (0.0, 0.5):
                ell = elliptic_hull_distance(origin, (n, n, n), voxel, cams, labels, 4, tol)
                inside = (hull.ravel() <= 0) & (ell.ravel() <= 0)
                ratios[narrow, tol].append(np.std(P[inside, 2]) / np.std(P[inside, 0]))
    mean = {k: float(np.mean(v)) for k, v in ratios.items()}
    assert mean[True, 0.0] > 1.3, mean
    assert abs(mean[True, 0.5] - 1) < min(0.15, 0.5 * (mean[True, 0.0] - 1)), mean
    assert abs(mean[False, 0.5] - 1) < 0.10 and abs(mean[False, 0.0] - 1) < 0.10, mean


def test_ghosts_where_the_views_see_two_bubbles_are_carved():
    """Two spheres side by side: where one view's rays through sphere 3 cross the other
    view's through sphere 4, the visual hull holds a ghost; the elliptic hull carves it
    (+inf) and keeps both spheres."""
    cams = _rig()
    r = 6e-4
    offs = {3: np.array([-1.5e-3, 0.0, 0.0]), 4: np.array([1.5e-3, 0.0, 0.0])}
    labels = []
    for cam in cams:
        lab = np.full((cam.height, cam.width), -1, np.int32)
        vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
        for b, off in offs.items():
            uv = cam.project((CENTRE + off)[None], distort=False)[0]
            rp = r * cam.K[0, 0] / cam.world_to_camera((CENTRE + off)[None])[0, 2]
            lab[np.hypot(uu - uv[0], vv - uv[1]) <= rp] = b
        labels.append(lab)
    voxel = 5e-5
    origin = CENTRE - 4e-3
    n = int(8e-3 / voxel) + 1
    axes = [origin[i] + voxel * np.arange(n) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    hull = silhouette_distance(origin, (n, n, n), voxel, cams, [lab >= 0 for lab in labels])
    ell = elliptic_hull_distance(origin, (n, n, n), voxel, cams, labels).ravel()
    near = np.min([np.linalg.norm(P - (CENTRE + o), axis=1) for o in offs.values()], axis=0)
    seen = []
    for cam, lab in zip(cams, labels, strict=True):
        uv = np.round(cam.project(P, distort=False)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        seen.append(
            np.where(ok, lab[uv[:, 1].clip(0, cam.height - 1), uv[:, 0].clip(0, cam.width - 1)], -1)
        )
    ghost = (seen[0] >= 0) & (seen[1] >= 0) & (seen[0] != seen[1])
    assert ghost.sum() > 100 and (hull.ravel()[ghost] <= 0).all()  # the hull's ghosts ...
    assert near[ghost].min() > r and np.isposinf(ell[ghost]).all()  # ... are carved
    same = (seen[0] >= 0) & (seen[0] == seen[1])
    assert (ell[same & (near > 2 * r)] > 0).all()  # the hull's corners
    assert (ell[near < 0.7 * r] <= 0).all()  # both spheres' cores stay
    out = np.zeros(len(P), bool)
    for cam in cams:
        uv = np.round(cam.project(P, distort=False)).astype(int)
        out |= (uv[:, 0] < 0) | (uv[:, 0] >= cam.width) | (uv[:, 1] < 0) | (uv[:, 1] >= cam.height)
    assert out.any() and np.isposinf(ell[out]).all()  # outside a view's image: carved


def _sphere_labels(cam, spheres: dict[int, tuple[np.ndarray, float]]) -> np.ndarray:
    """(H, W) labels: the id of the sphere (centre m, radius m) whose surface the pixel
    centre's ray meets first, else −1."""
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    pix = np.stack([uu, vv, np.ones_like(uu)], -1).reshape(-1, 3)
    d = pix @ np.linalg.inv(cam.K).T @ cam.R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out, best = np.full(len(d), -1, np.int32), np.full(len(d), np.inf)
    for b, (c, r) in spheres.items():
        o = cam.center - c
        B, C = d @ o, o @ o - r**2
        disc = B**2 - C
        t = np.where(disc >= 0, -B - np.sqrt(np.maximum(disc, 0)), np.inf)
        near = t < best
        out[near], best[near] = b, t[near]
    return out.reshape(cam.height, cam.width)


@pytest.mark.parametrize(
    ("focal", "ratio_tol", "vol_tol"), [(3000.0, 0.05, 0.04), (800.0, 0.15, 0.08)]
)
def test_hull_meshes_are_the_bubbles_each_on_its_own_grid(focal, ratio_tol, vol_tol):
    """`mesh: surface: hull` on two spheres (radii 1 and 0.6 mm: 30 and 18 px in the
    images at focal 3000 px, 8 and 5 px at 800): each mesh is closed, carries its
    bubble's id; its volume is within ``vol_tol`` of 4/3 π r³ (+1 to +2 % at 3000 px;
    at 800 px the 5 px sphere's silhouettes are 2.6 % short of π r² in area, its mesh
    6.5 % short in volume),
    its centre within 10 % of r, its extent along the views' bisector over its extent
    across within ``ratio_tol`` of 1 (the visual hull's, cot 20° ≈ 2.7)."""
    from surfphase.cameras import look_at
    from surfphase.mesh.measure import is_closed, signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    spheres = {3: (CENTRE + [-1.5e-3, 0, 0], 1e-3), 5: (CENTRE + [1.5e-3, 0.5e-3, 0], 0.6e-3)}
    cams = []
    for k, az in enumerate((-20.0, 20.0)):
        a, e = np.radians(az), np.radians(6.0)
        eye = CENTRE + 0.1 * np.array([np.sin(a) * np.cos(e), np.sin(e), -np.cos(a) * np.cos(e)])
        cams.append(look_at(f"cam{k}", eye, CENTRE, focal, 240, 240))
    labels = [_sphere_labels(c, spheres) for c in cams]
    verts, faces, ids = hull_mesh_frame(cams, labels, mesh_params({"surface": "hull"}))
    assert set(np.unique(ids)) == {3, 5}
    for b, (c, r) in spheres.items():
        mine = ids == b
        keep = mine[faces].all(axis=1)
        assert keep.sum() == mine[faces].any(axis=1).sum()  # no face joins two bubbles
        remap = np.cumsum(mine) - 1
        v, f = verts[mine], remap[faces[keep]]
        assert is_closed(f)
        vol = abs(signed_volume(v, f))
        assert abs(vol / (4 / 3 * np.pi * r**3) - 1) < vol_tol, vol / (4 / 3 * np.pi * r**3)
        assert np.linalg.norm(0.5 * (v.min(0) + v.max(0)) - c) < 0.3 * r
        ratio = np.ptp(v[:, 2]) / np.ptp(v[:, 0])  # bisector z, across x
        assert abs(ratio - 1) < ratio_tol, ratio


def test_nucleation_frames_need_a_piece_both_views_agree_on():
    """A frame whose nucleation region (id 0) is an attached sphere both views see is a
    nucleation frame; one where each view shows only a speck of its own (that
    triangulate to nothing) is not, with the cameras, and is without them."""
    from surfphase.fit.outputs import nucleation_frames

    cams = _rig()
    sphere = {0: (CENTRE + [0.5e-3, 0, 0], 0.7e-3)}
    seen = [_sphere_labels(c, sphere) for c in cams]
    specks = [np.full((c.height, c.width), -1, np.int32) for c in cams]
    specks[0][200:210, 10:20] = 0
    specks[1][20:26, 200:206] = 0
    stacks = [np.stack([a, b]) for a, b in zip(seen, specks, strict=True)]
    frames = np.array([7, 8])
    assert nucleation_frames(stacks, frames, cams) == {7}
    assert nucleation_frames(stacks, frames) == {7, 8}


def test_hull_is_moved_to_the_reported_centre():
    """With ``centres`` a bubble's hull is moved so that its volume centroid is there
    (within 2 % of r: voxel against mesh centroid), its shape (volume) unchanged; a
    bubble without an entry stays where the hull puts it."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    spheres = {3: (CENTRE + [-1.5e-3, 0, 0], 1e-3), 5: (CENTRE + [1.5e-3, 0.5e-3, 0], 0.6e-3)}
    cams = _rig()
    labels = [_sphere_labels(c, spheres) for c in cams]
    p = mesh_params({"surface": "hull"})
    v0, f0, id0 = hull_mesh_frame(cams, labels, p)
    target = spheres[3][0] + np.array([0.0, 0.0, 0.3e-3])  # 0.3 r off in depth
    v1, f1, id1 = hull_mesh_frame(cams, labels, p, centres={3: target})

    def piece(v, f, ids, b):
        mine = ids == b
        keep = mine[f].all(axis=1)
        return v[mine], (np.cumsum(mine) - 1)[f[keep]]

    def centroid(v, f):
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        w = np.einsum("ij,ij->i", a, np.cross(b, c))
        return ((a + b + c) / 4 * w[:, None]).sum(axis=0) / w.sum()

    va, fa = piece(v1, f1, id1, 3)
    assert np.linalg.norm(centroid(va, fa) - target) < 0.02 * 1e-3
    vb, fb = piece(v0, f0, id0, 3)
    assert abs(signed_volume(va, fa) / signed_volume(vb, fb) - 1) < 0.02
    np.testing.assert_allclose(piece(v1, f1, id1, 5)[0], piece(v0, f0, id0, 5)[0])


def test_an_id_in_several_pieces_is_meshed_per_pair_the_views_agree_on():
    """The nucleation region (id 0) as two attached spheres plus, in one view only, a
    speck of the same id the other view does not see: one closed mesh per sphere, each
    its volume within 5 % and its centre within 10 % of r, and none at the speck
    (the region's whole silhouettes' centroids triangulate to no point of either)."""
    from surfphase.mesh.measure import is_closed, signed_volume, vertex_components
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    spheres = {0: (CENTRE + [-1.5e-3, 0, 0], 0.8e-3), 1: (CENTRE + [1.5e-3, 0.3e-3, 0], 0.6e-3)}
    cams = _rig()
    labels = [_sphere_labels(c, spheres) for c in cams]
    labels = [np.where(lab >= 0, 0, -1).astype(np.int32) for lab in labels]
    labels[1][200:212, 10:22] = 0  # a speck in one view only
    verts, faces, ids = hull_mesh_frame(cams, labels, mesh_params({"surface": "hull"}))
    assert set(np.unique(ids)) == {0}
    comp = vertex_components(faces, len(verts))
    assert len(np.unique(comp)) == 2
    for c, r in spheres.values():
        centres = [
            0.5 * (verts[comp == k].min(0) + verts[comp == k].max(0)) for k in np.unique(comp)
        ]
        k = int(np.argmin([np.linalg.norm(x - c) for x in centres]))
        assert np.linalg.norm(centres[k] - c) < 0.1 * r
        mine = comp == np.unique(comp)[k]
        keep = mine[faces].all(axis=1)
        f = (np.cumsum(mine) - 1)[faces[keep]]
        assert is_closed(f)
        vol = abs(signed_volume(verts[mine], f))
        assert abs(vol / (4 / 3 * np.pi * r**3) - 1) < 0.05, vol / (4 / 3 * np.pi * r**3)


def test_marching_cubes_puts_a_plateau_of_zeros_outside():
    """A ball of negative values inside a shell of exact zeros (a silhouette's grown
    distance is 0 one pixel out) meshes as the ball (radius within a voxel), not as
    sheets through the plateau."""
    from surfphase.mesh.fuse import marching_cubes_mesh

    voxel, n = 1e-4, 40
    origin = np.zeros(3)
    g = (np.arange(n) - n / 2) * voxel
    r = np.sqrt(sum(a**2 for a in np.meshgrid(g, g, g, indexing="ij")))
    sdf = (r - 8 * voxel).astype(np.float32)
    sdf[(r > 8 * voxel) & (r < 14 * voxel)] = 0.0
    verts, _ = marching_cubes_mesh(sdf, origin, voxel)
    rad = np.linalg.norm(verts - origin - n / 2 * voxel, axis=1)
    assert np.abs(rad - 8 * voxel).max() < voxel


def test_hull_vertices_take_their_own_bubbles_velocity():
    """A vertex gets the velocity of the nearest surfel of its own bubble, even when a
    surfel of another bubble is nearer; a bubble without surfels gets NaN (unknown)."""
    from surfphase.mesh.stage import bubble_vertex_velocities

    verts = np.array([[0.0, 0, 0], [1e-3, 0, 0], [5e-3, 0, 0]])
    vbub = np.array([1, 1, 2])
    means = np.array([[2e-3, 0, 0], [1.1e-3, 0, 0], [9e-3, 0, 0]])
    sbub = np.array([1, 3, 1])
    vel = np.array([[0.1, 0, 0], [0.9, 0, 0], [0.2, 0, 0]])
    out = bubble_vertex_velocities(verts, vbub, means, sbub, vel)
    np.testing.assert_array_equal(out[:2], [[0.1, 0, 0], [0.1, 0, 0]])
    assert np.isnan(out[2]).all()


def test_smoothed_centres_keep_a_straight_line_and_remove_zig_zag():
    """Centres on a straight line (a tilted body's sections) come back exactly; the same
    line with alternating ±steps comes back within a ninth of them inside (a 9-slice
    window averages an alternating error down to 1/9), within 26 % at the ends; with
    ``half_window`` 0 nothing changes."""
    from surfphase.mesh.hull import smooth_centres

    k = np.arange(20)
    line = np.stack([1e-3 + 2e-5 * k, 0.094 - 1e-5 * k], axis=1)
    w = np.full(len(k), 100.0)
    np.testing.assert_allclose(smooth_centres(k, line, w, 4), line, atol=1e-15)
    zig = line + np.where(k % 2 == 0, 2e-5, -2e-5)[:, None]
    out = smooth_centres(k, zig, w, 4)
    assert np.abs(out - line)[4:-4].max() < 2e-5 / 9 + 1e-12
    assert np.abs(out - line).max() < 0.26 * 2e-5
    assert np.array_equal(smooth_centres(k, zig, w, 0), zig)


def _two_spheres_rig(focal: float, supersample: int = 1):
    """Two views 40° apart, 6° up, 240² at ``focal`` px (× ``supersample`` in focal and
    size: the same images sampled finer), and two spheres (radii 1 and 0.6 mm)."""
    from surfphase.cameras import look_at

    spheres = {3: (CENTRE + [-1.5e-3, 0, 0], 1e-3), 5: (CENTRE + [1.5e-3, 0.5e-3, 0], 0.6e-3)}
    cams = []
    for k, az in enumerate((-20.0, 20.0)):
        a, e = np.radians(az), np.radians(6.0)
        eye = CENTRE + 0.1 * np.array([np.sin(a) * np.cos(e), np.sin(e), -np.cos(a) * np.cos(e)])
        n = 240 * supersample
        cams.append(look_at(f"cam{k}", eye, CENTRE, focal * supersample, n, n))
    return cams, spheres


def _bubble_mesh(verts, faces, ids, b):
    mine = ids == b
    keep = mine[faces].all(axis=1)
    return verts[mine], (np.cumsum(mine) - 1)[faces[keep]]


def test_projected_area_of_a_hull_mesh_is_its_silhouettes():
    """Half the summed areas of a closed convex mesh's projected triangles against its
    silhouette counted on pixels 8 times finer (rays against the analytic sphere, from
    which the hull was made): within 1 %."""
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params
    from surfphase.mesh.surfaces import projected_area

    cams, spheres = _two_spheres_rig(3000.0)
    fine, _ = _two_spheres_rig(3000.0, 8)
    labels = [_sphere_labels(c, spheres) for c in cams]
    verts, faces, ids = hull_mesh_frame(cams, labels, mesh_params({"surface": "hull"}))
    for b in spheres:
        v, f = _bubble_mesh(verts, faces, ids, b)
        for cam, fc in zip(cams, fine, strict=True):
            true = (_sphere_labels(fc, spheres) == b).sum() / 64.0
            assert abs(projected_area(cam, v, f) / true - 1) < 0.01


def test_small_bubbles_keep_their_volume_with_their_native_silhouettes():
    """At 350 px focal the spheres are 3.5 and 2.1 px in radius in the labels the hull
    is made from, and the smaller one's hull falls 11 % short in volume; given their
    silhouettes' areas at 8 times the resolution (``areas``, as the masks'
    native-resolution instances), each mesh is scaled to them and holds the sphere's
    volume within 6 % (the slices of a sphere a few pixels across stay a little short
    in depth), its centre kept."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    cams, spheres = _two_spheres_rig(350.0)
    fine, _ = _two_spheres_rig(350.0, 8)
    labels = [_sphere_labels(c, spheres) for c in cams]
    areas = {b: [(_sphere_labels(fc, spheres) == b).sum() / 64.0 for fc in fine] for b in spheres}
    p = mesh_params({"surface": "hull"})
    centres = {b: c for b, (c, _) in spheres.items()}
    plain = hull_mesh_frame(cams, labels, p, centres=centres)
    scaled = hull_mesh_frame(cams, labels, p, centres=centres, areas=areas)
    errs = {}
    for b, (_c, r) in spheres.items():
        true = 4 / 3 * np.pi * r**3
        v0, f0 = _bubble_mesh(*plain, b)
        v1, f1 = _bubble_mesh(*scaled, b)
        errs[b] = (abs(signed_volume(v0, f0)) / true - 1, abs(signed_volume(v1, f1)) / true - 1)
        assert abs(errs[b][1]) < 0.06, errs
        assert np.linalg.norm(v1.mean(0) - v0.mean(0)) < 0.1 * r
    assert min(e[0] for e in errs.values()) < -0.1, errs  # the cause


def test_small_pieces_of_the_nucleation_region_keep_their_volume_with_their_native_areas():
    """The same two spheres as pieces of the nucleation region (id 0), each view's
    pieces given as the masks' instances give them (centroid and area at 8 times the
    resolution, in the labels' pixels): each piece's hull is scaled to its own areas and
    holds its sphere's volume within 6 %; without them the smaller falls > 10 % short."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    cams, spheres = _two_spheres_rig(350.0)
    fine, _ = _two_spheres_rig(350.0, 8)
    labels = [np.where(_sphere_labels(c, spheres) >= 0, 0, -1) for c in cams]
    pieces = []
    for fc in fine:
        lab = _sphere_labels(fc, spheres)
        rows = []
        for b in spheres:
            vv, uu = np.nonzero(lab == b)
            rows.append(((uu.mean() + 0.5) / 8 - 0.5, (vv.mean() + 0.5) / 8 - 0.5, len(uu) / 64.0))
        pieces.append(np.array(rows))
    p = mesh_params({"surface": "hull"})
    out = {}
    for name, kw in (("plain", {}), ("scaled", {"pieces": pieces})):
        verts, faces, ids = hull_mesh_frame(cams, labels, p, **kw)
        assert set(np.unique(ids)) == {0}
        near = np.argmin(
            [np.linalg.norm(verts - c, axis=1) / r for c, r in spheres.values()], axis=0
        )
        for k, (b, (_c, r)) in enumerate(spheres.items()):
            v, f = _bubble_mesh(verts, faces, near, k)
            out[name, b] = abs(signed_volume(v, f)) / (4 / 3 * np.pi * r**3) - 1
    assert all(abs(out["scaled", b]) < 0.06 for b in spheres), out
    assert min(out["plain", b] for b in spheres) < -0.1, out  # the cause


def test_nucleation_areas_keep_whole_pieces_per_view():
    """From an ``instances.csv``: each view's whole pieces of id 0 (centroid, area);
    a piece the border cuts and the other ids are left out."""
    import pandas as pd

    from surfphase.mesh.stage import nucleation_areas

    cams, _ = _two_spheres_rig(3000.0)
    rows = [  # frame, camera, bubble, area, cx, cy, x0, y0, x1, y1
        (4, "cam0", 0, 30.0, 15.0, 200.5, 12, 197, 18, 204),
        (4, "cam0", 0, 12.0, 60.2, 230.0, 58, 228, 62, 239),  # cut by the bottom border
        (4, "cam0", 1, 100.0, 20.0, 20.0, 10, 10, 30, 30),
        (4, "cam1", 0, 33.0, 25.0, 201.0, 22, 198, 28, 204),
        (4, "cam1", 0, 8.0, 90.0, 210.0, 88, 208, 92, 212),
    ]
    cols = ["frame", "camera", "bubble", "area", "cx", "cy", "x0", "y0", "x1", "y1"]
    got = nucleation_areas(pd.DataFrame(rows, columns=cols), cams)
    assert list(got) == [4]
    assert np.allclose(got[4][0], [[15.0, 200.5, 30.0]])
    assert np.allclose(got[4][1], [[25.0, 201.0, 33.0], [90.0, 210.0, 8.0]])


def test_silhouette_areas_sum_pieces_and_leave_out_cut_and_half_seen_bubbles():
    """From an ``instances.csv``: an id's pieces in a view are summed; a bubble the
    border cuts in a view, one only one view shows, and the nucleation region (id 0)
    are left out."""
    import pandas as pd

    from surfphase.mesh.stage import silhouette_areas

    cams, _ = _two_spheres_rig(3000.0)
    rows = [  # frame, camera, bubble, area, x0, y0, x1, y1
        (4, "cam0", 1, 100.0, 10, 10, 20, 20),
        (4, "cam0", 1, 20.5, 21, 10, 24, 14),  # a second piece of bubble 1
        (4, "cam1", 1, 110.0, 30, 10, 40, 20),
        (4, "cam0", 2, 90.0, 0, 50, 9, 60),  # cut by cam0's left border
        (4, "cam1", 2, 95.0, 50, 50, 60, 60),
        (4, "cam0", 3, 80.0, 70, 70, 80, 80),  # cam1 does not show it
        (4, "cam0", 0, 300.0, 100, 200, 140, 239),
        (4, "cam1", 0, 310.0, 100, 200, 140, 239),
        (5, "cam0", 1, 101.0, 10, 12, 20, 22),
        (5, "cam1", 1, 112.0, 30, 12, 40, 22),
    ]
    cols = ["frame", "camera", "bubble", "area", "x0", "y0", "x1", "y1"]
    got = silhouette_areas(pd.DataFrame(rows, columns=cols), cams)
    assert got == {4: {1: [120.5, 110.0]}, 5: {1: [101.0, 112.0]}}


def _one_behind_another(back: int):
    """Two views 40° apart, 6° up, 240² at 1500 px, and two spheres (ids 3 and ``back``,
    1 and 0.8 mm) one behind the other for cam1 (3 mm apart along its line of sight,
    0.7 mm across), apart for cam0: the cameras, the spheres ``{id: ((3,) m, r m)}``,
    each view's labels, and cam1's (H, W) pixels of the back sphere's disc that the
    front one covers. cam1's labels show the back one as a crescent."""
    from surfphase.cameras import look_at

    cams = []
    for k, az in enumerate((-20.0, 20.0)):
        a, e = np.radians(az), np.radians(6.0)
        eye = CENTRE + 0.1 * np.array([np.sin(a) * np.cos(e), np.sin(e), -np.cos(a) * np.cos(e)])
        cams.append(look_at(f"cam{k}", eye, CENTRE, 1500.0, 240, 240))
    d = (CENTRE - cams[1].center) / np.linalg.norm(CENTRE - cams[1].center)
    side = np.cross(d, [0.0, 1.0, 0.0])
    back_c = CENTRE + 0.0015 * d + 0.0007 * side / np.linalg.norm(side)
    spheres = {3: (CENTRE - 0.0015 * d, 1e-3), back: (back_c, 0.8e-3)}
    labels = [_sphere_labels(c, spheres) for c in cams]
    assert 0 < (labels[1] == back).sum() < 0.7 * (labels[0] == back).sum()  # a crescent
    c, r = spheres[back]
    uv = cams[1].project(c[None], distort=False)[0]
    rho = r * 1500.0 / cams[1].world_to_camera(c[None])[0, 2]
    vv, uu = np.mgrid[0:240, 0:240]
    behind = (np.hypot(uu - uv[0], vv - uv[1]) <= rho) & (labels[1] == 3)
    return cams, spheres, labels, behind


def test_a_bubble_hidden_behind_another_in_one_view_is_meshed_whole():
    """Two spheres (1 and 0.8 mm) one behind the other for cam1 (3 mm apart along its
    line of sight, 0.7 mm across), apart for cam0: cam1's labels show the back one as a
    crescent. Meshed from those labels, the back sphere's hull is short; with the pixels
    its disc covers behind the front one added in cam1 (``hidden``), its volume is
    within 8 % of 4/3 π r³ and its bisector/across extent within 0.15 of 1."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    cams, spheres, labels, behind = _one_behind_another(5)
    r = spheres[5][1]
    p = mesh_params({"surface": "hull"})
    got = {}
    # The crescent's centroid is off the sphere's image: with hull_agreeing (default) a
    # bubble the fit does not report and whose views disagree is not meshed at all.
    assert 5 not in hull_mesh_frame(cams, labels, p)[2]
    loose = {**p, "hull_agreeing": False}
    for name, hidden, q in (("crescent", None, loose), ("whole", {5: [None, behind]}, p)):
        verts, faces, ids = hull_mesh_frame(cams, labels, q, hidden=hidden)
        v, f = _bubble_mesh(verts, faces, ids, 5)
        d_xz = np.ptp(v @ np.c_[[0, 0, 1], [1, 0, 0]], axis=0)  # bisector z, across x
        got[name] = (abs(signed_volume(v, f)) / (4 / 3 * np.pi * r**3), d_xz[0] / d_xz[1])
    vol, ratio = got["whole"]
    assert abs(vol - 1) < 0.08 and abs(ratio - 1) < 0.15, got
    assert got["crescent"][0] < 0.8, got


def test_an_id_the_two_views_give_to_different_things_is_not_meshed():
    """Labels of a sphere (id 2, 0.8 mm) seen by both views, and an id 7 that cam0's
    masks give to a thin strip (2 × 40 px) and cam1's to a speck (3 × 3 px), their
    centroids the images of one point 5 mm from the sphere: the two are no one object
    (sizes 3× apart there). The sphere is meshed within 8 % of its volume; id 7 gets no
    hull, unless ``hull_agreeing`` is off or the fit reports it, there (a ``centres``
    entry) or in another frame (``spared``)."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    cams = _rig(40.0, 6.0)
    r = 0.8e-3
    labels = [_sphere_labels(c, {2: (CENTRE, r)}) for c in cams]
    ghost = CENTRE + np.array([0.002, -0.001, 0.004])
    (u0, v0), (u1, v1) = (np.round(c.project(ghost[None], distort=False)[0]) for c in cams)
    labels[0][int(v0) : int(v0) + 2, int(u0) - 20 : int(u0) + 20] = 7
    labels[1][int(v1) - 1 : int(v1) + 2, int(u1) - 1 : int(u1) + 2] = 7
    p = mesh_params({"surface": "hull"})
    verts, faces, ids = hull_mesh_frame(cams, labels, p)
    assert set(np.unique(ids)) == {2}
    v, f = _bubble_mesh(verts, faces, ids, 2)
    assert abs(abs(signed_volume(v, f)) / (4 / 3 * np.pi * r**3) - 1) < 0.08
    loose = hull_mesh_frame(cams, labels, {**p, "hull_agreeing": False})[2]
    assert 7 in loose
    assert 7 in hull_mesh_frame(cams, labels, p, centres={7: ghost})[2]
    assert 7 in hull_mesh_frame(cams, labels, p, spared={2, 7})[2]


def test_spared_ids_are_the_reported_bubbles_and_those_cut_in_both_views():
    """``spared_ids``: every id ``bubbles.csv`` reports in any frame, and at this frame
    the ids whose silhouettes touch the image border in both input views (not one)."""
    from types import SimpleNamespace

    from surfphase.mesh.stage import spared_ids

    lab = np.full((2, 20, 30), -1, np.int32)
    lab[1, 0:3, 10:14] = 3  # the top border, view 0
    lab[1, 8:12, 0:2] = 4  # the left border, view 0
    other = np.full((2, 20, 30), -1, np.int32)
    other[1, 0:2, 5:9] = 3  # the top border, view 1
    other[1, 8:12, 10:14] = 4  # inside, view 1
    s = SimpleNamespace(centres={0: {5: np.zeros(3)}, 1: {6: np.zeros(3)}}, masks=[lab, other])
    assert spared_ids(s, 1) == {3, 5, 6}
    assert spared_ids(s, 0) == {5, 6}
    assert spared_ids(SimpleNamespace(centres=None, masks=[lab, other]), 1) == {3}


def test_an_attached_bubble_hidden_behind_a_free_one_in_one_view_is_meshed_whole():
    """The scene of the test above with the back sphere the nucleation region's (id 0,
    an attached bubble) and the front one a free bubble: cam1 shows a crescent of it.
    Meshed from those labels, its hull is short; with the free bubble's pixels that its
    disc covers added in cam1 (``hidden[0]``, the mask stage's attached circle), its
    volume is within 8 % of 4/3 π r³. Hidden pixels that do not touch the piece are not
    its own."""
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    cams, spheres, labels, behind = _one_behind_another(0)
    r = spheres[0][1]
    stray = np.zeros_like(behind)
    stray[5:9, 5:9] = True  # far from the piece
    p = mesh_params({"surface": "hull"})
    vols = {}
    for name, hidden in (("crescent", None), ("whole", {0: [None, behind]}),
                         ("stray", {0: [None, behind | stray]}), ("only stray", {0: [None, stray]})):  # fmt: skip
        verts, faces, ids = hull_mesh_frame(cams, labels, p, hidden=hidden)
        v, f = _bubble_mesh(verts, faces, ids, 0)
        vols[name] = abs(signed_volume(v, f)) / (4 / 3 * np.pi * r**3)
    assert vols["crescent"] < 0.8, vols
    assert abs(vols["whole"] - 1) < 0.08, vols
    assert vols["stray"] == vols["whole"] and vols["only stray"] == vols["crescent"], vols


def test_an_attached_bubble_one_view_fuses_with_its_neighbour_is_meshed_too():
    """Two attached spheres (id 0, radii 0.8 and 0.6 mm, 40° apart views at 800 px):
    cam0 sees them apart, cam1 the smaller one behind the larger, its side showing beside
    it, one fused piece. The views agree on the larger with the fused piece; the
    smaller, left over, is placed where its sphere's image explains what of the fused
    piece the larger's does not: both meshed, each centre within 0.3 r (the larger's
    pair triangulates the fused piece's centroid: 0.23 r; the smaller 0.07 r) and
    volume within 10 % (4 % and 1 %) of the truth's, each view's pieces given with
    their native areas and the fused view's, shared, left out of either's scaling.
    Before, the smaller had no mesh."""
    from scipy import ndimage as ndi

    from surfphase.masks.anchors import agreeing_pieces
    from surfphase.mesh.hull import hidden_pieces
    from surfphase.mesh.measure import signed_volume
    from surfphase.mesh.stage import hull_mesh_frame, mesh_params

    def rig(ss: int) -> list:
        out = []
        for k, az in enumerate((-20.0, 20.0)):
            a, e = np.radians(az), np.radians(6.0)
            d = np.array([np.sin(a) * np.cos(e), np.sin(e), -np.cos(a) * np.cos(e)])
            out.append(look_at(f"cam{k}", CENTRE + 0.1 * d, CENTRE, 800.0 * ss, 240 * ss, 240 * ss))
        return out

    cams = rig(1)
    front = np.array([0.0, 0.7e-3, 0.0])  # both sit on the plate (y = 0)
    ray = front - cams[1].center
    ray /= np.linalg.norm(ray)
    side = np.cross(ray, [0.0, 1.0, 0.0])
    back = front + 3.0e-3 * ray + 0.7e-3 * side / np.linalg.norm(side)
    back[1] = 0.55e-3
    spheres = {1: (front, 0.8e-3), 2: (back, 0.6e-3)}
    labels = [_sphere_labels(c, spheres) for c in cams]
    assert len(np.unique(ndi.label(labels[0] >= 0)[0])) == 3  # apart in cam0
    assert len(np.unique(ndi.label(labels[1] >= 0)[0])) == 2  # fused in cam1
    assert (labels[1] == 2).sum() > 4  # the smaller shows beside the larger
    pieces = []
    for fine in rig(8):
        lab = _sphere_labels(fine, spheres)
        comp, n = ndi.label(lab >= 0)
        rows = []
        for k in range(1, n + 1):
            vv, uu = np.nonzero(comp == k)
            rows.append(((uu.mean() + 0.5) / 8 - 0.5, (vv.mean() + 0.5) / 8 - 0.5, len(uu) / 64.0))
        pieces.append(np.array(rows))
    labs0 = [np.where(lab >= 0, 0, -1).astype(np.int32) for lab in labels]
    und = [c.undistorted() for c in cams]
    pairs = agreeing_pieces(und, labs0[0], labs0[1], 0)
    assert len(pairs) == 1 and np.linalg.norm(pairs[0][0] - front) < 0.4e-3  # fused centroid
    found = hidden_pieces(und, labs0[0], labs0[1], 0, pairs)
    assert len(found) == 1 and found[0][4] == 1
    verts, faces, ids = hull_mesh_frame(
        cams, labs0, mesh_params({"surface": "hull"}), pieces=pieces
    )
    assert set(np.unique(ids)) == {0}
    near = np.argmin([np.linalg.norm(verts - c, axis=1) / r for c, r in spheres.values()], axis=0)
    for k, (c, r) in enumerate(spheres.values()):
        v, f = _bubble_mesh(verts, faces, near, k)
        assert len(f), k
        assert np.linalg.norm(0.5 * (v.min(0) + v.max(0)) - c) < 0.3 * r
        assert abs(abs(signed_volume(v, f)) / (4 / 3 * np.pi * r**3) - 1) < 0.1
