"""The reference rig of the synthetic campaign: true cameras in the lab frame.

Lab frame (docs/conventions.md §1): +y up, heated plate at y = 0, x horizontal in cam0's image
(cam0 sits on the +z axis looking towards −z, so image-right is lab +x).

Cameras (native resolution ``native``, e.g. 512×512):

* ``cam0``, ``cam1``: the two input cameras, ``baseline_deg`` (35°) apart in azimuth
  about the vertical axis through the scene centre, slightly above it, looking down at it;
* ``mid``: a held-out camera half-way between them;
* ``orbit01``…``orbit11``: the method's orbit views, 30° steps from cam0 towards cam1.

Only cam0 and cam1 carry lens distortion (they are the ones a lab calibrates).

Geometry: 30 mm working distance, fx = 900 px at 512 px (a 32° field of view, a macro
lens): one native pixel is ≈ 33 µm at the scene centre, a 2 mm bubble ≈ 60 px natively
and ≈ 15 px at the 128×128 fit size. A narrower field of view makes the principal point
ill-conditioned for a planar-board calibration (it trades off against the rotation).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from surfphase.cameras import Camera, look_at, orbit_cameras

#: Scene centre in metres (lab frame): above the plate, where bubbles rise.
SCENE_CENTER = np.array([0.0, 0.006, 0.0])


def default_rig(
    native: int = 512,
    distance: float = 0.03,
    height: float = 0.008,
    fx: float = 900.0,
    baseline_deg: float = 35.0,
    orbit_views: int = 11,
    orbit_step_deg: float = 30.0,
    dist0: tuple[float, ...] = (-0.12, 0.08, 0.0005, -0.0003, 0.0),
    dist1: tuple[float, ...] = (-0.10, 0.06, -0.0004, 0.0002, 0.0),
    native_height: int | None = None,
) -> dict[str, Camera]:
    """True cameras of the synthetic rig, ``{name: Camera}``, metres and pixels.

    ``native`` is the image width (and height, unless ``native_height`` is given), in
    pixels. ``fx`` is given for a width of 512 and scaled with it (the horizontal field
    of view is kept); principal points are offset a few pixels from the image centre,
    as real sensors are. ``height`` is cam0's eye height above the plate (m); the
    cameras look at :data:`SCENE_CENTER`, so their elevation is
    ``atan((height − SCENE_CENTER[1]) / distance)`` (:func:`eye_height`).
    """
    s = native / 512.0
    native_h = native if native_height is None else int(native_height)
    eye0 = SCENE_CENTER + np.array([0.0, height - SCENE_CENTER[1], distance])
    base = look_at(
        "cam0",
        eye0,
        SCENE_CENTER,
        fx=fx * s,
        fy=fx * s * 1.002,
        width=native,
        height=native_h,
        cx=(native - 1) / 2 + 3.2 * s,
        cy=(native_h - 1) / 2 - 2.1 * s,
        role="input",
    )
    cam0 = replace(base, dist=np.asarray(dist0, dtype=np.float64))
    (c1,) = orbit_cameras(base, SCENE_CENTER, n_views=1, step_deg=baseline_deg)
    K1 = base.K.copy()
    K1[0, 0] *= 1.004
    K1[1, 1] *= 1.004
    K1[0, 2] -= 2.4 * s
    K1[1, 2] += 1.7 * s
    cam1 = replace(c1, name="cam1", K=K1, dist=np.asarray(dist1, dtype=np.float64), role="input")
    (mid,) = orbit_cameras(base, SCENE_CENTER, n_views=1, step_deg=baseline_deg / 2)
    mid = replace(mid, name="mid", role="heldout")
    orbit = orbit_cameras(base, SCENE_CENTER, n_views=orbit_views, step_deg=orbit_step_deg)
    cams = [cam0, cam1, mid, *orbit]
    return {c.name: c for c in cams}


def eye_height(elevation_deg: float, distance: float = 0.03) -> float:
    """Eye height above the plate (m) of a camera at ``distance`` (m, horizontal) from
    :data:`SCENE_CENTER` that looks at it from ``elevation_deg`` above the horizontal."""
    return float(SCENE_CENTER[1] + distance * np.tan(np.deg2rad(elevation_deg)))
