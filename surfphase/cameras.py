"""Pinhole cameras with OpenCV distortion, and the ``cameras.json`` format.

Conventions (docs/conventions.md):

* world points in metres, lab frame: +y up (against gravity), heated plate at y = 0;
* ``x_cam = R @ x_world + t``; the camera looks along its +z, +x right, +y down;
* pixel ``(u, v)``: origin at the *centre* of the top-left pixel (OpenCV's convention),
  ``u`` to the right, ``v`` down;
* distortion: OpenCV's ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``.

``cameras.json`` holds ``{"units": "m", "cameras": {name: camera_dict}}`` where
``camera_dict`` has ``width``, ``height`` (pixels), ``K`` (3×3), ``dist`` (list),
``R`` (3×3), ``t`` (3,) and an optional free-form ``role`` (``input``, ``heldout``,
``orbit``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from surfphase.io import atomic_write_text


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole camera.

    Attributes:
        name: camera id, e.g. ``"cam0"``.
        width, height: image size in pixels.
        K: (3, 3) intrinsics in pixels.
        dist: (N,) OpenCV distortion coefficients, N in {0, 4, 5, 8}.
        R: (3, 3) world-to-camera rotation.
        t: (3,) world-to-camera translation in metres.
        role: free-form tag (``input``, ``heldout``, ``orbit``...).
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    role: str = "input"
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, metres."""
        return -self.R.T @ self.t

    @property
    def view_dir(self) -> np.ndarray:
        """(3,) unit optical axis in world coordinates."""
        return self.R[2].copy()

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix ``K [R | t]`` (no distortion)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    def world_to_camera(self, X: np.ndarray) -> np.ndarray:
        """(N, 3) world points → (N, 3) camera-frame points, metres."""
        return np.asarray(X, dtype=np.float64) @ self.R.T + self.t

    def project(self, X: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project (N, 3) world points (m) to (N, 2) pixels.

        With ``distort=False`` the ideal (undistorted) pinhole projection is returned.
        Points behind the camera give non-finite or meaningless pixels; check depth first.
        """
        X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
        if distort and self.dist.size and np.any(self.dist != 0):
            rvec, _ = cv2.Rodrigues(self.R)
            uv, _ = cv2.projectPoints(X, rvec, self.t.astype(np.float64), self.K, self.dist)
            return uv.reshape(-1, 2)
        Xc = self.world_to_camera(X)
        z = Xc[:, 2:3]
        xy = Xc[:, :2] / z
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def pixel_rays(self, uv: np.ndarray, distorted: bool = True) -> np.ndarray:
        """Unit ray directions (N, 3) in world coordinates through pixels (N, 2).

        ``distorted=True`` treats ``uv`` as pixels of the distorted (raw) image.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if distorted and self.dist.size and np.any(self.dist != 0):
            xy = cv2.undistortPoints(uv, self.K, self.dist).reshape(-1, 2)
        else:
            Kinv = np.linalg.inv(self.K)
            xy = uv.reshape(-1, 2) @ Kinv[:2, :2].T + Kinv[:2, 2]
        d_cam = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        d = d_cam @ self.R  # R^T applied to row vectors
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (e.g. 0.25 to downscale 4×).

        Uses the pixel-centre convention: ``u' = (u + 0.5)·factor − 0.5``.
        """
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return replace(
            self,
            K=K,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
        )

    def cropped(self, x0: int, y0: int, width: int, height: int) -> Camera:
        """The same camera for the crop ``[y0:y0+height, x0:x0+width]`` of its image."""
        K = self.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return replace(self, K=K, width=int(width), height=int(height))

    def undistorted(self) -> Camera:
        """The same camera with zero distortion (what undistorted frames are seen by)."""
        return replace(self, dist=np.zeros(5))

    def to_dict(self) -> dict:
        d = {
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "role": self.role,
        }
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, name: str, d: Mapping) -> Camera:
        known = {"width", "height", "K", "dist", "R", "t", "role"}
        return cls(
            name=name,
            width=int(d["width"]),
            height=int(d["height"]),
            K=np.asarray(d["K"], dtype=np.float64).reshape(3, 3),
            dist=np.asarray(d.get("dist", []), dtype=np.float64).ravel(),
            R=np.asarray(d["R"], dtype=np.float64).reshape(3, 3),
            t=np.asarray(d["t"], dtype=np.float64).ravel(),
            role=str(d.get("role", "input")),
            extra={k: v for k, v in d.items() if k not in known},
        )


def look_at(
    name: str,
    eye: np.ndarray,
    target: np.ndarray,
    fx: float,
    width: int,
    height: int,
    up: np.ndarray = (0.0, 1.0, 0.0),
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    dist: np.ndarray | None = None,
    role: str = "input",
) -> Camera:
    """Camera at ``eye`` (m) looking at ``target`` (m), image +v pointing along −up.

    Principal point defaults to the image centre ``((W−1)/2, (H−1)/2)``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    # Right-handed camera frame with +y (image down) along -up: x = y × z.
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    t = -R @ eye
    K = np.array(
        [
            [fx, 0.0, (width - 1) / 2 if cx is None else cx],
            [0.0, fx if fy is None else fy, (height - 1) / 2 if cy is None else cy],
            [0.0, 0.0, 1.0],
        ]
    )
    return Camera(
        name=name,
        width=int(width),
        height=int(height),
        K=K,
        dist=np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64),
        R=R,
        t=t,
        role=role,
    )


def orbit_cameras(
    reference: Camera,
    center: np.ndarray,
    n_views: int = 11,
    step_deg: float = 30.0,
    prefix: str = "orbit",
) -> list[Camera]:
    """``n_views`` cameras orbiting ``center`` about the lab +y axis.

    View k (1-based) is ``reference`` rotated by ``k·step_deg`` about the vertical
    axis through ``center``: same distance, same height, same intrinsics, looking at
    ``center``. View 12 of a 30° orbit would coincide with the reference.
    """
    center = np.asarray(center, dtype=np.float64)
    eye0 = reference.center
    cams = []
    for k in range(1, n_views + 1):
        a = np.deg2rad(step_deg * k)
        Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        eye = center + Ry @ (eye0 - center)
        # Rotate the whole reference pose so roll and look direction follow the orbit.
        R = reference.R @ Ry.T
        t = -R @ eye
        cams.append(
            replace(reference, name=f"{prefix}{k:02d}", R=R, t=t, dist=np.zeros(5), role="orbit")
        )
    return cams


def load_cameras(path: str | os.PathLike) -> dict[str, Camera]:
    """Read ``cameras.json`` → ``{name: Camera}`` (file order kept)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        cams = data["cameras"]
    except (OSError, ValueError, KeyError) as e:
        raise ValueError(f"{path}: not a readable cameras.json ({e})") from e
    return {name: Camera.from_dict(name, d) for name, d in cams.items()}


def save_cameras(
    path: str | os.PathLike, cameras: Mapping[str, Camera] | list[Camera], **meta
) -> None:
    """Write ``cameras.json`` atomically. Extra keyword arguments go to the top level."""
    if not isinstance(cameras, Mapping):
        cameras = {c.name: c for c in cameras}
    data = {
        "units": "m",
        "convention": "x_cam = R x_world + t; pixel origin at centre of top-left pixel; "
        "lab frame +y up, heated plate y = 0",
        **meta,
        "cameras": {name: c.to_dict() for name, c in cameras.items()},
    }
    atomic_write_text(path, json.dumps(data, indent=1))


def triangulate(cams: list[Camera], uvs: list[np.ndarray]) -> np.ndarray:
    """Linear (DLT) triangulation of (N, 2) undistorted pixels seen by several cameras.

    Returns (N, 3) world points in metres. ``uvs[i]`` are pixels of ``cams[i]`` with
    distortion already removed.
    """
    n = np.asarray(uvs[0]).reshape(-1, 2).shape[0]
    out = np.zeros((n, 3))
    Ps = [c.P for c in cams]
    for j in range(n):
        rows = []
        for P, uv in zip(Ps, uvs, strict=True):
            u, v = np.asarray(uv, dtype=np.float64).reshape(-1, 2)[j]
            rows.append(u * P[2] - P[0])
            rows.append(v * P[2] - P[1])
        _, _, vt = np.linalg.svd(np.asarray(rows))
        X = vt[-1]
        out[j] = X[:3] / X[3]
    return out
