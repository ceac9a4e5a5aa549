"""VTK XML meshes for ParaView: PolyData (``.vtp``) with velocity, and a ``.pvd`` series.

VTK's PLY reader (which ParaView uses) drops the PLY's extra vertex properties, so the
mesh stage also writes each frame as a VTK XML PolyData file, written here without VTK:

* ``<frame:06d>.vtp`` — ``VTKFile type="PolyData"`` version 1.0, little-endian, raw
  binary appended data with UInt64 block headers. Points: Float32 x y z, metres, lab
  frame. Polys: triangles (Int64 ``connectivity`` and ``offsets``). Point data:
  ``velocity`` (Float32, 3 components, m/s) and ``speed`` (Float32, m/s, the norm of
  the velocity). Field data: ``frame`` (Int64, the session frame index) and
  ``TimeValue`` (Float64, seconds).
* ``<name>.pvd`` — ``VTKFile type="Collection"``: one ``DataSet`` per frame with
  ``timestep`` (seconds, 17 significant digits) and ``file`` (relative to the .pvd), so
  ParaView opens the session as one time series.
"""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from surfphase.io import atomic_path

VTP_VERSION = "1.0"


def _block(a: np.ndarray) -> bytes:
    """One appended-data block: UInt64 byte count, then the raw little-endian bytes."""
    raw = np.ascontiguousarray(a).tobytes()
    return np.uint64(len(raw)).astype("<u8").tobytes() + raw


def _array_xml(name: str, vtk_type: str, count: str, offset: int) -> str:
    """A DataArray element; ``count`` is its NumberOfComponents/NumberOfTuples attribute."""
    return (
        f'<DataArray type="{vtk_type}" Name={quoteattr(name)} {count} '
        f'format="appended" offset="{offset}"/>'
    )


def write_polydata(
    path: str | os.PathLike,
    verts: np.ndarray,
    faces: np.ndarray,
    velocity: np.ndarray,
    frame: int,
    time_s: float,
) -> None:
    """Write one frame's triangle mesh as a VTK XML PolyData file, whole or not at all.

    Args:
        verts: (V, 3) positions, metres (stored Float32).
        faces: (F, 3) vertex indices (stored Int64 connectivity, offsets 3, 6, ...).
        velocity: (V, 3) m/s (point array ``velocity``, Float32; ``speed`` its norm).
        frame: session frame index (field data ``frame``).
        time_s: the frame's time, seconds (field data ``TimeValue``).
    """
    verts = np.asarray(verts, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    velocity = np.asarray(velocity, np.float64).reshape(-1, 3)
    V, F = len(verts), len(faces)
    if velocity.shape != (V, 3):
        raise ValueError(f"{path}: velocity is {velocity.shape}, need ({V}, 3)")
    if F and (faces.min() < 0 or faces.max() >= V):
        raise ValueError(f"{path}: face indices outside 0..{V - 1}")
    one, three, tuple1 = 'NumberOfComponents="1"', 'NumberOfComponents="3"', 'NumberOfTuples="1"'
    blocks = [
        ("Points", "Float32", three, verts.astype("<f4")),
        ("connectivity", "Int64", one, faces.astype("<i8").ravel()),
        ("offsets", "Int64", one, (3 * np.arange(1, F + 1)).astype("<i8")),
        ("velocity", "Float32", three, velocity.astype("<f4")),
        ("speed", "Float32", one, np.linalg.norm(velocity, axis=1).astype("<f4")),
        ("frame", "Int64", tuple1, np.array([frame], "<i8")),
        ("TimeValue", "Float64", tuple1, np.array([time_s], "<f8")),
    ]
    data, xml, offset = [], {}, 0
    for name, vtk_type, comp, arr in blocks:
        b = _block(arr)
        xml[name] = _array_xml(name, vtk_type, comp, offset)
        data.append(b)
        offset += len(b)
    head = (
        '<?xml version="1.0"?>\n'
        f'<VTKFile type="PolyData" version="{VTP_VERSION}" byte_order="LittleEndian" '
        'header_type="UInt64">\n'
        "<PolyData>\n"
        f"<FieldData>{xml['frame']}{xml['TimeValue']}</FieldData>\n"
        f'<Piece NumberOfPoints="{V}" NumberOfVerts="0" NumberOfLines="0" '
        f'NumberOfStrips="0" NumberOfPolys="{F}">\n'
        f'<PointData Scalars="speed" Vectors="velocity">{xml["velocity"]}{xml["speed"]}'
        "</PointData>\n"
        f"<Points>{xml['Points']}</Points>\n"
        f"<Polys>{xml['connectivity']}{xml['offsets']}</Polys>\n"
        "</Piece>\n"
        "</PolyData>\n"
        '<AppendedData encoding="raw">\n_'
    )
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(head.encode("ascii"))
        for b in data:
            fh.write(b)
        fh.write(b"\n</AppendedData>\n</VTKFile>\n")


def write_pvd(path: str | os.PathLike, entries: list[tuple[float, str]]) -> None:
    """Write a ParaView collection (``.pvd``) of ``(time_s, file)`` entries, whole or not
    at all; ``file`` is relative to the .pvd's folder (forward slashes)."""
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "<Collection>",
    ]
    for t, f in entries:
        if not np.isfinite(t):
            raise ValueError(f"{path}: time {t!r} of {f} is not finite")
        lines.append(
            f'<DataSet timestep="{float(t):.17g}" group="" part="0" file={quoteattr(str(f))}/>'
        )
    lines += ["</Collection>", "</VTKFile>", ""]
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines), encoding="ascii")
