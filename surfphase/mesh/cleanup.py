"""Mesh cleanup with pymeshlab: drop tiny components, smooth lightly, close small holes.

Positions stay in metres: every threshold is given in absolute units or face counts.
"""

from __future__ import annotations

import numpy as np


def clean_mesh(
    verts: np.ndarray,
    faces: np.ndarray,
    min_diameter: float,
    smooth_steps: int = 5,
    max_hole_edges: int = 30,
) -> tuple[np.ndarray, np.ndarray]:
    """Clean a triangle mesh.

    Args:
        verts: (V, 3) metres. faces: (F, 3) vertex indices.
        min_diameter: connected components whose bounding-box diagonal is below this
            (metres) are removed (specks from stray surfels).
        smooth_steps: Taubin λ|μ smoothing steps (volume-preserving, so radii do not
            shrink); 0 skips.
        max_hole_edges: holes bounded by at most this many edges are closed; larger
            openings (e.g. where a bubble leaves the grid) stay open.

    Returns:
        (V', 3) float64 vertices (metres) and (F', 3) int64 faces.
    """
    import pymeshlab

    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces.astype(np.int32)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_connected_component_by_diameter(
        mincomponentdiag=pymeshlab.PureValue(float(min_diameter))
    )
    if ms.current_mesh().face_number() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    if smooth_steps > 0:
        ms.apply_coord_taubin_smoothing(stepsmoothnum=int(smooth_steps))
    if max_hole_edges > 0:
        try:
            ms.meshing_close_holes(maxholesize=int(max_hole_edges), selfintersection=False)
        except pymeshlab.PyMeshLabException:
            # Hole closing needs a 2-manifold mesh; a non-manifold one keeps its holes.
            pass
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)


def mesh_stats(faces: np.ndarray, n_verts: int) -> dict:
    """``components`` (connected by shared vertices) and ``watertight`` (every edge
    shared by exactly two faces) of a triangle mesh."""
    from surfphase.mesh.measure import is_closed, vertex_components

    if len(faces) == 0:
        return {"components": 0, "watertight": False}
    labels = vertex_components(faces, n_verts)
    components = len(np.unique(labels[np.unique(faces)]))
    return {"components": int(components), "watertight": is_closed(faces)}


def drop_fragments(
    verts: np.ndarray, faces: np.ndarray, min_frac: float
) -> tuple[np.ndarray, np.ndarray]:
    """One bubble's mesh without the pieces much smaller than its largest.

    A bubble is one body of vapour. Where two views meet at a small angle, the hull's
    end slices (a few pixels of silhouette chord) are placed in depth by strips whose
    pixel error that angle multiplies, and come out as slivers beside the bubble.

    Args:
        verts: (V, 3) metres. faces: (F, 3) vertex indices.
        min_frac: a connected component whose bounding-box diagonal is less than this
            fraction of the largest component's is dropped (0: keep all).

    Returns:
        (V', 3) vertices and (F', 3) faces of the kept components (unused vertices
        dropped, faces renumbered).
    """
    from surfphase.mesh.measure import vertex_components

    v = np.asarray(verts, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(f) == 0 or min_frac <= 0:
        return v, f
    comp = vertex_components(f, len(v))
    fc = comp[f[:, 0]]
    diag = {
        int(c): float(np.linalg.norm(np.ptp(v[np.unique(f[fc == c])], axis=0)))
        for c in np.unique(fc)
    }
    top = max(diag.values())
    keep_f = f[np.isin(fc, [c for c, d in diag.items() if d >= min_frac * top])]
    used = np.unique(keep_f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[keep_f]
