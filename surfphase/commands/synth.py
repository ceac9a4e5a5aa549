"""``surfphase synth``: write a synthetic campaign; ``surfphase bench synth``: time it."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path


def _add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        default="demo",
        choices=["demo", "tiny", "bench", "bench-mixed", "bench-drawn"],
        help="base settings (bench: the varied sessions of `surfphase bench accuracy`; "
        "bench-mixed: their settings recombined by the seed; bench-drawn: settings drawn "
        "by the seed from the ranges the bench spans)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--sessions", type=int, help="number of capture sessions")
    p.add_argument("--frames", type=int, help="frames per session")
    p.add_argument("--fps", type=float, help="frame rate, frames/s")
    p.add_argument("--native", type=int, help="native (raw) frame size, pixels")
    p.add_argument("--bubbles", type=int, help="target mean number of bubbles in the column")
    p.add_argument("--clips", type=int, help="number of monocular clips")
    p.add_argument("--clip-frames", type=int, help="frames per monocular clip")
    p.add_argument("--mesh-spacing", type=float, help="truth grid spacing, metres")
    p.add_argument("--bit-depth", type=int, choices=[8, 16], help="PNG bit depth")


def _overrides(args: argparse.Namespace) -> dict:
    keys = ("sessions", "frames", "fps", "native", "bubbles", "clips", "clip_frames",
            "mesh_spacing", "bit_depth")  # fmt: skip
    return {k: getattr(args, k) for k in keys}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "synth",
        help="generate a synthetic pool-boiling campaign with ground truth",
        description="Write a self-contained synthetic campaign (videos, calibration images, "
        "sheets, ground truth, monocular clips) under --out.",
    )
    p.add_argument("--out", required=True, type=Path, help="campaign folder to create")
    p.add_argument("--force", action="store_true", help="replace a non-empty --out")
    _add_options(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from surfphase.synth.campaign import write_campaign

    out = write_campaign(
        args.out, preset=args.preset, seed=args.seed, overwrite=args.force, **_overrides(args)
    )
    log = json.loads((out / "synth.json").read_text())
    print(f"wrote {out} in {log['timings']['total_s']:.1f} s")
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "synth",
        help="time the generation of a synthetic campaign (default: the demo)",
        description="Generate a campaign into a temporary folder (or --out) with a fixed "
        "number of CPU threads and print the timings as JSON.",
    )
    p.add_argument("--threads", type=int, default=2, help="CPU threads for OpenCV/BLAS")
    p.add_argument("--out", type=Path, help="keep the campaign here instead of a temp folder")
    _add_options(p)
    p.set_defaults(func=_bench)


def _bench(args: argparse.Namespace) -> int:
    import cv2

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)  # for libraries loaded from here on
    cv2.setNumThreads(args.threads)
    from surfphase.synth.campaign import write_campaign

    with tempfile.TemporaryDirectory(prefix="surfphase-bench-synth-") as tmp:
        out = args.out or Path(tmp) / "campaign"
        t0, c0 = time.perf_counter(), time.process_time()
        write_campaign(out, preset=args.preset, seed=args.seed, overwrite=True, **_overrides(args))
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        log = json.loads((out / "synth.json").read_text())
    result = {
        "bench": "synth",
        "preset": args.preset,
        "threads": args.threads,
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "timings": log["timings"],
        "sessions": {
            k: {
                kk: v[kk]
                for kk in (
                    "seconds",
                    "render_s",
                    "truth_s",
                    "merges",
                    "visible_in_cam0_per_frame",
                    "mesh_volume_error_pct",
                )
            }  # fmt: skip
            for k, v in log["sessions"].items()
        },
        "settings": log["settings"],
    }
    print(json.dumps(result, indent=1))
    return 0
