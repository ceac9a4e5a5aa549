"""The joint bundle adjustment of a camera rig: parameter layout, reprojection residuals
and their Jacobian, Levenberg–Marquardt (plain or robust), the Gauss–Newton covariance and
the 1-sigma uncertainties it gives (:mod:`surfphase.calib.solve` runs it).

Parameters: per camera fx, fy, cx, cy and distortion; per camera other than the first,
its pose relative to the first (rvec, tvec); per moment, the board pose in camera 0's
frame. Units: pixels, radians, the board's length unit (metres).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import least_squares

from surfphase.calib.detect import Detection


def _rt_to_mat(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return R, np.asarray(tvec, dtype=np.float64).ravel()


def _mat_to_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return np.concatenate([rvec.ravel(), np.asarray(t, dtype=np.float64).ravel()])


class _Problem:
    """Parameter layout and residuals of the joint bundle adjustment."""

    def __init__(self, n_cams: int, images: list[str], n_dist: int):
        self.n_cams, self.images, self.n_dist = n_cams, images, n_dist
        self.n_intr = 4 + n_dist
        self.o_extr = n_cams * self.n_intr
        self.o_pose = self.o_extr + 6 * (n_cams - 1)
        self.n_params = self.o_pose + 6 * len(images)

    def pack(self, Ks, dists, extr, poses) -> np.ndarray:
        x = np.zeros(self.n_params)
        for c in range(self.n_cams):
            K = Ks[c]
            x[c * self.n_intr : c * self.n_intr + 4] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
            x[c * self.n_intr + 4 : (c + 1) * self.n_intr] = dists[c][: self.n_dist]
        for c in range(1, self.n_cams):
            x[self.o_extr + 6 * (c - 1) : self.o_extr + 6 * c] = extr[c]
        for i, name in enumerate(self.images):
            x[self.o_pose + 6 * i : self.o_pose + 6 * (i + 1)] = poses[name]
        return x

    def unpack(self, x: np.ndarray):
        """Inverse of :meth:`pack`: (Ks, dists, extrinsics, {image: board pose})."""
        Ks, dists = zip(*(self.intrinsics(x, c) for c in range(self.n_cams)), strict=True)
        extr = [self.extrinsics(x, c).copy() for c in range(self.n_cams)]
        poses = {name: self.pose(x, i).copy() for i, name in enumerate(self.images)}
        return list(Ks), list(dists), extr, poses

    def intrinsics(self, x: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
        fx, fy, cx, cy = x[c * self.n_intr : c * self.n_intr + 4]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        dist = np.zeros(5)
        dist[: self.n_dist] = x[c * self.n_intr + 4 : (c + 1) * self.n_intr]
        return K, dist

    def extrinsics(self, x: np.ndarray, c: int) -> np.ndarray:
        """(6,) rvec, tvec of camera ``c`` relative to camera 0."""
        if c == 0:
            return np.zeros(6)
        return x[self.o_extr + 6 * (c - 1) : self.o_extr + 6 * c]

    def pose(self, x: np.ndarray, i: int) -> np.ndarray:
        """(6,) rvec, tvec of the board of image ``i`` in camera 0's frame."""
        return x[self.o_pose + 6 * i : self.o_pose + 6 * (i + 1)]

    def project(
        self, x: np.ndarray, c: int, i: int, obj: np.ndarray, jacobian: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 2) pixels of board points ``obj`` (N, 3) in camera ``c`` at image ``i``.

        With ``jacobian``, also the (2N, n_params) derivative of the flattened pixels.
        """
        K, dist = self.intrinsics(x, c)
        rb, tb = np.split(self.pose(x, i), 2)
        re, te = np.split(self.extrinsics(x, c), 2)
        # Board → camera 0 → camera c: x_c = R_e (R_b x + t_b) + t_e.
        (r, t, dr_drb, dr_dtb, dr_dre, dr_dte, dt_drb, dt_dtb, dt_dre, dt_dte) = cv2.composeRT(
            rb, tb, re, te
        )
        uv, J = cv2.projectPoints(obj, r, t, K, dist)
        uv = uv.reshape(-1, 2)
        if not jacobian:
            return uv, None
        Jr, Jt = J[:, 0:3], J[:, 3:6]
        out = np.zeros((2 * len(obj), self.n_params))
        o = c * self.n_intr
        out[:, o : o + 4] = J[:, 6:10]
        out[:, o + 4 : o + self.n_intr] = J[:, 10 : 10 + self.n_dist]
        o = self.o_pose + 6 * i
        out[:, o : o + 3] = Jr @ dr_drb + Jt @ dt_drb
        out[:, o + 3 : o + 6] = Jr @ dr_dtb + Jt @ dt_dtb
        if c > 0:
            o = self.o_extr + 6 * (c - 1)
            out[:, o : o + 3] = Jr @ dr_dre + Jt @ dt_dre
            out[:, o + 3 : o + 6] = Jr @ dr_dte + Jt @ dt_dte
        return uv, out

    def residuals(
        self, x: np.ndarray, views: list[tuple[int, int, Detection]], jacobian: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Stacked reprojection errors (pixels) of ``views`` and, optionally, their Jacobian."""
        res, jac = [], []
        for c, i, det in views:
            uv, J = self.project(x, c, i, det.object_points, jacobian)
            res.append((uv - det.image_points).ravel())
            jac.append(J)
        return np.concatenate(res), (np.vstack(jac) if jacobian else None)


def _bundle_adjust(
    problem: _Problem,
    x0: np.ndarray,
    views: list[tuple[int, int, Detection]],
    robust_scale: float | None = None,
    robust_rounds: int = 4,
    free: np.ndarray | None = None,
    max_nfev: int = 100,
):
    """Minimise all reprojection errors; ``views`` are (camera, pose index, detection).

    With ``robust_scale`` (px), the soft-L1 loss of that scale is minimised by
    iteratively reweighted least squares (weight ``1/sqrt(1 + (e/scale)²)`` per corner
    of error ``e``), so views that do not fit cannot pull the solution (used to find
    them); otherwise plain least squares. ``free``: (n_params,) bool, the parameters to
    fit (the others keep their ``x0`` values); all by default. Levenberg–Marquardt.
    Returns the parameters and the (N_k, 2) unweighted residuals (pixels) of each view.
    """
    sizes = np.cumsum([0] + [2 * len(d) for _, _, d in views])
    free = np.ones(x0.size, dtype=bool) if free is None else np.asarray(free, dtype=bool)
    # Poses seen by no view would make the Jacobian singular: keep them fixed.
    seen = np.zeros(x0.size, dtype=bool)
    seen[: problem.o_pose] = True
    for _, i, _ in views:
        seen[problem.o_pose + 6 * i : problem.o_pose + 6 * (i + 1)] = True
    free = free & seen
    cache: dict = {}

    def full(xf: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = xf
        return x

    def evaluate(xf: np.ndarray, s: np.ndarray):
        key = xf.tobytes()
        if key not in cache:
            cache.clear()
            r, J = problem.residuals(full(xf), views, jacobian=True)
            cache[key] = (r * s, J[:, free] * s[:, None])
        return cache[key]

    def weights(x: np.ndarray) -> np.ndarray:
        e = np.linalg.norm(problem.residuals(x, views)[0].reshape(-1, 2), axis=1)
        return np.repeat(1.0 / np.sqrt(1.0 + (e / robust_scale) ** 2), 2)

    x = x0.copy()
    w = weights(x) if robust_scale else np.ones(sizes[-1])
    for _ in range(robust_rounds if robust_scale else 1):
        sqrt_w = np.sqrt(w)
        cache.clear()
        sol = least_squares(
            lambda xf, s=sqrt_w: evaluate(xf, s)[0],
            x[free],
            jac=lambda xf, s=sqrt_w: evaluate(xf, s)[1],
            x_scale="jac",
            method="lm",
            xtol=1e-10,
            ftol=1e-10,
            gtol=1e-10,
            max_nfev=max_nfev,
        )
        x = full(sol.x)
        if robust_scale:
            w = weights(x)
    res = problem.residuals(x, views)[0]
    per_view = [res[sizes[k] : sizes[k + 1]].reshape(-1, 2) for k in range(len(views))]
    return x, per_view


def _covariance(problem: _Problem, x: np.ndarray, views) -> tuple[np.ndarray, float]:
    """(n_params, n_params) Gauss–Newton covariance of the fit, and the residual sd (px).

    ``σ² (JᵀJ)⁻¹`` with the full Jacobian of every residual, ``σ²`` the residual sum of
    squares over the degrees of freedom. Poses seen by no view get zero rows and columns;
    columns are normalised before inversion for conditioning.
    """
    res, J = problem.residuals(x, views, jacobian=True)
    scale = np.linalg.norm(J, axis=0)
    used = scale > 0
    Jn = J[:, used] / scale[used]
    dof = max(res.size - int(used.sum()), 1)
    sigma2 = float(res @ res) / dof
    cov = np.zeros((x.size, x.size))
    try:
        inv = np.linalg.inv(Jn.T @ Jn)
    except np.linalg.LinAlgError:
        inv = np.full((used.sum(), used.sum()), np.inf)
    cov[np.ix_(used, used)] = inv * sigma2 / np.outer(scale[used], scale[used])
    return cov, float(np.sqrt(sigma2))


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (rad) of the rotation between ``Ra`` and ``Rb``."""
    return float(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1.0, 1.0)))


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(r) ** 2, axis=-1)))) if len(r) else 0.0


def _uncertainties(problem: _Problem, x: np.ndarray, cov: np.ndarray, names) -> dict:
    """1-sigma uncertainties per camera: intrinsics (px), distortion, and the pose
    relative to camera 0 (rvec rad, tvec m, baseline m)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {}
    for c, n in enumerate(names):
        o = c * problem.n_intr
        d = {
            "intrinsics_px": dict(
                zip(("fx", "fy", "cx", "cy"), sd[o : o + 4].tolist(), strict=True)
            ),
            "dist": sd[o + 4 : o + problem.n_intr].tolist(),
        }
        if c > 0:
            o = problem.o_extr + 6 * (c - 1)
            t = x[o + 3 : o + 6]
            g = t / np.linalg.norm(t)
            d["rvec_rad"] = x[o : o + 3].tolist()
            d["rvec_sd_rad"] = sd[o : o + 3].tolist()
            d["tvec_m"] = t.tolist()
            d["tvec_sd_m"] = sd[o + 3 : o + 6].tolist()
            d["baseline_sd_m"] = float(np.sqrt(max(g @ cov[o + 3 : o + 6, o + 3 : o + 6] @ g, 0)))
        out[n] = d
    return out
