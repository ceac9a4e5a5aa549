"""Meshes per frame: TSDF fusion of rendered surfel depth, marching cubes, cleanup, PLY.

The stage never imports the command line or Snakemake (docs/method.md §1.1). Names are imported
on first use, so that the workflow can read :mod:`surfphase.mesh.windows` while it
builds the DAG without importing torch.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "fuse_depths": "fuse",
    "marching_cubes_mesh": "fuse",
    "render_depths": "fuse",
    "voxel_grid": "fuse",
    "read_vertex_properties": "ply",
    "speed_colors": "ply",
    "write_mesh_ply": "ply",
    "gather_mesh": "stage",
    "run_mesh": "stage",
    "run_mesh_window": "stage",
    "vertex_velocities": "stage",
    "sheet_frame_count": "windows",
    "window_count": "windows",
    "window_positions": "windows",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
