"""``surfphase ingest``: a session's recordings → undistorted frame stacks."""

from __future__ import annotations

import argparse
from pathlib import Path

from surfphase.commands.calibrate import parse_cam_args


def parse_crop(text: str | None) -> tuple[int, int, int, int] | None:
    """``"x0,y0,w,h"`` → a tuple of ints (pixels), or None for no crop."""
    if text is None or text.strip() in ("", "none", "None"):
        return None
    parts = text.split(",")
    try:
        values = tuple(int(p) for p in parts)
    except ValueError as e:
        raise ValueError(f"--crop expects x0,y0,w,h integers, not {text!r}") from e
    if len(values) != 4:
        raise ValueError(f"--crop expects x0,y0,w,h integers, not {text!r}")
    return values


def _parse_scale(text: str) -> float | str:
    """``--scale``: a factor in (0, 1] or ``auto``."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError as e:
        raise ValueError(f"--scale expects a number in (0, 1] or auto, not {text!r}") from e


def _missing_cameras(session: str, rig: str | None, rigs_sheet: str | None, path: Path):
    """Raise the most useful error for a missing ``cameras.json``."""
    if rig and rigs_sheet and Path(rigs_sheet).is_file():
        import pandas as pd

        rigs = pd.read_csv(rigs_sheet, sep="\t", dtype=str, comment="#")
        if "rig" in rigs.columns and rig not in set(rigs["rig"].str.strip()):
            raise ValueError(f"session {session}: rig {rig} is not a row of {rigs_sheet}")
    which = f"of rig {rig} " if rig else ""
    raise FileNotFoundError(
        f"session {session}: calibration {which}not found: {path} (run calibrate first)"
    )


def _run(args: argparse.Namespace) -> int:
    from surfphase.cameras import load_cameras
    from surfphase.ingest import ingest_session

    cams_path = Path(args.cameras)
    if not cams_path.is_file():
        _missing_cameras(args.session, args.rig, args.rigs_sheet, cams_path)
    meta = ingest_session(
        args.session,
        load_cameras(cams_path),
        parse_cam_args(args.cam),
        fps=args.fps,
        frames=args.frames,
        scale=_parse_scale(args.scale),
        crop=parse_crop(args.crop),
        out=Path(args.out),
        fit_size=args.fit_size,
        native=args.native_masks,
    )
    sizes = ", ".join(
        f"{n} {c['count']}×{c['size'][1]}×{c['size'][0]}" for n, c in meta["cameras"].items()
    )
    print(f"session {args.session}: {sizes} (scale {meta['scale']:.4g}); wrote {args.out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "ingest",
        help="undistort a session's recordings into frame stacks",
        description="Read each camera's recording (video file, image folder or multi-page "
        "TIFF; 8 or 16 bit), keep the frame range, undistort with the rig's calibration, "
        "crop and downscale; write OUT/<cam>.npy (float32 in [0, 1]), OUT/cameras.json, "
        "OUT/meta.json.",
    )
    p.add_argument("--session", required=True, help="session id")
    p.add_argument("--cameras", required=True, help="the rig's cameras.json (from calibrate)")
    p.add_argument("--rig", default=None, help="the session's rig id (for messages)")
    p.add_argument(
        "--rigs-sheet", default=None, help="rigs.tsv, to say when the rig is not a row of it"
    )
    p.add_argument(
        "--cam", action="append", required=True, metavar="NAME=PATH", help="a camera's recording"
    )
    p.add_argument("--fps", type=float, required=True, help="frame rate, frames per second")
    p.add_argument("--frames", default=None, help="start:stop[:step] (stop exclusive)")
    p.add_argument(
        "--scale", default="1.0", help="downscale factor, e.g. 0.25, or auto (see --fit-size)"
    )
    p.add_argument(
        "--fit-size",
        type=int,
        default=None,
        help="with --scale auto: the fitted frame's longer side, pixels",
    )
    p.add_argument("--crop", default=None, help="x0,y0,w,h pixels of the undistorted image")
    p.add_argument(
        "--native-masks",
        action="store_true",
        help="also keep the undistorted frames before downscaling (OUT/native/, uint16) for "
        "the mask stage",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=_run)
