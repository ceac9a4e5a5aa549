"""Mesh snapshots for the report: a frame's mesh drawn from the front and the side,
coloured by the speed of its surface.

The meshes are the mesh stage's PLY files (``<frame:06d>.ply``: vertex ``x y z`` in
metres, lab frame, and ``vx vy vz`` in m/s). Each view is an orthographic projection:
``front`` looks along −z (as camera 0 does: x to the right, y up), ``side`` along −x
(−z to the right, y up). Triangles are filled in back-to-front order (painter's
algorithm) with the colour of their mean vertex speed on a colour map over
[0, ``speed_max``] m/s (the mesh stage's ``speed_max``, so the colours match the PLY's
own), optionally shaded by how squarely they face the viewer.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from surfphase.eval.geometry import read_ply
from surfphase.io import atomic_path

#: (screen-right axis, screen-up axis, towards-the-viewer axis) of each view, as
#: (world axis index, sign) pairs.
VIEWS = {
    "front": ((0, 1.0), (1, 1.0), (2, 1.0)),
    "side": ((2, -1.0), (1, 1.0), (0, 1.0)),
}
SPEED_CMAP = "viridis"
DEFAULT_SPEED_MAX = 0.4  # m/s, as the mesh stage's default


def mesh_speeds(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(verts (V, 3) m, faces (F, 3), speed (V,) m/s)`` of a mesh-stage PLY."""
    from surfphase.mesh.ply import read_vertex_properties

    verts, faces = read_ply(path)
    props = read_vertex_properties(path)
    names = props.dtype.names or ()
    if not {"vx", "vy", "vz"} <= set(names):
        raise ValueError(f"{path}: the mesh has no per-vertex velocity (vx, vy, vz)")
    vel = np.stack([props[c].astype(np.float64) for c in ("vx", "vy", "vz")], axis=1)
    return verts, faces, np.linalg.norm(vel, axis=1)


def project_view(verts: np.ndarray, view: str) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) metres → (V, 2) screen coordinates in mm and (V,) depth towards the viewer
    (larger = nearer) for an orthographic ``view`` (:data:`VIEWS`)."""
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r} (known: {sorted(VIEWS)})")
    (a, sa), (b, sb), (c, sc) = VIEWS[view]
    v = np.asarray(verts, dtype=np.float64)
    return np.stack([sa * v[:, a], sb * v[:, b]], axis=1) * 1e3, sc * v[:, c]


def face_colors(
    verts: np.ndarray,
    faces: np.ndarray,
    speed: np.ndarray,
    speed_max: float,
    view: str,
    shade: bool = True,
) -> np.ndarray:
    """(F, 3) RGB in [0, 1]: the colour map at each face's mean vertex speed / speed_max
    (clipped to [0, 1]), times ``0.45 + 0.55·|n·d|`` with ``shade`` (n the face normal,
    d the view direction)."""
    from matplotlib import colormaps

    if not speed_max > 0:
        raise ValueError(f"speed colour range must be positive, got {speed_max}")
    s = np.asarray(speed, dtype=np.float64)[faces].mean(axis=1)
    rgb = np.asarray(colormaps[SPEED_CMAP](np.clip(s / speed_max, 0.0, 1.0)))[:, :3]
    if shade:
        a, b, c = (verts[faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        axis, sign = VIEWS[view][2]
        rgb = rgb * (0.45 + 0.55 * np.abs(sign * n[:, axis]))[:, None]
    return rgb


def mesh_snapshot(
    ply: str | os.PathLike,
    out_png: str | os.PathLike,
    speed_max: float = DEFAULT_SPEED_MAX,
    title: str = "",
    views: Sequence[str] = ("front", "side"),
    shade: bool = True,
    colorbar: bool = True,
    dpi: int = 100,
) -> dict:
    """Draw one mesh from each of ``views`` side by side, coloured by speed; write a PNG.

    Returns ``{"faces": F, "vertices": V, "max_speed_mps": …, "panels": {view: (col0,
    row0, col1, row1)}}``, the panels' pixel boxes in the PNG.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import Normalize

    verts, faces, speed = mesh_speeds(ply)
    if len(faces) == 0:
        raise ValueError(f"{ply}: the mesh has no faces")
    fig, axes = plt.subplots(1, len(views), figsize=(4.0 * len(views) + 0.8, 4.2), squeeze=False)
    axes = axes[0]
    lo = hi = None
    for ax, view in zip(axes, views, strict=True):
        xy, depth = project_view(verts, view)
        order = np.argsort(depth[faces].mean(axis=1), kind="stable")  # far first
        rgb = face_colors(verts, faces, speed, speed_max, view, shade)[order]
        polys = PolyCollection(
            xy[faces[order]], facecolors=rgb, edgecolors=rgb, linewidths=0.3, antialiased=False
        )
        ax.add_collection(polys)
        span_lo, span_hi = xy.min(axis=0), xy.max(axis=0)
        lo = span_lo if lo is None else np.minimum(lo, span_lo)
        hi = span_hi if hi is None else np.maximum(hi, span_hi)
        ax.set_title(view)
        ax.set_aspect("equal")
        ax.set_xlabel({"front": "x (mm)", "side": "−z (mm)"}[view])
        ax.set_ylabel("y (mm)")
    pad = 0.05 * float(np.max(hi - lo)) + 1e-3
    for ax, view in zip(axes, views, strict=True):
        xy, _ = project_view(verts, view)
        ax.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    if colorbar:
        sm = ScalarMappable(norm=Normalize(0.0, speed_max), cmap=SPEED_CMAP)
        fig.colorbar(sm, ax=list(axes), label="speed (m/s)", shrink=0.8)
    if title:
        fig.suptitle(title)
    fig.canvas.draw()
    height = fig.canvas.get_width_height()[1] * dpi / fig.dpi
    panels = {}
    for ax, view in zip(axes, views, strict=True):
        x0, y0, x1, y1 = ax.get_window_extent().extents * dpi / fig.dpi
        panels[view] = (int(np.ceil(x0)), int(np.ceil(height - y1)), int(x1), int(height - y0))
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return {
        "faces": int(len(faces)),
        "vertices": int(len(verts)),
        "max_speed_mps": float(speed.max()) if speed.size else 0.0,
        "panels": panels,
    }


def mesh_snapshots(
    mesh_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    count: int = 4,
    speed_max: float | None = None,
    session: str = "",
) -> list[Path]:
    """Snapshots of ``count`` meshes of ``mesh_dir`` (evenly spread over the frames with a
    non-empty mesh, by name) as ``out_dir/<frame:06d>.png`` (the folder is emptied of PNGs first).

    ``speed_max`` (m/s) defaults to the one in ``mesh_dir/mesh.json``, else
    :data:`DEFAULT_SPEED_MAX`; returns the PNGs written.
    """
    mesh_dir, out_dir = Path(mesh_dir), Path(out_dir)
    if not mesh_dir.is_dir():
        raise FileNotFoundError(f"{mesh_dir}: session {session}: mesh folder not found")
    plys = sorted(p for p in mesh_dir.glob("*.ply") if p.stem.isdigit())
    # Frames where nothing was reconstructed have an empty mesh: nothing to draw.
    plys = [p for p in plys if len(read_ply(p)[1])]
    if speed_max is None:
        speed_max = DEFAULT_SPEED_MAX
        info = mesh_dir / "mesh.json"
        if info.is_file():
            try:
                value = json.loads(info.read_text()).get("speed_max")
            except ValueError as e:
                raise ValueError(f"{info}: session {session}: not valid JSON ({e})") from e
            if isinstance(value, int | float) and value > 0:
                speed_max = float(value)
    if count > 0 and len(plys) > count:
        pick = np.unique(np.linspace(0, len(plys) - 1, count).round().astype(int))
        plys = [plys[i] for i in pick]
    elif count <= 0:
        plys = []
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("*.png"):
        old.unlink()
    written = []
    for p in plys:
        frame = int(p.stem)
        title = f"{session} frame {frame}".strip() + f" — speed colour 0–{speed_max:g} m/s"
        png = out_dir / f"{p.stem}.png"
        mesh_snapshot(p, png, speed_max, title=title)
        written.append(png)
    return written
