"""Meshes per frame: TSDF fusion of rendered surfel depth, marching cubes, cleanup, PLY.

The stage never imports the command line or Snakemake (DESIGN.md).
"""

from surfphase.mesh.fuse import fuse_depths, marching_cubes_mesh, render_depths, voxel_grid
from surfphase.mesh.ply import read_vertex_properties, speed_colors, write_mesh_ply
from surfphase.mesh.stage import run_mesh, vertex_velocities

__all__ = [
    "fuse_depths",
    "marching_cubes_mesh",
    "read_vertex_properties",
    "render_depths",
    "run_mesh",
    "speed_colors",
    "vertex_velocities",
    "voxel_grid",
    "write_mesh_ply",
]
