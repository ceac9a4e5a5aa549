"""Differentiable 2D Gaussian surfel renderer: surfels and cameras in, images out.

The renderer knows nothing of bubbles, SDF values or fits (docs/method.md §1.1).
"""

from surfphase.render.composite import over_background
from surfphase.render.rasterize import camera_tensors, depth_normals, rasterize_surfels

__all__ = ["camera_tensors", "depth_normals", "over_background", "rasterize_surfels"]
