"""Are the calibration's stated uncertainties honest? Synthetic rigs with known truth.

Each trial draws a rig (the synthetic rig of :func:`surfphase.synth.rig.default_rig`
with its baseline angle, focal length, working distance and lens distortion drawn at
random), renders its ChArUco views (:mod:`surfphase.synth.charuco`), calibrates it and
compares every stated 1-sigma uncertainty with the true error:

* per camera ``fx``, ``fy``, ``cx``, ``cy`` (px);
* per camera after the first, its pose relative to camera 0 (``x_c = R x_0 + t``):
  the three rvec components (rad, error = estimated − true Rodrigues vector), the three
  tvec components (m) and the baseline ``|t|`` (m).

Honest means: the true error lies within 3 stated sd in at least 95 % of the cases,
and the stated sd is not more than 3× the observed spread (RMS) of the errors.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import cv2
import numpy as np

#: Honesty targets: coverage of |error| <= 3 sd, and most stated sd / observed spread.
MIN_COVERAGE_3SD = 0.95
MAX_SD_OVER_SPREAD = 3.0


def random_rig(seed: int, native: int = 512) -> dict:
    """A synthetic rig drawn from ``seed``: ``{name: Camera}`` (see the module doc)."""
    from surfphase.synth.rig import default_rig

    rng = np.random.default_rng([7919, seed])

    def lens() -> tuple[float, ...]:
        return (
            rng.uniform(-0.15, -0.05),
            rng.uniform(0.0, 0.1),
            rng.uniform(-6e-4, 6e-4),
            rng.uniform(-6e-4, 6e-4),
            0.0,
        )

    return default_rig(
        native=native,
        distance=rng.uniform(0.026, 0.034),
        fx=rng.uniform(820.0, 980.0),
        baseline_deg=rng.uniform(25.0, 45.0),
        dist0=lens(),
        dist1=lens(),
    )


def trial(seed: int, n_poses: int = 20, native: int = 512) -> list[dict]:
    """Calibrate rig ``seed``; one row per stated quantity: ``quantity`` (e.g.
    ``cam1.fx``), ``kind`` (``fx``, ``cx``, ``rvec``, ``tvec``, ``baseline``...),
    ``error`` (estimate − truth) and ``sd`` (stated)."""
    from surfphase.calib.board import board_from_dict
    from surfphase.calib.solve import calibrate_rig_detailed
    from surfphase.synth.charuco import board_yaml_dict, write_calibration_images

    true = random_rig(seed, native)
    inputs = [n for n, c in true.items() if c.role == "input"]
    with tempfile.TemporaryDirectory() as tmp:
        write_calibration_images(true, Path(tmp), seed=seed, n_poses=n_poses)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cal = calibrate_rig_detailed(
                board_from_dict(board_yaml_dict()),
                {n: Path(tmp) / n for n in inputs},
                rig=f"synthetic{seed}",
            )
    rows = []
    rep = cal.report
    for n in inputs:
        est, g = cal.cameras[n].K, true[n].K
        sd = rep["cameras"][n]["sd_px"]
        for k, (i, j) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
            rows.append(
                {"quantity": f"{n}.{k}", "kind": k, "error": est[i, j] - g[i, j], "sd": sd[k]}
            )
    c0 = inputs[0]
    for n in inputs[1:]:
        Rt = true[n].R @ true[c0].R.T
        tt = true[n].t - Rt @ true[c0].t
        rel = rep["cameras"][n]["relative_to_" + c0]
        rt, _ = cv2.Rodrigues(Rt)
        for a in range(3):
            rows.append(
                {
                    "quantity": f"{n}.rvec{a}",
                    "kind": "rvec",
                    "error": rel["rvec_rad"][a] - float(rt.ravel()[a]),
                    "sd": rel["rvec_sd_rad"][a],
                }
            )
            rows.append(
                {
                    "quantity": f"{n}.tvec{a}",
                    "kind": "tvec",
                    "error": rel["tvec_m"][a] - float(tt[a]),
                    "sd": rel["tvec_sd_m"][a],
                }
            )
        rows.append(
            {
                "quantity": f"{n}.baseline",
                "kind": "baseline",
                "error": float(np.linalg.norm(rel["tvec_m"]) - np.linalg.norm(tt)),
                "sd": rel["baseline_sd_m"],
            }
        )
    for r in rows:
        r["seed"] = seed
        r["warnings"] = len(rep["warnings"]) + sum(
            1 for w in caught if "Calibration" in type(w.message).__name__
        )
    return rows


def summarise(rows: list[dict]) -> dict:
    """Coverage and sd/spread per kind of quantity, and overall; ``honest`` per the
    module doc's targets."""
    out = {}
    kinds = sorted({r["kind"] for r in rows})
    for kind in [*kinds, "all"]:
        sel = [r for r in rows if kind in ("all", r["kind"])]
        err = np.array([r["error"] for r in sel])
        sd = np.array([r["sd"] for r in sel])
        cover = float(np.mean(np.abs(err) <= 3 * sd))
        entry = {"n": len(sel), "coverage_3sd": cover}
        if kind != "all":
            spread = float(np.sqrt(np.mean(err**2)))
            stated = float(np.sqrt(np.mean(sd**2)))
            entry.update(
                {
                    "error_rms": spread,
                    "sd_rms": stated,
                    "sd_over_spread": stated / spread if spread > 0 else float("inf"),
                }
            )
        out[kind] = entry
    ratios = [v["sd_over_spread"] for k, v in out.items() if k != "all"]
    out["honest"] = bool(
        out["all"]["coverage_3sd"] >= MIN_COVERAGE_3SD and max(ratios) <= MAX_SD_OVER_SPREAD
    )
    out["warnings"] = int(sum(r["warnings"] for r in {r["seed"]: r for r in rows}.values()))
    return out


def run(n_rigs: int = 20, n_poses: int = 20, native: int = 512, first_seed: int = 0) -> dict:
    """``n_rigs`` trials (seeds ``first_seed``...): ``{"rows": [...], "summary": {...}}``."""
    rows = []
    for seed in range(first_seed, first_seed + n_rigs):
        rows += trial(seed, n_poses=n_poses, native=native)
    return {"rows": rows, "summary": summarise(rows)}


__all__ = ["MAX_SD_OVER_SPREAD", "MIN_COVERAGE_3SD", "random_rig", "run", "summarise", "trial"]
