"""``surfphase calibrate``: calibrate a rig from ChArUco views (cameras.json + report).

Each camera's views are a folder of images or a recording (video, TIFF stack, Photron,
Phantom), sampled and optionally paired by a timestamps file
(:mod:`surfphase.calib.sources`). Checks that fail (:mod:`surfphase.calib.checks`) are
printed to stderr as ``WARNING`` lines and listed in ``report.json``'s ``warnings``;
``--strict`` makes them errors.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np


def parse_cam_args(values: list[str], option: str = "--cam") -> dict[str, Path]:
    """``["cam0=DIR", "cam1=DIR"]`` → ``{"cam0": Path(DIR), ...}`` (order kept)."""
    out: dict[str, Path] = {}
    for v in values:
        name, sep, path = v.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"{option} expects NAME=PATH, not {v!r}")
        if name in out:
            raise ValueError(f"{option}: camera {name} given twice")
        out[name] = Path(path)
    return out


def _run(args: argparse.Namespace) -> int:
    from surfphase.calib import calibrate_rig_detailed, write_calibration
    from surfphase.calib.solve import CalibrationWarning

    dirs = parse_cam_args(args.cam)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)  # printed below, once each
        cal = calibrate_rig_detailed(
            Path(args.board),
            dirs,
            min_images=args.min_images,
            rig=args.rig,
            max_view_rms=args.max_view_rms,
            timestamps=Path(args.timestamps) if args.timestamps else None,
            max_frames=args.max_frames,
            sync_tolerance=args.sync_tolerance,
            strict=args.strict,
        )
    write_calibration(Path(args.out), cal)
    r = cal.report
    for w in r["warnings"]:
        print(f"WARNING: {w}", file=sys.stderr)
    print(
        f"rig {args.rig}: RMS {r['rms_px']:.3f} px; "
        + ", ".join(f"{n} {c['images_used']} views" for n, c in r["cameras"].items())
        + f"; board polarity {r['polarity']['from']}; intrinsics from {r['intrinsics_from']}"
        + (f"; {len(r['warnings'])} WARNING(S), see above" if r["warnings"] else "")
        + f"; wrote {args.out}"
    )
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate a camera rig from ChArUco images or recordings",
        description="Detect ChArUco corners, solve intrinsics, distortion and extrinsics of "
        "all cameras in the lab frame; write OUT/cameras.json, OUT/report.json, "
        "OUT/corners.png. Each --cam is a folder of images (same file name = same moment) "
        "or a recording (video, TIFF stack, Photron, Phantom) whose frames are sampled.",
    )
    p.add_argument("--rig", required=True, help="rig id (used in messages and the report)")
    p.add_argument("--board", required=True, help="board YAML")
    p.add_argument(
        "--cam",
        action="append",
        required=True,
        metavar="NAME=PATH",
        help="a camera's folder of calibration images or its calibration recording; the "
        "first is camera 0",
    )
    p.add_argument(
        "--timestamps",
        help="CSV of per-frame capture times of the recordings (columns cam_id, frame_time "
        "in s, optional frame_index); only near-simultaneous frames are paired",
    )
    p.add_argument(
        "--max-frames",
        type=int,
        default=None,
        help="most frames sampled from each recording, evenly spaced (default: "
        "surfphase.calib.sources.MAX_FRAMES)",
    )
    p.add_argument(
        "--sync-tolerance",
        type=float,
        default=None,
        help="most seconds between paired frames (default: a quarter of the slower "
        "camera's median frame interval)",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="stop (instead of warning) when a check against the single-camera "
        "calibrations or the per-view extrinsics fails",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--min-images", type=int, default=6, help="fewest usable images per camera")
    p.add_argument(
        "--max-view-rms", type=float, default=1.0, help="reject views above this RMS (px)"
    )
    p.set_defaults(func=_run)


def _bench(args: argparse.Namespace) -> int:
    """Calibrate the synthetic rig; print accuracy against the true cameras and timings."""
    import tempfile

    from surfphase.calib import calibrate_rig_detailed
    from surfphase.calib.board import board_from_dict
    from surfphase.synth.charuco import board_yaml_dict, write_calibration_images
    from surfphase.synth.rig import default_rig

    true = default_rig()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_calibration_images(true, Path(tmp), seed=args.seed, n_poses=args.poses)
        t1 = time.perf_counter()
        inputs = [n for n, c in true.items() if c.role == "input"]
        cal = calibrate_rig_detailed(
            board_from_dict(board_yaml_dict()), {n: Path(tmp) / n for n in inputs}, rig="synthetic"
        )
        t2 = time.perf_counter()
    rows = {n: _camera_errors(cal, n, true[n]) for n in inputs}
    c0, c1 = inputs[:2]
    b = np.linalg.norm(cal.cameras[c1].center - cal.cameras[c0].center)
    bt = np.linalg.norm(true[c1].center - true[c0].center)
    out = {
        "poses": args.poses,
        "seed": args.seed,
        "render_s": round(t1 - t0, 2),
        "calibrate_s": round(t2 - t1, 2),
        "baseline_err_pct": float(100 * abs(b / bt - 1)),
        "warnings": cal.report["warnings"],
        "cameras": rows,
    }
    print(json.dumps(out, indent=1))
    return 0


def _camera_errors(cal, name: str, true) -> dict:
    """Camera ``name`` of a calibration (:class:`surfphase.calib.Calibration`) against
    its ``true`` camera: focal length (% , worse of fx, fy), principal point (px, worse
    axis), its stated sd (px), rotation (degrees, lab frame), reprojection RMS (px)."""
    c = cal.cameras[name]
    dR = c.R @ true.R.T
    return {
        "focal_err_pct": float(100 * np.max(np.abs(np.diag(c.K)[:2] / np.diag(true.K)[:2] - 1))),
        "pp_err_px": float(np.max(np.abs(c.K[:2, 2] - true.K[:2, 2]))),
        "pp_sd_px": float(max(cal.report["cameras"][name]["sd_px"][k] for k in ("cx", "cy"))),
        "rot_err_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
        "rms_px": cal.report["cameras"][name]["rms_px"],
    }


def _bench_campaign(args: argparse.Namespace) -> int:
    """Calibrate every rig of a synthetic campaign (``surfphase synth``'s ``rigs.tsv``)
    and compare each camera with the truth of the first session on that rig
    (``sessions.tsv``'s ``gt`` column: ``<gt>/cameras.json``); prints JSON: per rig the
    worse camera's errors and the views rejected, then the mean and worst over rigs."""
    import warnings

    import pandas as pd

    from surfphase.calib import calibrate_rig_detailed
    from surfphase.cameras import load_cameras
    from surfphase.sheets import camera_columns

    root = Path(args.campaign)
    rigs = pd.read_csv(root / "rigs.tsv", sep="\t", dtype=str)
    sessions = pd.read_csv(root / "sessions.tsv", sep="\t", dtype=str)
    out: dict[str, dict] = {}
    for r in rigs.to_dict("records"):
        gt = sessions.loc[sessions["rig"] == r["rig"], "gt"].dropna()
        if gt.empty:
            continue
        true = load_cameras(root / gt.iloc[0] / "cameras.json")
        names = [c for c in camera_columns(rigs.columns) if isinstance(r[c], str) and r[c]]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cal = calibrate_rig_detailed(
                root / r["board"], {n: root / r[n] for n in names}, rig=r["rig"]
            )
        errs = [_camera_errors(cal, n, true[n]) for n in names]
        out[r["rig"]] = {
            "focal_err_pct": max(e["focal_err_pct"] for e in errs),
            "pp_err_px": max(e["pp_err_px"] for e in errs),
            "rejected_views": sum(len(cal.report["cameras"][n]["rejected"]) for n in names),
            "warnings": len(caught),
        }
    keys = ("focal_err_pct", "pp_err_px")
    summary = {
        "rigs": len(out),
        **{f"mean_{k}": float(np.mean([v[k] for v in out.values()])) for k in keys},
        **{f"worst_{k}": float(np.max([v[k] for v in out.values()])) for k in keys},
        "rigs_warned": sum(v["warnings"] > 0 for v in out.values()),
    }
    print(json.dumps({"campaign": str(root), "summary": summary, "rigs": out}, indent=1))
    return 0


def _bench_uncertainty(args: argparse.Namespace) -> int:
    """Stated sd against true errors on synthetic rigs; prints the summary (JSON)."""
    from surfphase.calib.uncertainty import run

    t0 = time.perf_counter()
    out = run(args.rigs, n_poses=args.poses, native=args.native, first_seed=args.seed)
    summary = {
        "rigs": args.rigs,
        "poses": args.poses,
        "native": args.native,
        "seconds": round(time.perf_counter() - t0, 1),
        **out["summary"],
    }
    print(json.dumps(summary, indent=1))
    if args.rows:
        Path(args.rows).write_text(json.dumps(out["rows"], indent=1))
    return 0 if summary["honest"] else 1


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "calibrate", help="calibration accuracy and time on the synthetic rig"
    )
    p.add_argument("--poses", type=int, default=20, help="calibration poses to render")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_bench)
    p = bench_subparsers.add_parser(
        "calib-campaign",
        help="calibrate every rig of a synthetic campaign against its true cameras",
        description="Calibrate each rig of CAMPAIGN's rigs.tsv (a campaign `surfphase "
        "synth` wrote: its sessions' gt/cameras.json hold the truth) and print, per rig, "
        "the worse camera's focal length (%) and principal point (px) errors, the views "
        "rejected and the warnings, then the mean and worst over the rigs (JSON).",
    )
    p.add_argument("--campaign", required=True, help="a campaign folder `surfphase synth` wrote")
    p.set_defaults(func=_bench_campaign)
    p = bench_subparsers.add_parser(
        "calib-uncertainty",
        help="are the calibration's stated sd honest? synthetic rigs with known truth",
        description="Calibrate RIGS synthetic rigs drawn at random (baseline, focal length, "
        "distance, distortion) and compare every stated sd (fx, fy, cx, cy; relative "
        "rvec, tvec, baseline) with the true error: the fraction within 3 sd (target >= "
        "0.95) and the stated sd over the errors' RMS per kind (target <= 3). Exit status 1 "
        "when a target is missed.",
    )
    p.add_argument("--rigs", type=int, default=20, help="synthetic rigs (trials)")
    p.add_argument("--poses", type=int, default=20, help="board poses rendered per rig")
    p.add_argument("--native", type=int, default=512, help="image size (px) of the cameras")
    p.add_argument("--seed", type=int, default=0, help="first rig's seed")
    p.add_argument("--rows", help="also write every (quantity, error, sd) row to this JSON")
    p.set_defaults(func=_bench_uncertainty)
