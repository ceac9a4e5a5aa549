"""Multi-camera ChArUco calibration: intrinsics, distortion, extrinsics in the lab frame.

1. Corners per image and camera (:mod:`surfphase.calib.detect`).
2. Per camera, ``cv2.calibrateCamera`` on every usable view: intrinsics, distortion and
   a board pose per view (the starting point).
3. One joint bundle adjustment over all cameras and images (``scipy.optimize
   .least_squares``): per camera fx, fy, cx, cy and distortion; per camera other than
   the first, its pose relative to the first; per image, the board pose in the first
   camera's frame. Images seen by one camera only still pin that camera's intrinsics;
   images seen by several tie the extrinsics together in one metric frame.
4. Views whose reprojection RMS exceeds ``max_view_rms`` are rejected and step 3 rerun.
5. The board pose of the reference image (see :mod:`surfphase.calib.board`) gives the
   lab frame; every camera is expressed in it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from surfphase.calib.board import BoardSpec, load_board
from surfphase.calib.detect import (
    Detection,
    detect_corners,
    list_images,
    make_detector,
    read_gray,
    usable,
)
from surfphase.cameras import Camera


@dataclass
class Calibration:
    """Everything a calibration run found; ``cameras`` and ``report`` are the results.

    ``detections[cam][image_name]`` are the corners found; ``residuals[cam][image_name]``
    the (N, 2) reprojection errors (pixels) of the views used in the final fit.
    """

    cameras: dict[str, Camera]
    report: dict
    image_dirs: dict[str, Path]
    detections: dict[str, dict[str, Detection]] = field(default_factory=dict)
    residuals: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


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
):
    """Minimise all reprojection errors; ``views`` are (camera, image index, detection).

    With ``robust_scale`` (px), the soft-L1 loss of that scale is minimised by
    iteratively reweighted least squares (weight ``1/sqrt(1 + (e/scale)²)`` per corner
    of error ``e``), so views that do not fit cannot pull the solution (used to find
    them); otherwise plain least squares. Levenberg–Marquardt throughout.
    Returns the parameters and the (N_k, 2) unweighted residuals (pixels) of each view.
    """
    sizes = np.cumsum([0] + [2 * len(d) for _, _, d in views])

    def weights(x: np.ndarray) -> np.ndarray:
        e = np.linalg.norm(problem.residuals(x, views)[0].reshape(-1, 2), axis=1)
        return np.repeat(1.0 / np.sqrt(1.0 + (e / robust_scale) ** 2), 2)

    x = x0
    w = weights(x) if robust_scale else np.ones(sizes[-1])
    for _ in range(robust_rounds if robust_scale else 1):
        sqrt_w = np.sqrt(w)
        sol = least_squares(
            lambda x, s=sqrt_w: problem.residuals(x, views)[0] * s,
            x,
            jac=lambda x, s=sqrt_w: problem.residuals(x, views, jacobian=True)[1] * s[:, None],
            x_scale="jac",
            method="lm",
            xtol=1e-10,
            ftol=1e-10,
            gtol=1e-10,
            max_nfev=100,
        )
        x = sol.x
        if robust_scale:
            w = weights(x)
    res = problem.residuals(x, views)[0]
    per_view = [res[sizes[k] : sizes[k + 1]].reshape(-1, 2) for k in range(len(views))]
    return x, per_view


def _parameter_sd(problem: _Problem, x: np.ndarray, views) -> np.ndarray:
    """(n_params,) standard deviations of the fitted parameters (Gauss–Newton covariance).

    The residual variance is estimated from the fit itself (sum of squares over the
    degrees of freedom); columns are normalised before inversion for conditioning.
    """
    res, J = problem.residuals(x, views, jacobian=True)
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Jn = J / scale
    dof = max(res.size - x.size, 1)
    sigma2 = float(res @ res) / dof
    try:
        cov = np.linalg.inv(Jn.T @ Jn) * sigma2
    except np.linalg.LinAlgError:
        return np.full(x.size, np.inf)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None)) / scale


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (rad) of the rotation between ``Ra`` and ``Rb``."""
    return float(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1.0, 1.0)))


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(r) ** 2, axis=-1)))) if len(r) else 0.0


def _single_opencv_thread(fn):
    """Run ``fn`` with OpenCV on one thread.

    OpenCV's thread pool changes the last digits of a calibration from run to run, and
    the same inputs must give the same cameras.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            return fn(*args, **kwargs)
        finally:
            cv2.setNumThreads(threads)

    return wrapper


@_single_opencv_thread
def calibrate_rig_detailed(
    board_yaml: Path | BoardSpec,
    image_dirs: dict[str, Path],
    min_images: int = 6,
    rig: str | None = None,
    min_corners: int = 4,
    max_view_rms: float = 1.0,
    fix_k3: bool = True,
    max_refits: int = 8,
) -> Calibration:
    """Calibrate all cameras of a rig from synchronized ChArUco images.

    Args:
        board_yaml: the board description (``board.yaml`` path or a :class:`BoardSpec`).
        image_dirs: ``{camera name: folder of images}``; the first camera is camera 0
            (the one the reference image's board faces). Images with the same file
            name across folders were taken at the same moment.
        min_images: fewest usable views a camera needs.
        rig: rig id, used in error messages and the report.
        min_corners: fewest corners for a view to be used.
        max_view_rms: views whose reprojection RMS (px) exceeds this are rejected.
        max_refits: most robust passes (each may reject views) before the final fit.
        fix_k3: keep the 6th-order radial term at zero (narrow lenses cannot pin it).

    Returns:
        A :class:`Calibration`: cameras (lab frame, metres, raw-image intrinsics and
        distortion, role ``input``) and a JSON-ready report.
    """
    where = f"rig {rig}: " if rig else ""
    if not image_dirs:
        raise ValueError(f"{where}no camera folders given")
    board = board_yaml if isinstance(board_yaml, BoardSpec) else load_board(board_yaml)
    names = list(image_dirs)
    dirs = {n: Path(p) for n, p in image_dirs.items()}
    detector = make_detector(board)

    detections: dict[str, dict[str, Detection]] = {}
    rejected: dict[str, list[dict]] = {n: [] for n in names}
    sizes: dict[str, tuple[int, int]] = {}
    files: dict[str, list[str]] = {}
    for n in names:
        folder = dirs[n]
        if not folder.is_dir():
            raise FileNotFoundError(f"{where}calibration folder of {n} not found: {folder}")
        paths = list_images(folder)
        if not paths:
            raise ValueError(f"{where}no calibration images (png/tif/jpg) in {folder}")
        files[n] = [p.name for p in paths]
        detections[n] = {}
        for p in paths:
            img = read_gray(p)
            shape = (img.shape[1], img.shape[0])
            if sizes.setdefault(n, shape) != shape:
                raise ValueError(
                    f"{where}{p}: image size {shape[0]}×{shape[1]} differs from the other "
                    f"images of {folder} ({sizes[n][0]}×{sizes[n][1]})"
                )
            det = detect_corners(img, board, detector)
            why = usable(det, min_corners)
            if why is None:
                detections[n][p.name] = det
            else:
                rejected[n].append({"image": p.name, "reason": why})
        found = len(detections[n])
        if found < min_images:
            raise ValueError(
                f"{where}board found in only {found} of {len(paths)} images of {folder} "
                f"(need {min_images})"
            )

    reference = board.reference_image or files[names[0]][0]
    if not any(reference in detections[n] for n in names):
        raise ValueError(
            f"{where}the board is not found in the reference image {reference} "
            f"({', '.join(str(dirs[n] / reference) for n in names)})"
        )

    # Step 2: each camera alone.
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    Ks, dists, cam_poses = [], [], []
    for n in names:
        views = list(detections[n].items())
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [d.object_points.astype(np.float32) for _, d in views],
            [d.image_points.astype(np.float32) for _, d in views],
            sizes[n],
            None,
            None,
            flags=flags,
        )
        Ks.append(K)
        dists.append(dist.ravel()[:5])
        cam_poses.append(
            {
                img: (r.ravel(), t.ravel())
                for (img, _), r, t in zip(views, rvecs, tvecs, strict=True)
            }
        )

    # Relative poses of cameras 1.. to camera 0 from their best shared view.
    extr = [np.zeros(6)]
    for c in range(1, len(names)):
        shared = [i for i in detections[names[c]] if i in detections[names[0]]]
        if not shared:
            raise ValueError(
                f"{where}no image shows the board to both {names[0]} and {names[c]} "
                f"({dirs[names[0]]}, {dirs[names[c]]}): the extrinsics cannot be tied"
            )
        candidates = []
        for i in shared:
            R0, t0 = _rt_to_mat(*cam_poses[0][i])
            Rc, tc = _rt_to_mat(*cam_poses[c][i])
            R = Rc @ R0.T
            candidates.append((R, tc - R @ t0))
        # The medoid of the shared views' estimates: one bad view cannot spoil it.
        cost = [
            sum(
                _angle(Ra, Rb) + np.linalg.norm(ta - tb) / max(np.linalg.norm(ta), 1e-12)
                for Rb, tb in candidates
            )
            for Ra, ta in candidates
        ]
        extr.append(_mat_to_rt(*candidates[int(np.argmin(cost))]))

    images = sorted({i for n in names for i in detections[n]})
    poses = {}
    for i in images:
        if i in cam_poses[0]:
            poses[i] = np.concatenate(cam_poses[0][i])
            continue
        c = next(c for c in range(1, len(names)) if i in cam_poses[c])
        Rb, tb = _rt_to_mat(*cam_poses[c][i])
        Re, te = _rt_to_mat(*np.split(extr[c], 2))
        poses[i] = _mat_to_rt(Re.T @ Rb, Re.T @ (tb - te))

    # Steps 3-4: joint bundle adjustment. A robust loss first, so that views that do not
    # fit stand out; drop the worst of them (above the limit and within half of the worst
    # RMS) and repeat from the per-camera start; then plain least squares on the rest.
    n_dist = 4 if fix_k3 else 5
    views = {(n, i) for n in names for i in detections[n]}

    def setup():
        images = sorted({i for _, i in views})
        index = {i: k for k, i in enumerate(images)}
        problem = _Problem(len(names), images, n_dist)
        active = [
            (c, index[i], detections[n][i])
            for c, n in enumerate(names)
            for i in sorted(detections[n])
            if (n, i) in views
        ]
        return images, index, problem, active

    for _ in range(max(1, max_refits)):
        images, index, problem, active = setup()
        x = problem.pack(Ks, dists, extr, {i: poses[i] for i in images})
        x, per_view = _bundle_adjust(problem, x, active, robust_scale=max_view_rms)
        fitted = problem.unpack(x)
        view_rms = [_rms(r) for r in per_view]
        worst = max(view_rms)
        if worst <= max_view_rms:
            break
        for (c, i, _), rms in zip(active, view_rms, strict=True):
            if rms > max_view_rms and rms >= 0.5 * worst:
                rejected[names[c]].append(
                    {
                        "image": images[i],
                        "reason": f"reprojection RMS {rms:.2f} px above {max_view_rms} px",
                    }
                )
                views.discard((names[c], images[i]))
        for n in names:
            used = sum(1 for m, _ in views if m == n)
            if used < min_images:
                raise ValueError(
                    f"{where}only {used} views of {dirs[n]} fit the calibration "
                    f"(need {min_images}); views with reprojection RMS above "
                    f"{max_view_rms} px were rejected"
                )
    images, index, problem, active = setup()
    Kf, df, ef, pf = fitted
    x, per_view = _bundle_adjust(problem, problem.pack(Kf, df, ef, pf), active)
    if reference not in index:
        raise ValueError(f"{where}the reference image {reference} was rejected (see the report)")

    # Step 5: lab frame from the reference image's board pose in camera 0.
    Rb, tb = _rt_to_mat(*np.split(problem.pose(x, index[reference]), 2))
    Rl, tl = board.board_to_lab()
    R0 = Rb @ Rl.T
    t0 = tb - R0 @ tl
    cameras: dict[str, Camera] = {}
    for c, n in enumerate(names):
        K, dist = problem.intrinsics(x, c)
        Re, te = _rt_to_mat(*np.split(problem.extrinsics(x, c), 2))
        cameras[n] = Camera(
            name=n,
            width=sizes[n][0],
            height=sizes[n][1],
            K=K,
            dist=dist,
            R=Re @ R0,
            t=Re @ t0 + te,
            role="input",
        )

    residuals: dict[str, dict[str, np.ndarray]] = {n: {} for n in names}
    for (c, i, _), r in zip(active, per_view, strict=True):
        residuals[names[c]][images[i]] = r
    sd = _parameter_sd(problem, x, active)
    intr_sd = {
        n: dict(
            zip(
                ("fx", "fy", "cx", "cy"),
                sd[c * problem.n_intr : c * problem.n_intr + 4],
                strict=True,
            )
        )
        for c, n in enumerate(names)
    }
    report = _report(
        rig, board, reference, names, dirs, files, cameras, residuals, rejected, intr_sd
    )
    return Calibration(cameras, report, dirs, detections, residuals)


def _report(
    rig, board, reference, names, dirs, files, cameras, residuals, rejected, intr_sd
) -> dict:
    per_cam = {}
    for n in names:
        res = residuals[n]
        all_r = np.concatenate(list(res.values())) if res else np.zeros((0, 2))
        per_cam[n] = {
            "folder": str(dirs[n]),
            "images": len(files[n]),
            "images_used": len(res),
            "corners_used": int(len(all_r)),
            "rms_px": _rms(all_r),
            "per_image_rms_px": {i: _rms(r) for i, r in sorted(res.items())},
            "rejected": sorted(rejected[n], key=lambda d: d["image"]),
            "fx": cameras[n].K[0, 0],
            "fy": cameras[n].K[1, 1],
            "cx": cameras[n].K[0, 2],
            "cy": cameras[n].K[1, 2],
            "dist": cameras[n].dist.tolist(),
            # 1-sigma uncertainties; in a narrow field of view the principal point is the
            # least constrained (it trades off against the camera's rotation).
            "sd_px": {k: float(v) for k, v in intr_sd[n].items()},
            "center_m": cameras[n].center.tolist(),
        }
    all_r = [r for n in names for r in residuals[n].values()]
    c0 = cameras[names[0]].center
    return {
        "rig": rig,
        "board": {
            "squares_x": board.squares_x,
            "squares_y": board.squares_y,
            "square_length": board.square_length,
            "marker_length": board.marker_length,
            "dictionary": board.dictionary,
            "lab_origin_in_board": board.lab_origin.tolist(),
        },
        "reference_image": reference,
        "rms_px": _rms(np.concatenate(all_r)) if all_r else 0.0,
        "baselines_m": {n: float(np.linalg.norm(cameras[n].center - c0)) for n in names[1:]},
        "cameras": per_cam,
    }


def calibrate_rig(
    board_yaml: Path,
    image_dirs: dict[str, Path],
    min_images: int = 6,
    rig: str | None = None,
    **options,
) -> tuple[dict[str, Camera], dict]:
    """Calibrate a rig; returns ``(cameras, report)``.

    See :func:`calibrate_rig_detailed` for the arguments; ``options`` are passed on.
    """
    cal = calibrate_rig_detailed(board_yaml, image_dirs, min_images=min_images, rig=rig, **options)
    return cal.cameras, cal.report


__all__ = ["Calibration", "calibrate_rig", "calibrate_rig_detailed", "read_gray", "list_images"]
