"""Checks of a rig calibration against independent estimates, and of its units.

The joint solve can fit its corners well (a low RMS) and still be wrong: inconsistent
pairs of views pull a camera's intrinsics to where the pairs agree. Each camera's
intrinsics are therefore compared with its own single-camera ``cv2.calibrateCamera``,
and each baseline with the median of the baselines the shared views give one by one
(each from the two cameras' single-camera board poses). Disagreements are warnings
that name the camera and the figures.

Lengths in the wrong unit (a board given in millimetres where metres are expected)
fit just as well, scaled: they are caught by the cameras' distance from the board.
"""

from __future__ import annotations

import numpy as np

#: fx of the joint solve within this fraction of the single-camera calibration's fx.
MAX_FOCAL_DIFF = 0.03
#: Principal point of the joint solve within this many pixels of the single-camera one.
MAX_PP_DIFF_PX = 25.0
#: Baseline within this fraction of the median of the per-view baselines.
MAX_BASELINE_DIFF = 0.03
#: Relative rotation within this angle (degrees) of the per-view estimates' median.
MAX_ROTATION_DIFF_DEG = 2.0
#: A camera farther than this from the board (median over its views) means lengths in
#: the wrong unit: the board's lengths are metres.
MAX_BOARD_DISTANCE_M = 10.0


def intrinsics_warnings(
    camera: str, joint: np.ndarray, single: np.ndarray, where: str = ""
) -> tuple[dict, list[str]]:
    """Compare the (3, 3) intrinsics of the joint solve with the single-camera ones.

    Returns ``(figures, warnings)``: the relative fx difference, the principal point
    distance (px) and a warning per check that fails (fx: :data:`MAX_FOCAL_DIFF`,
    principal point: :data:`MAX_PP_DIFF_PX`).
    """
    dfx = float(joint[0, 0] / single[0, 0] - 1)
    dpp = float(np.hypot(joint[0, 2] - single[0, 2], joint[1, 2] - single[1, 2]))
    out = []
    if abs(dfx) > MAX_FOCAL_DIFF:
        out.append(
            f"{where}{camera}: the joint solve's fx {joint[0, 0]:.1f} px differs by "
            f"{100 * dfx:+.1f} % from the single-camera calibration's {single[0, 0]:.1f} px "
            f"(limit {100 * MAX_FOCAL_DIFF:g} %)"
        )
    if dpp > MAX_PP_DIFF_PX:
        out.append(
            f"{where}{camera}: the joint solve's principal point ({joint[0, 2]:.1f}, "
            f"{joint[1, 2]:.1f}) px is {dpp:.1f} px from the single-camera calibration's "
            f"({single[0, 2]:.1f}, {single[1, 2]:.1f}) px (limit {MAX_PP_DIFF_PX:g} px)"
        )
    return {"fx_rel_diff": dfx, "pp_diff_px": dpp}, out


def mean_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    """The rotation nearest (Frobenius) to the mean of ``Rs`` (each (3, 3))."""
    U, _, Vt = np.linalg.svd(np.mean(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def extrinsics_warnings(
    camera: str,
    reference: str,
    R: np.ndarray,
    t: np.ndarray,
    per_view: list[tuple[np.ndarray, np.ndarray]],
    where: str = "",
) -> tuple[dict, list[str]]:
    """Compare camera ``camera``'s pose relative to ``reference`` with per-view estimates.

    Args:
        R, t: the joint solve's ``x_cam = R x_ref + t`` (metres).
        per_view: ``(R_k, t_k)`` of the same from each shared view alone.

    Returns ``(figures, warnings)``: the baseline ``|t|``, the per-view baselines'
    median and their relative difference (:data:`MAX_BASELINE_DIFF`), and the angle
    between ``R`` and the per-view rotations' mean (:data:`MAX_ROTATION_DIFF_DEG`).
    """
    baseline = float(np.linalg.norm(t))
    second = float(np.median([np.linalg.norm(tk) for _, tk in per_view]))
    Rm = mean_rotation([Rk for Rk, _ in per_view])
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R @ Rm.T) - 1) / 2, -1.0, 1.0))))
    diff = baseline / second - 1
    out = []
    if abs(diff) > MAX_BASELINE_DIFF:
        out.append(
            f"{where}{camera}: the joint solve's baseline to {reference}, {baseline:.4g} m, "
            f"differs by {100 * diff:+.1f} % from the median of the {len(per_view)} shared "
            f"views' own baselines, {second:.4g} m (limit {100 * MAX_BASELINE_DIFF:g} %)"
        )
    if angle > MAX_ROTATION_DIFF_DEG:
        out.append(
            f"{where}{camera}: the joint solve's rotation relative to {reference} is "
            f"{angle:.1f}° from the mean of the {len(per_view)} shared views' own rotations "
            f"(limit {MAX_ROTATION_DIFF_DEG:g}°)"
        )
    figures = {
        "baseline_m": baseline,
        "per_view_median_baseline_m": second,
        "baseline_rel_diff": float(diff),
        "rotation_diff_deg": angle,
        "shared_views": len(per_view),
    }
    return figures, out


def check_units(
    distances: dict[str, float], square_length: float, marker_length: float, where: str = ""
) -> None:
    """Raise ValueError when a camera is implausibly far from the board.

    ``distances``: ``{camera: median board distance (m)}``. Farther than
    :data:`MAX_BOARD_DISTANCE_M` means the board's lengths are not in metres; the
    message says what they would be in millimetres or centimetres.
    """
    far = {n: d for n, d in distances.items() if d > MAX_BOARD_DISTANCE_M}
    if not far:
        return
    worst = max(far.values())
    cams = ", ".join(f"{n} {d:.4g} m" for n, d in far.items())
    guesses = "; ".join(
        f"in {unit} they are {square_length / f:g} and {marker_length / f:g} m (cameras "
        f"{worst / f:.3g} m away)"
        for unit, f in (("millimetres", 1000.0), ("centimetres", 100.0))
        if worst / f <= MAX_BOARD_DISTANCE_M
    )
    raise ValueError(
        f"{where}the cameras are implausibly far from the board ({cams}, median over "
        f"their views; limit {MAX_BOARD_DISTANCE_M:g} m): the board's lengths must be in "
        f"metres, and square_length {square_length:g}, marker_length {marker_length:g} "
        f"are not" + (f": if they are {guesses}" if guesses else "")
    )
