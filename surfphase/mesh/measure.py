"""Per-bubble size from a frame's mesh: volume and equivalent diameter.

A frame's mesh holds every bubble. Each connected component belongs to the bubble that
most of its vertices' nearest surfels are bound to; a bubble's volume is the sum of its
components' enclosed volumes (divergence theorem), and its equivalent diameter
``d_eq = (6 V / π)^(1/3)``. Units: metres, m³.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def vertex_components(faces: np.ndarray, n_verts: int) -> np.ndarray:
    """(V,) connected-component label of each vertex (vertices joined by triangle edges)."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_verts, n_verts))
    return connected_components(g, directed=False)[1]


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume (units³) of a closed triangle mesh, positive for outward faces."""
    a, b, c = (np.asarray(verts, dtype=np.float64)[np.asarray(faces)[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def is_closed(faces: np.ndarray) -> bool:
    """Every edge shared by exactly two triangles."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return False
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return bool(np.all(np.unique(e, axis=0, return_counts=True)[1] == 2))


def vertex_bubbles(verts: np.ndarray, surfel_means: np.ndarray, surfel_bubble: np.ndarray):
    """(V,) bubble id of each vertex: that of its nearest surfel ((N, 3) m, (N,) ids)."""
    if len(verts) == 0 or len(surfel_means) == 0:
        return np.full(len(verts), -1, dtype=np.int64)
    _, idx = cKDTree(surfel_means).query(verts)
    return np.asarray(surfel_bubble, dtype=np.int64)[idx]


def bubble_sizes(verts: np.ndarray, faces: np.ndarray, vertex_bubble: np.ndarray) -> list[dict]:
    """Per bubble id ≥ 1: ``volume_m3``, ``d_eq_m``, ``components`` and ``closed``.

    ``verts`` (V, 3) m, ``faces`` (F, 3), ``vertex_bubble`` (V,) ids (−1 unbound, 0 the
    nucleation region, which the plate cuts open: not reported). A component whose
    vertices are mostly unbound belongs to no bubble. ``closed`` is False when a
    component is open (cut by the plate or the image), where the volume is only a bound.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return []
    comp = vertex_components(faces, len(verts))
    face_comp = comp[faces[:, 0]]
    vb = np.asarray(vertex_bubble, dtype=np.int64)
    out: dict[int, dict] = {}
    for c in np.unique(face_comp):
        ids, counts = np.unique(vb[comp == c], return_counts=True)
        owner = int(ids[np.argmax(counts)])
        if owner < 1:
            continue
        f = faces[face_comp == c]
        d = out.setdefault(owner, {"bubble": owner, "volume_m3": 0.0, "components": 0,
                                   "closed": True})  # fmt: skip
        d["volume_m3"] += abs(signed_volume(verts, f))
        d["components"] += 1
        d["closed"] = d["closed"] and is_closed(f)
    for d in out.values():
        d["d_eq_m"] = float((6.0 * d["volume_m3"] / np.pi) ** (1.0 / 3.0))
    return [out[b] for b in sorted(out)]
