"""The depth bound of the fit (``fit: depth_bound``): two views leave a bubble's extent
along their bisector unseen, so after every step a surfel farther than ``k·r`` along that
axis from its bubble's centre is put back at ``k·r``.

Centres and radii come from the frame's masks (triangulated centroids, or the mask
stage's sub-pixel anchors; the largest equivalent radius over the views); a surfel
belongs to the nearest bubble by distance / r; the nucleation region is left free.
Units: metres, lab frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch

from surfphase.cameras import Camera
from surfphase.fit import init


@dataclass
class DepthBounds:
    """Bubble spheres of one frame and the poorly seen axis (``depth_bound``)."""

    centres: torch.Tensor  # (B, 3) metres
    limits: torch.Tensor  # (B,) metres: k·r, inf for the nucleation region
    radii: torch.Tensor  # (B,) metres
    axis: torch.Tensor  # (3,) unit vector

    def apply(self, means: torch.Tensor) -> None:
        """Move (N, 3) ``means`` (metres, in place) back within the limits along the axis."""
        c, lim, r, u = (t.to(means) for t in (self.centres, self.limits, self.radii, self.axis))
        near = (torch.cdist(means, c) / r).argmin(dim=1)
        d = (means - c[near]) @ u
        excess = (d.abs() - lim[near]).clamp_min(0.0)
        means.sub_((excess * torch.sign(d))[:, None] * u)


def depth_bounds(
    cameras: Sequence[Camera],
    labels: Sequence[np.ndarray],
    k: float | None,
    centres: dict[int, np.ndarray] | None = None,
) -> DepthBounds | None:
    """The ``depth_bound`` of one frame's masks (see ``DEFAULTS``), or None when off or
    no bubble is seen in two views. ``centres`` (m, by bubble id), where given, replace
    the triangulated centroids of the frame's binary masks (the mask stage's sub-pixel
    anchors)."""
    if k is None:
        return None
    spheres = init.bubble_spheres(cameras, labels, radius="max")
    if not spheres:
        return None
    for b, c in (centres or {}).items():
        if b in spheres:
            spheres[b] = (np.asarray(c, dtype=np.float64), *spheres[b][1:])
    ids = sorted(spheres)
    axis = np.mean([c.view_dir for c in cameras], axis=0)
    axis /= np.linalg.norm(axis)
    radii = np.array([spheres[b][1] for b in ids])
    limits = np.where(np.array(ids) >= 1, float(k) * radii, np.inf)
    as_t = partial(torch.as_tensor, dtype=torch.float64)
    return DepthBounds(
        as_t(np.stack([spheres[b][0] for b in ids])), as_t(limits), as_t(radii), as_t(axis)
    )
