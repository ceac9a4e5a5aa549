"""Small deterministic surfel scenes for the renderer's tests and benchmarks.

These are not the synthetic campaign's ground truth (that is :mod:`surfphase.synth`);
they are just plausible inputs: surfels tangent to a few millimetre-sized spheres seen
by cameras placed like the reference rig's inputs.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from surfphase.cameras import look_at
from surfphase.render.rasterize import camera_tensors


def sphere_scene(
    n_surfels: int,
    n_cameras: int = 2,
    size: int = 128,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> dict:
    """Surfels on three spheres (radii 1.5–2.5 mm) about 6 cm from the cameras.

    Cameras look at the scene centre from 35° steps in azimuth, focal length
    ``1800·size/512`` px (the synthetic rig's). Surfel standard deviations are about 0.6
    of the mean spacing on the spheres, so a covered pixel meets about 30 candidate
    surfels (front and back of a sphere), as a fitted scene does. Returns the keyword
    arguments of ``rasterize_surfels``.
    """
    g = torch.Generator().manual_seed(seed)
    centres = torch.tensor(
        [[0.0, 0.004, 0.0], [0.0045, 0.007, 0.001], [-0.004, 0.006, -0.002]], dtype=torch.float64
    )
    radii = torch.tensor([0.0025, 0.0018, 0.0015], dtype=torch.float64)
    area = 4 * math.pi * radii**2
    which = torch.multinomial(area / area.sum(), n_surfels, replacement=True, generator=g)
    d = torch.randn(n_surfels, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    means = centres[which] + radii[which, None] * d
    # Tangent frame from the sphere normal d: rotation with third column d, random spin.
    a = torch.randn(n_surfels, 3, generator=g, dtype=torch.float64)
    tu = a - (a * d).sum(1, keepdim=True) * d
    tu = tu / tu.norm(dim=1, keepdim=True)
    tv = torch.linalg.cross(d, tu)
    quats = _rotmat_to_quat(torch.stack([tu, tv, d], dim=-1))
    spacing = torch.sqrt(area.sum() / n_surfels)
    scales = spacing * (0.45 + 0.3 * torch.rand(n_surfels, 2, generator=g, dtype=torch.float64))
    opacities = 0.3 + 0.6 * torch.rand(n_surfels, generator=g, dtype=torch.float64)
    colors = 0.2 + 0.6 * torch.rand(n_surfels, 1, generator=g, dtype=torch.float64)
    target = [0.0, 0.0055, 0.0]
    cams = []
    for k in range(n_cameras):
        az = math.radians(35.0 * k)
        eye = [0.06 * math.sin(az), 0.008, 0.06 * math.cos(az)]
        cams.append(look_at(f"c{k}", eye, target, fx=1800.0 * size / 512, width=size, height=size))
    viewmats, Ks = camera_tensors(cams, device=device, dtype=dtype)
    conv = {"dtype": dtype, "device": device}
    return {
        "means": means.to(**conv),
        "quats": quats.to(**conv),
        "scales": scales.to(**conv),
        "opacities": opacities.to(**conv),
        "colors": colors.to(**conv),
        "viewmats": viewmats,
        "Ks": Ks,
        "width": size,
        "height": size,
        "backgrounds": torch.full((1,), 0.1, **conv),
    }


def _rotmat_to_quat(R: Tensor) -> Tensor:
    """(N, 3, 3) rotations → (N, 4) unit quaternions (w, x, y, z)."""
    m = R
    w = torch.sqrt(torch.clamp(1 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], min=0)) / 2
    x = torch.sqrt(torch.clamp(1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], min=0)) / 2
    y = torch.sqrt(torch.clamp(1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], min=0)) / 2
    z = torch.sqrt(torch.clamp(1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2], min=0)) / 2
    x = torch.copysign(x, m[:, 2, 1] - m[:, 1, 2])
    y = torch.copysign(y, m[:, 0, 2] - m[:, 2, 0])
    z = torch.copysign(z, m[:, 1, 0] - m[:, 0, 1])
    return torch.stack([w, x, y, z], dim=1)
