"""Per-bubble volume and equivalent diameter against pymeshlab's own volume and the
analytic spheres they approximate."""

from __future__ import annotations

import numpy as np
import pymeshlab
import pytest
from skimage.measure import marching_cubes

from surfphase.mesh.measure import bubble_sizes, signed_volume, vertex_bubbles

CENTRES = np.array([[0.0, 0.0, 0.0], [3e-3, 0.0, 0.0]])  # m
RADII = np.array([1.0e-3, 0.6e-3])


def _two_spheres():
    """One marching-cubes mesh of two balls 3 mm apart (metres, outward faces)."""
    h = 4e-5
    xs = np.arange(-1.3e-3, 3.8e-3, h)
    ys = np.arange(-1.3e-3, 1.3e-3, h)
    x, y, z = np.meshgrid(xs, ys, ys, indexing="ij")
    d = np.minimum(
        *(np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r
          for c, r in zip(CENTRES, RADII, strict=True))
    )  # fmt: skip
    verts, faces, _, _ = marching_cubes(d, 0.0, spacing=(h, h, h))
    return verts + np.array([xs[0], ys[0], ys[0]]), faces[:, ::-1].copy()


def test_volumes_match_pymeshlab_and_the_analytic_spheres():
    verts, faces = _two_spheres()
    vb = vertex_bubbles(verts, CENTRES, np.array([4, 7]))  # nearest "surfel": a centre
    sizes = bubble_sizes(verts, faces, vb)
    assert [s["bubble"] for s in sizes] == [4, 7] and all(s["closed"] for s in sizes)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(verts, faces))
    total = ms.get_geometric_measures()["mesh_volume"]
    assert sum(s["volume_m3"] for s in sizes) == pytest.approx(abs(total), rel=1e-6)
    assert abs(signed_volume(verts, faces)) == pytest.approx(abs(total), rel=1e-6)
    for s, r in zip(sizes, RADII, strict=True):
        assert s["d_eq_m"] == pytest.approx(2 * r, rel=0.02)


def test_unbound_and_nucleation_components_are_not_reported():
    verts, faces = _two_spheres()
    assert bubble_sizes(verts, faces, np.where(verts[:, 0] < 1.5e-3, 0, -1)) == []
    assert bubble_sizes(np.zeros((0, 3)), np.zeros((0, 3), int), np.zeros(0, int)) == []


@pytest.mark.parametrize("frac", [0.3, 0.7])
def test_drop_fragments_keeps_what_pymeshlab_keeps_at_that_diameter(frac):
    """Balls of 1 and 0.6 mm radius (bounding-box diagonals 2√3 and 1.2√3 mm): at 0.3
    of the largest's diagonal both stay, at 0.7 the small one goes, as pymeshlab's
    removal of components below that diameter gives (the reference)."""
    from surfphase.mesh.cleanup import drop_fragments

    verts, faces = _two_spheres()
    v, f = drop_fragments(verts, faces, frac)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(verts, faces))
    diag = float(np.linalg.norm(np.ptp(verts[verts[:, 0] < 1.5e-3], axis=0)))
    ms.meshing_remove_connected_component_by_diameter(
        mincomponentdiag=pymeshlab.PureValue(frac * diag)
    )
    ms.meshing_remove_unreferenced_vertices()
    ref = ms.current_mesh()
    assert len(f) == ref.face_number() and len(v) == ref.vertex_number()
    assert abs(signed_volume(v, f)) == pytest.approx(
        abs(ms.get_geometric_measures()["mesh_volume"]), rel=1e-9
    )
    assert len(f) == (len(faces) if frac < 0.6 else int((verts[faces[:, 0], 0] < 1.5e-3).sum()))
    assert np.array_equal(drop_fragments(verts, faces, 0.0)[1], faces)
