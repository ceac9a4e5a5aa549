"""``surfphase calibrate``: calibrate a rig from ChArUco images (cameras.json + report)."""

from __future__ import annotations

import argparse
import json
import time
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

    dirs = parse_cam_args(args.cam)
    cal = calibrate_rig_detailed(
        Path(args.board),
        dirs,
        min_images=args.min_images,
        rig=args.rig,
        max_view_rms=args.max_view_rms,
    )
    write_calibration(Path(args.out), cal)
    r = cal.report
    print(
        f"rig {args.rig}: RMS {r['rms_px']:.3f} px; "
        + ", ".join(f"{n} {c['images_used']} images" for n, c in r["cameras"].items())
        + f"; wrote {args.out}"
    )
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate a camera rig from ChArUco images",
        description="Detect ChArUco corners, solve intrinsics, distortion and extrinsics of "
        "all cameras in the lab frame; write OUT/cameras.json, OUT/report.json, "
        "OUT/corners.png.",
    )
    p.add_argument("--rig", required=True, help="rig id (used in messages and the report)")
    p.add_argument("--board", required=True, help="board YAML")
    p.add_argument(
        "--cam",
        action="append",
        required=True,
        metavar="NAME=DIR",
        help="a camera's folder of calibration images; the first is camera 0",
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
    rows = {}
    for n in inputs:
        c, g = cal.cameras[n], true[n]
        dR = c.R @ g.R.T
        rows[n] = {
            "focal_err_pct": float(100 * np.max(np.abs(np.diag(c.K)[:2] / np.diag(g.K)[:2] - 1))),
            "pp_err_px": float(np.max(np.abs(c.K[:2, 2] - g.K[:2, 2]))),
            "pp_sd_px": float(max(cal.report["cameras"][n]["sd_px"][k] for k in ("cx", "cy"))),
            "rot_err_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
            "rms_px": cal.report["cameras"][n]["rms_px"],
        }
    c0, c1 = inputs[:2]
    b = np.linalg.norm(cal.cameras[c1].center - cal.cameras[c0].center)
    bt = np.linalg.norm(true[c1].center - true[c0].center)
    out = {
        "poses": args.poses,
        "seed": args.seed,
        "render_s": round(t1 - t0, 2),
        "calibrate_s": round(t2 - t1, 2),
        "baseline_err_pct": float(100 * abs(b / bt - 1)),
        "cameras": rows,
    }
    print(json.dumps(out, indent=1))
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "calibrate", help="calibration accuracy and time on the synthetic rig"
    )
    p.add_argument("--poses", type=int, default=20, help="calibration poses to render")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_bench)
