"""Steps 3–7 of a rig calibration (:mod:`surfphase.calib.solve`): the cameras' poses
relative to camera 0, moments whose views do not fit one board pose split, the joint
bundle adjustment with view rejection, its checks, and the cameras in the lab frame.

A *moment* is a board pose: the views of several cameras taken at the same time share
one, and a view split off its moment keeps a pose of its own (key ``"<view>|<camera>"``).
``key_of`` maps each used view ``(camera, view)`` to its moment; the steps update it.
``single[camera] = (K, dist, {view: board pose in that camera})`` are the single-camera
calibrations (step 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfphase.calib import checks
from surfphase.calib.board import BoardSpec
from surfphase.calib.bundle import _angle, _bundle_adjust, _mat_to_rt, _Problem, _rms, _rt_to_mat
from surfphase.calib.detect import Detection
from surfphase.cameras import Camera

#: Fewest moments shared with camera 0 for a camera's extrinsics to be checked.
MIN_SHARED = 3


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


def initial_extrinsics(single: dict, names: list[str], sources: dict, where: str) -> list:
    """Poses (6,) of cameras 1.. relative to camera 0 (zeros for camera 0): the medoid of
    the shared views' estimates."""
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
    return extr


def _counts(key_of: dict) -> dict[str, int]:
    """Views per moment."""
    count: dict[str, int] = {}
    for k in key_of.values():
        count[k] = count.get(k, 0) + 1
    return count


@dataclass
class Moments:
    """The views of a rig and the board poses they belong to (see the module doc)."""

    names: list[str]
    single: dict
    detections: dict[str, dict[str, Detection]]
    n_dist: int

    def initial_poses(self, key_of: dict, extr: list, known: dict | None = None) -> dict:
        """``known`` with each other moment's board pose from its first camera's own
        calibration, through that camera's ``extr``."""
        poses = dict(known or {})
        for c, n in enumerate(self.names):
            for (m, i), k in sorted(key_of.items()):
                if m == n and k not in poses:
                    poses[k] = _in_cam0(self.single[n][2][i], extr[c])
        return poses

    def setup(self, key_of: dict, shared_only: bool = False):
        """The problem over the views of ``key_of`` (only moments of several views, with
        ``shared_only``: with the intrinsics held, a view alone fits its own pose and
        moves nothing else). Returns (moment keys, problem, active views, view ids)."""
        names = self.names
        count = _counts(key_of)
        view_ids = [
            (n, i)
            for n in names
            for i in sorted(self.detections[n])
            if (n, i) in key_of and (count[key_of[(n, i)]] > 1 or not shared_only)
        ]
        keys = sorted({key_of[v] for v in view_ids})
        index = {k: j for j, k in enumerate(keys)}
        problem = _Problem(len(names), keys, self.n_dist)
        c_of = {n: c for c, n in enumerate(names)}
        active = [(c_of[n], index[key_of[(n, i)]], self.detections[n][i]) for n, i in view_ids]
        return keys, problem, active, view_ids

    def alone_poses(self, key_of: dict, extr: list, poses: dict) -> dict:
        """``poses`` with each single view's board pose from its camera's own calibration
        (optimal while the intrinsics are held), through that camera's ``extr``."""
        count = _counts(key_of)
        out = dict(poses)
        for c, n in enumerate(self.names):
            for (m, i), k in key_of.items():
                if m == n and count[k] == 1:
                    out[k] = _in_cam0(self.single[n][2][i], extr[c])
        return out


def _held_fit(mo: Moments, key_of: dict, Ks, dists, extr, poses, robust: float | None = None):
    """Extrinsics and shared moments' poses fitted with the intrinsics held: (x,
    per-view residuals, problem, view ids); x None when no moment has several views."""
    keys, problem, active, view_ids = mo.setup(key_of, shared_only=True)
    if not active:
        return None, [], problem, view_ids
    x = problem.pack(Ks, dists, extr, {k: poses[k] for k in keys})
    free = np.ones(x.size, dtype=bool)
    free[: problem.o_extr] = False
    x, per_view = _bundle_adjust(problem, x, active, robust_scale=robust, free=free)
    return x, per_view, problem, view_ids


def _split_off(key_of: dict, view_ids: list, bad: dict, max_view_rms: float) -> list[dict]:
    """Split the worst moments of ``bad`` ({moment: RMS px}): every view but the first
    keeps its own pose. Returns the split records."""
    split = []
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
    return split


def split_moments(
    mo: Moments, key_of: dict, Ks, dists, extr, max_view_rms: float, max_refits: int
) -> tuple[list, dict, list[dict]]:
    """Step 3: intrinsics held, robust; split moments whose views do not fit together.

    Updates ``key_of``; returns (extrinsics, board poses, split records)."""
    split: list[dict] = []
    poses = mo.initial_poses(key_of, extr)
    for _ in range(max(1, max_refits)):
        x, per_view, problem, view_ids = _held_fit(
            mo, key_of, Ks, dists, extr, poses, robust=max_view_rms
        )
        if x is None:  # every shared moment was split: the check below says so
            break
        _, _, extr, poses = problem.unpack(x)
        rms = {v: _rms(r) for v, r in zip(view_ids, per_view, strict=True)}
        count = _counts({v: key_of[v] for v in view_ids})
        bad: dict[str, float] = {}
        for v in view_ids:
            if count[key_of[v]] > 1 and rms[v] > max_view_rms:
                bad[key_of[v]] = max(bad.get(key_of[v], 0.0), rms[v])
        if not bad:
            break
        split += _split_off(key_of, view_ids, bad, max_view_rms)
        poses = mo.initial_poses(key_of, extr, poses)
    return extr, poses, split


def tie_warnings(
    names: list[str], key_of: dict, split: list[dict], sync: dict, sources: dict, where: str
) -> list[str]:
    """Stop when a camera shares no consistent moment with camera 0; warn when most of
    its shared moments were split or too few remain to check its pose."""
    warn = []
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
    return warn


@dataclass
class Solution:
    """A fit of every view of ``key_of``: ``x`` in ``problem``'s layout."""

    keys: list
    problem: _Problem
    active: list
    view_ids: list
    x: np.ndarray
    per_view: list

    @property
    def index(self) -> dict:
        """Moment → pose index in ``problem``."""
        return {k: j for j, k in enumerate(self.keys)}


def joint_solve(
    mo: Moments, key_of: dict, Ks, dists, extr, poses, rejected: dict, max_view_rms: float,
    max_refits: int, min_images: int, sources: dict, where: str,
) -> Solution:  # fmt: skip
    """Step 4: everything free, plain least squares; reject views that still do not fit
    (recorded in ``rejected``, removed from ``key_of``)."""
    for _ in range(max(1, max_refits)):
        keys, problem, active, view_ids = mo.setup(key_of)
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
        for n in mo.names:
            used = sum(1 for m, _ in key_of if m == n)
            if used < min_images:
                raise ValueError(
                    f"{where}only {used} views of {sources[n].label} fit the calibration "
                    f"(need {min_images}); views with reprojection RMS above "
                    f"{max_view_rms} px were rejected"
                )
    return Solution(keys, problem, active, view_ids, x, per_view)


def held_intrinsics_solve(mo: Moments, key_of: dict, held: tuple[list, dict]) -> Solution:
    """The single-camera intrinsics kept, only the extrinsics and board poses solved
    (from step 3's ``held`` extrinsics and poses); the residuals of every view."""
    Ks = [mo.single[n][0] for n in mo.names]
    dists = [mo.single[n][1] for n in mo.names]
    extr, poses = held
    x, _, problem, _ = _held_fit(mo, key_of, Ks, dists, extr, poses)
    _, _, extr, shared_poses = problem.unpack(x)
    poses = mo.alone_poses(key_of, extr, {**poses, **shared_poses})
    keys, problem, active, view_ids = mo.setup(key_of)
    x = problem.pack(Ks, dists, extr, {k: poses[k] for k in keys})
    res = problem.residuals(x, active)[0]
    bounds = np.cumsum([0] + [2 * len(d) for _, _, d in active])
    per_view = [res[a:b].reshape(-1, 2) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    return Solution(keys, problem, active, view_ids, x, per_view)


def extrinsics_checks(
    mo: Moments, key_of: dict, sol: Solution, check: dict, where: str
) -> list[str]:
    """Each camera's pose against the per-view estimates of the moments it shares with
    camera 0 (figures into ``check``); returns the warnings."""
    names, warn = mo.names, []
    for c, n in enumerate(names[1:], start=1):
        tied = sorted(
            i
            for (m, i), k in key_of.items()
            if m == n and k == i and (names[0], i) in key_of and key_of[(names[0], i)] == i
        )
        per_view_rt = [_relative(mo.single[names[0]][2][i], mo.single[n][2][i]) for i in tied]
        Re, te = _rt_to_mat(*np.split(sol.problem.extrinsics(sol.x, c), 2))
        figures, w = checks.extrinsics_warnings(n, names[0], Re, te, per_view_rt, where)
        check[n].update(figures)
        warn += w
    return warn


def board_distances(names: list[str], sol: Solution) -> dict[str, float]:
    """Median distance (board units) from each camera to the board centre of its views."""
    problem, x = sol.problem, sol.x
    distances = {}
    for c, n in enumerate(names):
        d = []
        for cc, i, det in sol.active:
            if cc != c:
                continue
            Rb, tb = _rt_to_mat(*np.split(problem.pose(x, i), 2))
            Re, te = _rt_to_mat(*np.split(problem.extrinsics(x, c), 2))
            d.append(np.linalg.norm(Re @ (Rb @ det.object_points.mean(axis=0) + tb) + te))
        distances[n] = float(np.median(d))
    return distances


def lab_cameras(
    names: list[str], sizes: dict, sol: Solution, board: BoardSpec, reference: str
) -> dict[str, Camera]:
    """Step 7: the cameras in the lab frame, from the reference view's board pose."""
    problem, x = sol.problem, sol.x
    Rb, tb = _rt_to_mat(*np.split(problem.pose(x, sol.index[reference]), 2))
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
    return cameras
