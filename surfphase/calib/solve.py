"""Multi-camera ChArUco calibration: intrinsics, distortion, extrinsics in the lab frame.

1. Views per camera (:mod:`surfphase.calib.sources`: a folder of images or a sampled
   recording, paired by timestamps) and their corners (:mod:`surfphase.calib.detect`;
   a board printed inverted is found automatically or by the board's ``inverted`` key).
   When a camera has too few, the error says which likely cause fits what was seen.
2. Per camera alone, ``cv2.calibrateCamera`` on its usable views (views above
   ``max_view_rms`` dropped): intrinsics, distortion and a board pose per view. These are
   the joint solve's starting point and its independent check.
3. With those intrinsics held, the cameras' poses relative to camera 0 and a board pose
   per moment (robust loss). A moment whose views do not fit one board pose (the cameras
   were not simultaneous, or the board moved) is split: each camera keeps its view with
   its own board pose, which pins that camera's intrinsics but not the extrinsics.
4. One joint bundle adjustment (``scipy.optimize.least_squares``, Levenberg–Marquardt)
   over everything: per camera fx, fy, cx, cy and distortion; per camera other than the
   first, its pose relative to the first; per moment, the board pose in camera 0's frame.
   Views above ``max_view_rms`` are rejected and the fit rerun.
5. Checks (:mod:`surfphase.calib.checks`): each camera's intrinsics against step 2,
   each baseline and relative rotation against the shared views' own estimates; a
   disagreement is a warning naming the camera (in the report, on stderr). Cameras
   implausibly far from the board (lengths not in metres) stop the run.
6. Uncertainties: the Gauss–Newton covariance of all parameters (full Jacobian, residual
   variance from the fit), propagated to the baselines.
7. The board pose of the reference view (see :mod:`surfphase.calib.board`) gives the
   lab frame; every camera is expressed in it.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from surfphase.calib import checks
from surfphase.calib.board import BoardSpec, load_board
from surfphase.calib.detect import Detection, detect_view, diagnose, make_detector, usable
from surfphase.calib.sources import FrameSource, open_sources
from surfphase.cameras import Camera

#: With the board's polarity automatic, a camera whose views were all found in one
#: polarity, this many of them, is no longer tried in the other.
STICKY_POLARITY = 5
#: Fewest moments shared with camera 0 for a camera's extrinsics to be checked.
MIN_SHARED = 3
#: Views diagnosed when a camera has too few (evenly spaced among those without the board).
DIAGNOSE_VIEWS = 12


class CalibrationWarning(UserWarning):
    """A calibration that ran but disagrees with an independent estimate."""


@dataclass
class Calibration:
    """Everything a calibration run found; ``cameras`` and ``report`` are the results.

    ``detections[cam][view]`` are the corners found; ``residuals[cam][view]`` the (N, 2)
    reprojection errors (pixels) of the views used in the final fit; ``covariance`` the
    (P, P) covariance of the final fit's parameters (layout of ``problem``).
    """

    cameras: dict[str, Camera]
    report: dict
    sources: dict[str, FrameSource]
    detections: dict[str, dict[str, Detection]] = field(default_factory=dict)
    residuals: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    single: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def image_dirs(self) -> dict[str, Path]:
        """``{camera: folder or recording}``."""
        return {n: s.path for n, s in self.sources.items()}

    @property
    def warnings(self) -> list[str]:
        return list(self.report.get("warnings", []))


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


def _view_rms(det: Detection, K, dist, rvec, tvec) -> float:
    uv, _ = cv2.projectPoints(det.object_points, rvec, tvec, K, dist)
    return _rms(uv.reshape(-1, 2) - det.image_points)


def single_camera(
    views: dict[str, Detection],
    size: tuple[int, int],
    fix_k3: bool = True,
    max_view_rms: float = 1.0,
    max_refits: int = 8,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], list[dict]]:
    """One camera alone: ``cv2.calibrateCamera`` on ``views`` ({name: detection}).

    Views whose RMS exceeds ``max_view_rms`` px (and half the worst view's) are dropped
    and the calibration rerun, at most ``max_refits`` times. Returns ``(K (3, 3),
    dist (5,), {view: (6,) board pose rvec, tvec in the camera frame}, rejected)``.
    """
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    keep = dict(views)
    rejected: list[dict] = []
    for _ in range(max(1, max_refits)):
        names = sorted(keep)
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [keep[n].object_points.astype(np.float32) for n in names],
            [keep[n].image_points.astype(np.float32) for n in names],
            size,
            None,
            None,
            flags=flags,
        )
        dist = dist.ravel()[:5]
        rms = {
            n: _view_rms(keep[n], K, dist, r, t)
            for n, r, t in zip(names, rvecs, tvecs, strict=True)
        }
        worst = max(rms.values())
        if worst <= max_view_rms or len(keep) <= 4:
            break
        for n, e in rms.items():
            if e > max_view_rms and e >= 0.5 * worst:
                rejected.append(
                    {
                        "image": n,
                        "reason": f"reprojection RMS {e:.2f} px above {max_view_rms} px "
                        "(single-camera calibration)",
                    }
                )
                del keep[n]
    poses = {
        n: np.concatenate([r.ravel(), t.ravel()])
        for n, r, t in zip(names, rvecs, tvecs, strict=True)
    }
    return K, np.pad(dist, (0, 5 - dist.size)), poses, rejected


def _detect(sources, board, min_corners, min_images, where):
    """Corners in every view: (detections, rejected, sizes, polarity counts)."""
    detector = make_detector(board)
    detections: dict[str, dict[str, Detection]] = {}
    rejected: dict[str, list[dict]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    polarity: dict[str, dict[str, int]] = {}
    for n, src in sources.items():
        detections[n], rejected[n] = {}, []
        polarity[n] = {"normal": 0, "inverted": 0}
        missing = []
        for name, img in src.iter_views():
            shape = (img.shape[1], img.shape[0])
            if sizes.setdefault(n, shape) != shape:
                raise ValueError(
                    f"{where}{n}: view {name} of {src.path} is {shape[0]}×{shape[1]}, the "
                    f"others {sizes[n][0]}×{sizes[n][1]}"
                )
            # Automatic polarity: the one found more often is tried first; once one is
            # found STICKY_POLARITY times and the other never, only that one is tried.
            seen = polarity[n]
            order = (True, False) if seen["inverted"] > seen["normal"] else (False, True)
            if min(seen.values()) == 0 and max(seen.values()) >= STICKY_POLARITY:
                order = order[:1]
            det, inverted = detect_view(img, board, detector, min_corners, order)
            why = usable(det, min_corners)
            if why is None:
                detections[n][name] = det
                polarity[n]["inverted" if inverted else "normal"] += 1
            else:
                rejected[n].append({"image": name, "reason": why})
                if why == "board not found" or len(det) < min_corners:
                    missing.append(name)
        found = len(detections[n])
        if found < min_images:
            spaced = np.linspace(0, len(missing) - 1, min(DIAGNOSE_VIEWS, len(missing)))
            pick = [missing[k] for k in np.unique(np.round(spaced).astype(int))]
            images = [img for _, img in src.iter_views(pick)]
            causes = diagnose(images, board, min_corners, found) if images else []
            what = "images" if src.kind == "folder" else "sampled frames"
            msg = (
                f"{where}board found in only {found} of {len(src.names)} {what} of "
                f"{n} ({src.path}) (need {min_images})"
            )
            if causes:
                msg += "; likely cause: " + causes[0]
                if len(causes) > 1:
                    msg += "; also possible: " + "; ".join(causes[1:])
            raise ValueError(msg)
    return detections, rejected, sizes, polarity


def _medoid(candidates: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(6,) rvec, tvec of the candidate pose nearest all others (one bad view cannot
    spoil it)."""
    cost = [
        sum(
            _angle(Ra, Rb) + np.linalg.norm(ta - tb) / max(np.linalg.norm(ta), 1e-12)
            for Rb, tb in candidates
        )
        for Ra, ta in candidates
    ]
    return _mat_to_rt(*candidates[int(np.argmin(cost))])


def _relative(pose0: np.ndarray, posec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera c relative to camera 0 from the board poses of one view in each:
    ``x_c = R x_0 + t``."""
    R0, t0 = _rt_to_mat(*np.split(pose0, 2))
    Rc, tc = _rt_to_mat(*np.split(posec, 2))
    R = Rc @ R0.T
    return R, tc - R @ t0


def _in_cam0(pose: np.ndarray, extr: np.ndarray) -> np.ndarray:
    """A board pose in camera c's frame → in camera 0's, given c's pose ``extr``."""
    Rb, tb = _rt_to_mat(*np.split(pose, 2))
    Re, te = _rt_to_mat(*np.split(extr, 2))
    return _mat_to_rt(Re.T @ Rb, Re.T @ (tb - te))


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
    timestamps: Path | None = None,
    max_frames: int | None = None,
    sync_tolerance: float | None = None,
    strict: bool = False,
) -> Calibration:
    """Calibrate all cameras of a rig from synchronized ChArUco views.

    Args:
        board_yaml: the board description (``board.yaml`` path or a :class:`BoardSpec`).
        image_dirs: ``{camera name: folder of images or recording}``; the first camera
            is camera 0 (the one the reference view's board faces). Images with the same
            file name across folders were taken at the same moment; recordings are
            paired by frame index or by ``timestamps`` (:mod:`surfphase.calib.sources`).
        min_images: fewest usable views a camera needs.
        rig: rig id, used in error messages and the report.
        min_corners: fewest corners for a view to be used.
        max_view_rms: views whose reprojection RMS (px) exceeds this are rejected (a
            shared moment whose views do not fit one board pose is split instead).
        fix_k3: keep the 6th-order radial term at zero (narrow lenses cannot pin it).
        max_refits: most rejection passes of each step.
        timestamps: per-frame capture times of the recordings (the sources module's
            format); only frames within ``sync_tolerance`` seconds are paired.
        max_frames: most frames sampled from a recording (default
            :data:`surfphase.calib.sources.MAX_FRAMES`).
        strict: raise ValueError instead of warning when a check fails.

    Returns:
        A :class:`Calibration`: cameras (lab frame, metres, raw-image intrinsics and
        distortion, role ``input``) and a JSON-ready report, whose ``warnings`` list
        the checks that failed (each also issued as a :class:`CalibrationWarning`).
    """
    from surfphase.calib.sources import MAX_FRAMES

    where = f"rig {rig}: " if rig else ""
    if not image_dirs:
        raise ValueError(f"{where}no camera folders given")
    board = board_yaml if isinstance(board_yaml, BoardSpec) else load_board(board_yaml)
    sources, sync = open_sources(
        {n: Path(p) for n, p in image_dirs.items()},
        timestamps=timestamps,
        max_frames=max_frames or MAX_FRAMES,
        sync_tolerance=sync_tolerance,
        where=where,
    )
    names = list(sources)
    detections, rejected, sizes, polarity = _detect(sources, board, min_corners, min_images, where)
    warn: list[str] = []
    if sync.get("warning"):
        warn.append(f"{where}{sync['warning']}")

    # Step 2: each camera alone.
    single = {}
    for n in names:
        K, dist, poses, rej = single_camera(
            detections[n], sizes[n], fix_k3, max_view_rms, max_refits
        )
        rejected[n] += rej
        if len(poses) < min_images:
            raise ValueError(
                f"{where}only {len(poses)} views of {sources[n].label} fit a single-camera "
                f"calibration (need {min_images}); views with reprojection RMS above "
                f"{max_view_rms} px were rejected"
            )
        single[n] = (K, dist, poses)

    if board.reference_image:
        reference = board.reference_image
        if not any(reference in single[n][2] for n in names):
            raise ValueError(
                f"{where}the board is not found (or does not fit) in the reference image "
                f"{reference} ({', '.join(str(sources[n].path) for n in names)})"
            )
    else:
        reference = sorted(single[names[0]][2])[0]

    # Relative poses of cameras 1.. to camera 0: the medoid of the shared views' estimates.
    extr = [np.zeros(6)]
    for c in range(1, len(names)):
        shared = sorted(set(single[names[0]][2]) & set(single[names[c]][2]))
        if not shared:
            raise ValueError(
                f"{where}no view shows the board to both {names[0]} and {names[c]} "
                f"({sources[names[0]].path}, {sources[names[c]].path}): the extrinsics "
                "cannot be tied"
            )
        extr.append(
            _medoid([_relative(single[names[0]][2][i], single[names[c]][2][i]) for i in shared])
        )

    # Every view used and the board pose it belongs to (a moment, or its own when split).
    key_of = {(n, i): i for n in names for i in single[n][2]}
    n_dist = 4 if fix_k3 else 5
    Ks = [single[n][0] for n in names]
    dists = [single[n][1] for n in names]

    def initial_poses(key_of, extr, known=None):
        poses = dict(known or {})
        for c, n in enumerate(names):
            for (m, i), k in sorted(key_of.items()):
                if m == n and k not in poses:
                    poses[k] = _in_cam0(single[n][2][i], extr[c])
        return poses

    def setup(key_of, shared_only=False):
        """The problem over the views of ``key_of`` (only moments of several views, with
        ``shared_only``: with the intrinsics held, a view alone fits its own pose and
        moves nothing else)."""
        count: dict[str, int] = {}
        for k in key_of.values():
            count[k] = count.get(k, 0) + 1
        view_ids = [
            (n, i)
            for n in names
            for i in sorted(detections[n])
            if (n, i) in key_of and (count[key_of[(n, i)]] > 1 or not shared_only)
        ]
        keys = sorted({key_of[v] for v in view_ids})
        index = {k: j for j, k in enumerate(keys)}
        problem = _Problem(len(names), keys, n_dist)
        c_of = {n: c for c, n in enumerate(names)}
        active = [(c_of[n], index[key_of[(n, i)]], detections[n][i]) for n, i in view_ids]
        return keys, problem, active, view_ids

    def alone_poses(key_of, extr, poses):
        """``poses`` with each single view's board pose from its camera's own calibration
        (optimal while the intrinsics are held), through that camera's ``extr``."""
        count: dict[str, int] = {}
        for k in key_of.values():
            count[k] = count.get(k, 0) + 1
        out = dict(poses)
        for c, n in enumerate(names):
            for (m, i), k in key_of.items():
                if m == n and count[k] == 1:
                    out[k] = _in_cam0(single[n][2][i], extr[c])
        return out

    # Step 3: intrinsics held, robust; split moments whose views do not fit together.
    split: list[dict] = []
    poses = initial_poses(key_of, extr)
    for _ in range(max(1, max_refits)):
        keys, problem, active, view_ids = setup(key_of, shared_only=True)
        if not active:  # every shared moment was split: the check below says so
            break
        x = problem.pack(Ks, dists, extr, {k: poses[k] for k in keys})
        free = np.ones(x.size, dtype=bool)
        free[: problem.o_extr] = False
        x, per_view = _bundle_adjust(problem, x, active, robust_scale=max_view_rms, free=free)
        _, _, extr, poses = problem.unpack(x)
        rms = {v: _rms(r) for v, r in zip(view_ids, per_view, strict=True)}
        count: dict[str, int] = {}
        for v in view_ids:
            count[key_of[v]] = count.get(key_of[v], 0) + 1
        bad: dict[str, float] = {}
        for v in view_ids:
            if count[key_of[v]] > 1 and rms[v] > max_view_rms:
                bad[key_of[v]] = max(bad.get(key_of[v], 0.0), rms[v])
        if not bad:
            break
        worst = max(bad.values())
        for k, e in sorted(bad.items()):
            if e < 0.5 * worst:
                continue
            owner = next(v for v in view_ids if key_of[v] == k)
            others = [v for v in view_ids if key_of[v] == k and v != owner]
            for n, i in others:
                key_of[(n, i)] = f"{i}|{n}"
            split.append(
                {
                    "moment": k,
                    "cameras": [owner[0]] + [n for n, _ in others],
                    "reason": f"the views do not fit one board pose (RMS up to {e:.2f} px "
                    f"above {max_view_rms} px): not simultaneous, or the board moved; each "
                    "camera keeps its view alone",
                }
            )
        poses = initial_poses(key_of, extr, poses)
    for c in range(1, len(names)):
        tied = {k for (n, _), k in key_of.items() if n == names[c]} & {
            k for (n, _), k in key_of.items() if n == names[0]
        }
        if not tied:
            raise ValueError(
                f"{where}no moment shows the board to both {names[0]} and {names[c]} "
                f"consistently ({len(split)} moments did not fit one board pose): are "
                f"{sources[names[0]].path} and {sources[names[c]].path} synchronised?"
            )
        lost = sum(1 for m in split if names[c] in m["cameras"] and names[0] in m["cameras"])
        if lost >= 2 and lost > len(tied):
            warn.append(
                f"{where}{names[c]}: {lost} of the {lost + len(tied)} moments it shares with "
                f"{names[0]} do not fit one board pose: "
                + (
                    f"although paired by timestamps (within {sync['sync_tolerance_s']:.3g} s), "
                    "was the board flat and still, and are the timestamps right?"
                    if sync["mode"] == "timestamps"
                    else f"are {sources[names[0]].path} and {sources[names[c]].path} "
                    "synchronised (give a timestamps file), and was the board flat and still?"
                )
            )
        if len(tied) < MIN_SHARED:
            warn.append(
                f"{where}{names[c]}: its pose relative to {names[0]} rests on only "
                f"{len(tied)} shared moment(s), which nothing checks; record more views of "
                f"the board seen by both (at least {MIN_SHARED})"
            )

    # Step 4: everything free, plain least squares; reject views that still do not fit.
    poses = alone_poses(key_of, extr, poses)
    held = (list(extr), dict(poses))  # step 3's solution
    for _ in range(max(1, max_refits)):
        keys, problem, active, view_ids = setup(key_of)
        x = problem.pack(Ks, dists, extr, {k: poses[k] for k in keys})
        x, per_view = _bundle_adjust(problem, x, active)
        Ks, dists, extr, poses = problem.unpack(x)
        rms = {v: _rms(r) for v, r in zip(view_ids, per_view, strict=True)}
        worst = max(rms.values())
        if worst <= max_view_rms:
            break
        for v, e in rms.items():
            if e > max_view_rms and e >= 0.5 * worst:
                rejected[v[0]].append(
                    {
                        "image": v[1],
                        "reason": f"reprojection RMS {e:.2f} px above {max_view_rms} px "
                        "(joint solve)",
                    }
                )
                del key_of[v]
        for n in names:
            used = sum(1 for m, _ in key_of if m == n)
            if used < min_images:
                raise ValueError(
                    f"{where}only {used} views of {sources[n].label} fit the calibration "
                    f"(need {min_images}); views with reprojection RMS above "
                    f"{max_view_rms} px were rejected"
                )
    index = {k: j for j, k in enumerate(keys)}
    if reference not in index:
        raise ValueError(f"{where}the reference image {reference} was rejected (see the report)")

    # Step 5: checks against the single-camera calibrations and the per-view extrinsics.
    check: dict[str, dict] = {n: {} for n in names}
    moved, moved_cams = [], []
    for c, n in enumerate(names):
        K, _ = problem.intrinsics(x, c)
        figures, w = checks.intrinsics_warnings(n, K, single[n][0], where)
        check[n].update({"joint_" + k: v for k, v in figures.items()})
        moved += w
        moved_cams += [n] if w else []
    intrinsics_from = "joint solve"
    if moved:
        # The shared views pull the intrinsics away from what each camera's own views
        # say: keep those, and solve only the extrinsics and board poses with them.
        intrinsics_from = "single-camera calibrations (the joint solve disagreed)"
        warn += moved
        warn.append(
            f"{where}the joint solve moved the intrinsics of {', '.join(moved_cams)} away "
            "from the single-camera calibrations (above): the shared views do not agree with each camera's own "
            "views (unsynchronised frames, a board that is not flat, or too few shared "
            "views). The intrinsics are kept from the single-camera calibrations and only "
            "the extrinsics and board poses are solved; check the extrinsics"
        )
        Ks, dists = [single[n][0] for n in names], [single[n][1] for n in names]
        extr, poses = held
        keys, problem, active, view_ids = setup(key_of, shared_only=True)
        x = problem.pack(Ks, dists, extr, {k: poses[k] for k in keys})
        free = np.ones(x.size, dtype=bool)
        free[: problem.o_extr] = False
        x, _ = _bundle_adjust(problem, x, active, free=free)
        _, _, extr, shared_poses = problem.unpack(x)
        poses = alone_poses(key_of, extr, {**poses, **shared_poses})
        keys, problem, active, view_ids = setup(key_of)
        x = problem.pack(Ks, dists, extr, {k: poses[k] for k in keys})
        res = problem.residuals(x, active)[0]
        bounds = np.cumsum([0] + [2 * len(d) for _, _, d in active])
        per_view = [res[a:b].reshape(-1, 2) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        index = {k: j for j, k in enumerate(keys)}
    for c, n in enumerate(names[1:], start=1):
        tied = sorted(
            i
            for (m, i), k in key_of.items()
            if m == n and k == i and (names[0], i) in key_of and key_of[(names[0], i)] == i
        )
        per_view_rt = [_relative(single[names[0]][2][i], single[n][2][i]) for i in tied]
        Re, te = _rt_to_mat(*np.split(problem.extrinsics(x, c), 2))
        figures, w = checks.extrinsics_warnings(n, names[0], Re, te, per_view_rt, where)
        check[n].update(figures)
        warn += w
    distances = {}
    for c, n in enumerate(names):
        d = []
        for cc, i, det in active:
            if cc != c:
                continue
            Rb, tb = _rt_to_mat(*np.split(problem.pose(x, i), 2))
            Re, te = _rt_to_mat(*np.split(problem.extrinsics(x, c), 2))
            d.append(np.linalg.norm(Re @ (Rb @ det.object_points.mean(axis=0) + tb) + te))
        distances[n] = float(np.median(d))
        check[n]["board_distance_m"] = distances[n]
    checks.check_units(distances, board.square_length, board.marker_length, where)

    # Step 7: lab frame from the reference view's board pose in camera 0.
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
    for v, r in zip(view_ids, per_view, strict=True):
        residuals[v[0]][v[1]] = r
    cov, sigma = _covariance(problem, x, active)
    sd = _uncertainties(problem, x, cov, names)
    if strict and warn:
        raise ValueError("; ".join(warn))
    for w in warn:
        warnings.warn(w, CalibrationWarning, stacklevel=2)
    report = _report(rig, board, reference, names, sources, cameras, residuals, rejected, sd, sigma)
    report["sync"] = sync
    report["split_moments"] = split
    report["polarity"] = {
        "from": "board key inverted: " + ("true" if board.inverted else "false")
        if board.inverted is not None
        else "found automatically (each view tried as it is, then inverted)",
        "views": polarity,
    }
    report["single_camera"] = {
        n: {
            "fx": float(single[n][0][0, 0]),
            "fy": float(single[n][0][1, 1]),
            "cx": float(single[n][0][0, 2]),
            "cy": float(single[n][0][1, 2]),
            "views": len(single[n][2]),
        }
        for n in names
    }
    report["checks"] = check
    report["intrinsics_from"] = intrinsics_from
    report["warnings"] = warn
    cal = Calibration(cameras, report, sources, detections, residuals)
    cal.single = {n: (single[n][0], single[n][1]) for n in names}
    return cal


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


def _report(rig, board, reference, names, sources, cameras, residuals, rejected, sd, sigma) -> dict:
    per_cam = {}
    for n in names:
        res = residuals[n]
        all_r = np.concatenate(list(res.values())) if res else np.zeros((0, 2))
        per_cam[n] = {
            "folder": str(sources[n].path),
            "source": sources[n].kind,
            "images": len(sources[n].names),
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
            "sd_px": sd[n]["intrinsics_px"],
            "dist_sd": sd[n]["dist"],
            "center_m": cameras[n].center.tolist(),
        }
        if "rvec_rad" in sd[n]:
            per_cam[n]["relative_to_" + names[0]] = {
                k: sd[n][k]
                for k in ("rvec_rad", "rvec_sd_rad", "tvec_m", "tvec_sd_m", "baseline_sd_m")
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
            "inverted": board.inverted,
            "lab_origin_in_board": board.lab_origin.tolist(),
        },
        "reference_image": reference,
        "rms_px": _rms(np.concatenate(all_r)) if all_r else 0.0,
        "residual_sd_px": sigma,
        "baselines_m": {n: float(np.linalg.norm(cameras[n].center - c0)) for n in names[1:]},
        "baselines_sd_m": {n: sd[n]["baseline_sd_m"] for n in names[1:]},
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


__all__ = ["Calibration", "CalibrationWarning", "calibrate_rig", "calibrate_rig_detailed"]
