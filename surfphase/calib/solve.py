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

Steps 1–2 are here; steps 3–7 are :mod:`surfphase.calib.joint`, the bundle adjustment
itself :mod:`surfphase.calib.bundle`.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from surfphase.calib import checks, joint
from surfphase.calib.board import BoardSpec, load_board
from surfphase.calib.bundle import _covariance, _rms, _uncertainties
from surfphase.calib.detect import (
    Detection,
    detect_view,
    diagnose,
    make_detector,
    marker_corners,
    usable,
)
from surfphase.calib.sources import FrameSource, open_sources
from surfphase.cameras import Camera

#: With the board's polarity automatic, a camera whose views were all found in one
#: polarity, this many of them, is no longer tried in the other.
STICKY_POLARITY = 5
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
    """Corners in every view: (detections, rejected, sizes, polarity counts, the
    cameras whose reference view is its whole markers' corners: ``{camera: warning}``)."""
    detector = make_detector(board)
    detections: dict[str, dict[str, Detection]] = {}
    rejected: dict[str, list[dict]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    polarity: dict[str, dict[str, int]] = {}
    markers_only: dict[str, str] = {}
    for n, src in sources.items():
        detections[n], rejected[n] = {}, []
        polarity[n] = {"normal": 0, "inverted": 0}
        missing = []
        reference = None
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
            if why is not None and name == board.reference_image:
                reference = (name, img, len(det), order)
            if why is None:
                detections[n][name] = det
                polarity[n]["inverted" if inverted else "normal"] += 1
            else:
                rejected[n].append({"image": name, "reason": why})
                if why == "board not found" or len(det) < min_corners:
                    missing.append(name)
        if reference is not None and len(detections[n]) >= min_images:
            # The lab frame's view, where the board as described is found in the
            # camera's other views: standing at the bubbles it may fill a narrow view,
            # which then holds too few ChArUco corners; its whole markers' corners give
            # its pose.
            name, img, corners, order = reference
            alt, inverted = marker_corners(img, board, detector, order)
            if usable(alt, min_corners) is None:
                detections[n][name] = alt
                polarity[n]["inverted" if inverted else "normal"] += 1
                rejected[n] = [r for r in rejected[n] if r["image"] != name]
                markers_only[n] = (
                    f"{where}{n}: the reference image {name} holds {corners} ChArUco "
                    f"corner(s) (need {min_corners}): the board is only partly in view; "
                    f"its pose, and the lab frame, come from the corners of its "
                    f"{len(alt) // 4} whole markers, which are less precise ({src.path})"
                )
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
    return detections, rejected, sizes, polarity, markers_only


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
    paths = {n: Path(p) for n, p in image_dirs.items()}
    sources, sync = open_sources(
        paths, timestamps, max_frames or MAX_FRAMES, sync_tolerance, where=where
    )
    names = list(sources)
    detections, rejected, sizes, polarity, markers_only = _detect(
        sources, board, min_corners, min_images, where
    )
    warn: list[str] = list(markers_only.values())
    if sync.get("warning"):
        warn.append(f"{where}{sync['warning']}")
    # Step 2: each camera alone.
    single = _single_cameras(
        detections, sizes, sources, rejected, fix_k3, max_view_rms, max_refits, min_images, where
    )
    reference = _reference_view(board, single, sources, where)
    # Step 3: the relative poses, intrinsics held; moments that do not fit are split.
    mo = joint.Moments(names, single, detections, 4 if fix_k3 else 5)
    key_of = {(n, i): i for n in names for i in single[n][2]}
    Ks = [single[n][0] for n in names]
    dists = [single[n][1] for n in names]
    extr = joint.initial_extrinsics(single, names, sources, where)
    extr, poses, split = joint.split_moments(mo, key_of, Ks, dists, extr, max_view_rms, max_refits)
    warn += joint.tie_warnings(names, key_of, split, sync, sources, where)
    # Step 4: everything free; views that still do not fit are rejected.
    poses = mo.alone_poses(key_of, extr, poses)
    held = (list(extr), dict(poses))  # step 3's solution
    sol = joint.joint_solve(
        mo, key_of, Ks, dists, extr, poses, rejected, max_view_rms, max_refits, min_images,
        sources, where,
    )  # fmt: skip
    if reference not in sol.index:
        raise ValueError(f"{where}the reference image {reference} was rejected (see the report)")
    # Step 5: checks against the single-camera calibrations and the per-view extrinsics.
    check, moved, sol = _intrinsics_checks(mo, key_of, sol, held, where)
    warn += moved
    warn += joint.extrinsics_checks(mo, key_of, sol, check, where)
    distances = joint.board_distances(names, sol)
    for n in names:
        check[n]["board_distance_m"] = distances[n]
    checks.check_units(distances, board.square_length, board.marker_length, where)
    # Steps 6 and 7: uncertainties; the lab frame from the reference view's board pose.
    cameras = joint.lab_cameras(names, sizes, sol, board, reference)
    residuals = _residuals(names, sol)
    cov, sigma = _covariance(sol.problem, sol.x, sol.active)
    sd = _uncertainties(sol.problem, sol.x, cov, names)
    if strict and warn:
        raise ValueError("; ".join(warn))
    for w in warn:
        warnings.warn(w, CalibrationWarning, stacklevel=2)
    report = _report(rig, board, reference, names, sources, cameras, residuals, rejected, sd, sigma)
    report.update(
        _report_extra(board, sync, split, polarity, single, names, check, bool(moved), warn)
    )
    report["reference_from_markers"] = sorted(markers_only)
    cal = Calibration(cameras, report, sources, detections, residuals)
    cal.single = {n: (single[n][0], single[n][1]) for n in names}
    return cal


def _residuals(names: list[str], sol: joint.Solution) -> dict[str, dict[str, np.ndarray]]:
    """``{camera: {view: (N, 2) reprojection errors, px}}`` of the views ``sol`` fits."""
    residuals: dict[str, dict[str, np.ndarray]] = {n: {} for n in names}
    for v, r in zip(sol.view_ids, sol.per_view, strict=True):
        residuals[v[0]][v[1]] = r
    return residuals


def _single_cameras(
    detections, sizes, sources, rejected, fix_k3, max_view_rms, max_refits, min_images, where
) -> dict:
    """Step 2: ``{camera: (K, dist, {view: board pose})}`` of each camera alone; its
    rejected views are added to ``rejected``."""
    single = {}
    for n in sources:
        K, dist, poses, rej = single_camera(
            detections[n], sizes[n], fix_k3, max_view_rms, max_refits
        )
        rejected[n] += rej
        w, h = sizes[n]
        cx, cy = float(K[0, 2]), float(K[1, 2])
        if not (0.0 <= cx <= w - 1 and 0.0 <= cy <= h - 1):
            raise ValueError(
                f"{where}the single-camera calibration of {sources[n].label} puts its "
                f"principal point at ({cx:.0f}, {cy:.0f}) px, outside its {w}×{h} images "
                f"(fx {K[0, 0]:.1f} px, {len(poses)} views kept, {len(rej)} rejected for "
                f"reprojection RMS above {max_view_rms} px): its views of the board do not "
                "determine the camera. Record more views of the board, tilted and filling "
                "more of the frame"
            )
        if len(poses) < min_images:
            raise ValueError(
                f"{where}only {len(poses)} views of {sources[n].label} fit a single-camera "
                f"calibration (need {min_images}); views with reprojection RMS above "
                f"{max_view_rms} px were rejected"
            )
        single[n] = (K, dist, poses)
    return single


def _reference_view(board: BoardSpec, single: dict, sources: dict, where: str) -> str:
    """The view whose board pose gives the lab frame: the board's ``reference_image``,
    else camera 0's first view."""
    names = list(sources)
    if board.reference_image:
        reference = board.reference_image
        if not any(reference in single[n][2] for n in names):
            raise ValueError(
                f"{where}the board is not found (or does not fit) in the reference image "
                f"{reference} ({', '.join(str(sources[n].path) for n in names)})"
            )
        return reference
    return sorted(single[names[0]][2])[0]


def _intrinsics_checks(
    mo: joint.Moments, key_of: dict, sol: joint.Solution, held: tuple, where: str
) -> tuple[dict, list[str], joint.Solution]:
    """Each camera's joint intrinsics against its single-camera calibration. When the
    joint solve moved some, the single-camera intrinsics are kept and only the
    extrinsics and board poses solved (:func:`surfphase.calib.joint.held_intrinsics_solve`).

    Returns (per-camera check figures, warnings, the solution kept)."""
    check: dict[str, dict] = {n: {} for n in mo.names}
    moved, moved_cams = [], []
    for c, n in enumerate(mo.names):
        K, _ = sol.problem.intrinsics(sol.x, c)
        figures, w = checks.intrinsics_warnings(n, K, mo.single[n][0], where)
        check[n].update({"joint_" + k: v for k, v in figures.items()})
        moved += w
        moved_cams += [n] if w else []
    if not moved:
        return check, moved, sol
    # The shared views pull the intrinsics away from what each camera's own views
    # say: keep those, and solve only the extrinsics and board poses with them.
    moved.append(
        f"{where}the joint solve moved the intrinsics of {', '.join(moved_cams)} away "
        "from the single-camera calibrations (above): the shared views do not agree with each camera's own "
        "views (unsynchronised frames, a board that is not flat, or too few shared "
        "views). The intrinsics are kept from the single-camera calibrations and only "
        "the extrinsics and board poses are solved; check the extrinsics"
    )
    return check, moved, joint.held_intrinsics_solve(mo, key_of, held)


def _report_extra(board, sync, split, polarity, single, names, check, moved, warn) -> dict:
    """The report's entries beyond :func:`_report`: sync, split moments, polarity,
    single-camera figures, checks, where the intrinsics come from, warnings."""
    return {
        "sync": sync,
        "split_moments": split,
        "polarity": {
            "from": "board key inverted: " + ("true" if board.inverted else "false")
            if board.inverted is not None
            else "found automatically (each view tried as it is, then inverted)",
            "views": polarity,
        },
        "single_camera": {
            n: {
                "fx": float(single[n][0][0, 0]),
                "fy": float(single[n][0][1, 1]),
                "cx": float(single[n][0][0, 2]),
                "cy": float(single[n][0][1, 2]),
                "views": len(single[n][2]),
            }
            for n in names
        },
        "checks": check,
        "intrinsics_from": "single-camera calibrations (the joint solve disagreed)"
        if moved
        else "joint solve",
        "warnings": warn,
    }


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
