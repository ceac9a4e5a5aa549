"""Chamfer distance between a reconstructed surface and the true one.

Both surfaces are triangle meshes in metres; each is sampled with ``n`` points spread
uniformly over its area (seeded), and the symmetric Chamfer distance is the average of
the two directed mean nearest-neighbour distances,

    CD = ½·(mean_{a∈A} min_{b∈B} |a − b| + mean_{b∈B} min_{a∈A} |a − b|),

reported in millimetres; the same with squared distances (mm²) is reported beside it.

With input ``cameras``, both sample sets are first restricted to the volume every input
camera sees (:func:`in_all_views`): a bubble that has left the videos' frames, or has
not yet entered them, is in the true mesh but cannot be reconstructed, and is left out.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from surfphase.cameras import Camera

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh from a PLY file (ASCII or binary).

    Returns ``(verts, faces)``: (V, 3) float64 vertex positions (file units, metres here)
    and (F, 3) int64 vertex indices. Polygons with more than three corners are fanned
    into triangles.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: mesh file not found")
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[dict] = []
    for line in header[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append({"name": tok[1], "count": int(tok[2]), "props": []})
        elif tok[0] == "property":
            if tok[1] == "list":
                elements[-1]["props"].append(
                    (tok[4], "list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]])
                )
            else:
                elements[-1]["props"].append((tok[2], _PLY_TYPES[tok[1]], None, None))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    verts = np.zeros((0, 3))
    faces = np.zeros((0, 3), dtype=np.int64)
    if fmt == "ascii":
        tokens = data[body_start:].split()
        pos = 0
        for el in elements:
            if any(p[1] == "list" for p in el["props"]):
                polys = []
                for _ in range(el["count"]):
                    row = []
                    for _name, kind, _ct, _it in el["props"]:
                        if kind == "list":
                            n = int(tokens[pos])
                            row.append([int(x) for x in tokens[pos + 1 : pos + 1 + n]])
                            pos += 1 + n
                        else:
                            pos += 1
                    polys.append(row[0])
                if el["name"] == "face":
                    faces = _triangulate_polys(polys)
            else:
                k = len(el["props"])
                vals = np.array(tokens[pos : pos + k * el["count"]], dtype=np.float64)
                pos += k * el["count"]
                if el["name"] == "vertex":
                    names = [p[0] for p in el["props"]]
                    table = vals.reshape(el["count"], k)
                    verts = table[:, [names.index(c) for c in "xyz"]]
        return verts, faces
    bo = "<" if fmt == "binary_little_endian" else ">"
    pos = body_start
    for el in elements:
        if not any(p[1] == "list" for p in el["props"]):
            dt = np.dtype([(p[0], bo + p[1]) for p in el["props"]])
            rec = np.frombuffer(data, dtype=dt, count=el["count"], offset=pos)
            pos += dt.itemsize * el["count"]
            if el["name"] == "vertex":
                verts = np.stack([rec[c].astype(np.float64) for c in "xyz"], axis=1)
            continue
        if len(el["props"]) != 1:
            raise ValueError(
                f"{path}: binary PLY element {el['name']!r}: only one list property is supported"
            )
        _, _, ct, it = el["props"][0]
        ctype, itype = np.dtype(bo + ct), np.dtype(bo + it)
        polys = []
        if el["count"]:
            n0 = int(np.frombuffer(data, dtype=ctype, count=1, offset=pos)[0])
            dt = np.dtype([("n", ctype), ("i", itype, (n0,))])
            rec = np.frombuffer(data, dtype=dt, count=el["count"], offset=pos)
            if np.all(rec["n"] == n0):
                pos += dt.itemsize * el["count"]
                polys_arr = rec["i"].astype(np.int64)
                if el["name"] == "face":
                    faces = _triangulate_polys(polys_arr)
                continue
            for _ in range(el["count"]):
                n = int(np.frombuffer(data, dtype=ctype, count=1, offset=pos)[0])
                pos += ctype.itemsize
                polys.append(np.frombuffer(data, dtype=itype, count=n, offset=pos).tolist())
                pos += itype.itemsize * n
        if el["name"] == "face":
            faces = _triangulate_polys(polys)
    return verts, faces


def _triangulate_polys(polys) -> np.ndarray:
    """Polygons (lists of vertex indices) → (F, 3) int64 triangles (fan)."""
    if isinstance(polys, np.ndarray) and polys.ndim == 2 and polys.shape[1] == 3:
        return polys.astype(np.int64)
    tris = [(p[0], p[k], p[k + 1]) for p in polys for k in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def sample_surface(verts: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniform over the area of a triangle mesh (units of ``verts``).

    Triangles are drawn with probability proportional to their area, then a point is
    drawn uniformly inside each drawn triangle (square-root barycentric sampling).
    """
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if faces.size == 0 or n <= 0:
        raise ValueError("sample_surface: the mesh has no triangles or n ≤ 0")
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = area.sum()
    if not total > 0:
        raise ValueError("sample_surface: the mesh has zero area")
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(faces), size=n, p=area / total)
    r1 = np.sqrt(rng.random(n))[:, None]
    r2 = rng.random(n)[:, None]
    return (1 - r1) * a[tri] + r1 * (1 - r2) * b[tri] + r1 * r2 * c[tri]


def chamfer(points_a: np.ndarray, points_b: np.ndarray) -> dict:
    """Symmetric Chamfer distance between two point sets given in metres.

    Returns millimetres: ``mean_mm`` (½ of the sum of the two directed mean distances),
    ``mean_sq_mm2`` (the same with squared distances, mm²), and the directed means
    ``a_to_b_mm`` and ``b_to_a_mm``.
    """
    A = np.asarray(points_a, dtype=np.float64).reshape(-1, 3)
    B = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    if len(A) == 0 or len(B) == 0:
        raise ValueError("chamfer: empty point set")
    d_ab = cKDTree(B).query(A)[0] * 1e3
    d_ba = cKDTree(A).query(B)[0] * 1e3
    return {
        "mean_mm": float(0.5 * (d_ab.mean() + d_ba.mean())),
        "mean_sq_mm2": float(0.5 * ((d_ab**2).mean() + (d_ba**2).mean())),
        "a_to_b_mm": float(d_ab.mean()),
        "b_to_a_mm": float(d_ba.mean()),
    }


def in_all_views(points: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """(N,) bool: which of the (N, 3) world points (m) lie in front of every camera and
    project inside its image (raw pixels, distortion included; the image spans
    −0.5 … W − 0.5 by the pixel-centre convention). Occlusion is not considered."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.ones(len(P), dtype=bool)
    for cam in cameras:
        front = cam.world_to_camera(P)[:, 2] > 0
        uv = np.full((len(P), 2), np.nan)
        if front.any():
            uv[front] = cam.project(P[front])
        with np.errstate(invalid="ignore"):
            inside = (
                (uv[:, 0] >= -0.5)
                & (uv[:, 0] <= cam.width - 0.5)
                & (uv[:, 1] >= -0.5)
                & (uv[:, 1] <= cam.height - 0.5)
            )
        keep &= front & inside
    return keep


def mesh_chamfer(
    pred_ply: str | os.PathLike,
    true_ply: str | os.PathLike,
    n: int = 20000,
    seed: int = 0,
    cameras: Sequence[Camera] | None = None,
) -> dict:
    """:func:`chamfer` of ``n`` area-uniform samples of each mesh (PLY files, metres).

    With ``cameras``, only the samples :func:`in_all_views` are compared (``points_pred``
    and ``points_true`` say how many; ``whole_truth_mean_mm`` is ``mean_mm`` of all the
    samples, as without cameras); if either set is then empty, every distance is NaN
    (nothing to compare in that frame). A mesh without faces (a frame where nothing was
    reconstructed) gives NaN distances too, with its ``points_*`` 0."""
    vp, fp = read_ply(pred_ply)
    vt, ft = read_ply(true_ply)
    if len(fp) == 0 or len(ft) == 0:
        nan = float("nan")
        out = {"mean_mm": nan, "mean_sq_mm2": nan, "a_to_b_mm": nan, "b_to_a_mm": nan}
        if cameras is None:
            return out
        return {**out, "points_pred": 0 if len(fp) == 0 else n,
                "points_true": 0 if len(ft) == 0 else n, "whole_truth_mean_mm": nan}  # fmt: skip
    a, b = sample_surface(vp, fp, n, seed), sample_surface(vt, ft, n, seed + 1)
    if cameras is None:
        return chamfer(a, b)
    whole = chamfer(a, b)["mean_mm"]
    a, b = a[in_all_views(a, cameras)], b[in_all_views(b, cameras)]
    counts = {"points_pred": int(len(a)), "points_true": int(len(b)), "whole_truth_mean_mm": whole}
    if len(a) == 0 or len(b) == 0:
        nan = float("nan")
        return {"mean_mm": nan, "mean_sq_mm2": nan, "a_to_b_mm": nan, "b_to_a_mm": nan, **counts}
    return {**chamfer(a, b), **counts}
