"""Binary PLY meshes with per-vertex velocity and a speed colour (MeshLab, ParaView)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from surfphase.io import atomic_path

VERTEX_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("vx", "<f4"),
        ("vy", "<f4"),
        ("vz", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
    ]
)
FACE_DTYPE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def speed_colors(speed: np.ndarray, vmax: float, cmap: str = "viridis") -> np.ndarray:
    """(V,) speeds (m/s) → (V, 3) uint8 RGB from ``cmap`` over [0, vmax] (clipped)."""
    from matplotlib import colormaps

    if vmax <= 0:
        raise ValueError(f"speed colour range must be positive, got {vmax}")
    rgba = colormaps[cmap](np.clip(np.asarray(speed, np.float64) / vmax, 0.0, 1.0))
    return np.round(np.asarray(rgba)[..., :3] * 255).astype(np.uint8).reshape(-1, 3)


def write_mesh_ply(
    path: str | os.PathLike,
    verts: np.ndarray,
    faces: np.ndarray,
    velocity: np.ndarray,
    colors: np.ndarray,
    comment: str = "units: metres, m/s",
) -> None:
    """Write a binary little-endian PLY, whole or not at all.

    Args:
        verts: (V, 3) positions, metres (stored float32 x y z).
        faces: (F, 3) vertex indices (stored as ``list uchar int vertex_indices``).
        velocity: (V, 3) m/s (stored float32 vx vy vz).
        colors: (V, 3) uint8 (stored red green blue).
    """
    V = len(verts)
    if velocity.shape != (V, 3) or colors.shape != (V, 3):
        raise ValueError("write_mesh_ply: velocity and colors must be (V, 3)")
    vert = np.empty(V, VERTEX_DTYPE)
    for k, name in enumerate("xyz"):
        vert[name] = verts[:, k]
        vert["v" + name] = velocity[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        vert[name] = colors[:, k]
    face = np.empty(len(faces), FACE_DTYPE)
    face["n"] = 3
    face["v"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment {comment}\n"
        f"element vertex {V}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float vx\nproperty float vy\nproperty float vz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def read_vertex_properties(path: str | os.PathLike) -> np.ndarray:
    """Read the vertex record array of a PLY written by :func:`write_mesh_ply`."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: mesh file not found")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    count = next(int(h.split()[2]) for h in header if h.startswith("element vertex"))
    start = end + len(b"end_header\n")
    return np.frombuffer(data, VERTEX_DTYPE, count=count, offset=start)
