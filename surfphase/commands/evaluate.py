"""``surfphase evaluate``: metrics of one session; ``surfphase campaign-table``: all
sessions' metrics in one table."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _run(args: argparse.Namespace) -> int:
    from surfphase.eval.stage import run_evaluate

    m = run_evaluate(
        args.ingest,
        args.masks,
        args.fit,
        args.out,
        gt_dir=args.gt,
        meshes_dir=args.meshes,
        session=args.session,
        device=args.device,
        max_match_dist=args.max_match_dist_mm * 1e-3,
        include_nucleation=args.include_nucleation,
        reference_camera=args.reference_camera,
    )
    parts = [f"evaluate {m['session']}:"]
    for label, v in (m.get("velocity") or {}).items():
        rel = v["relative_error"]
        parts.append(
            f"{label} velocity error {rel:.3f}" if rel is not None else f"{label}: no match"
        )
    if "velocity" not in m:
        for label, r in m["reference2d"].items():
            if isinstance(r, dict) and r.get("relative_error_y") is not None:
                parts.append(
                    f"{label} vs 2D reference: relative error y {r['relative_error_y']:.3f}"
                )
    mean = (m.get("heldout") or {}).get("mean")
    if mean:
        parts.append(f"held-out PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.3f}")
    print(" ".join(parts) + f" -> {args.out}")
    return 0


def _table(args: argparse.Namespace) -> int:
    from surfphase.eval.stage import campaign_table
    from surfphase.io import atomic_write_text

    rows = []
    for p in map(Path, args.metrics):
        if not p.exists():
            raise FileNotFoundError(f"{p}: metrics file not found")
        try:
            rows.append(json.loads(p.read_text()))
        except ValueError as e:
            raise ValueError(f"{p}: not valid JSON ({e})") from e
        if "session" not in rows[-1]:
            raise ValueError(f"{p}: no 'session' in the metrics")
    table = campaign_table(rows)
    atomic_write_text(args.out, table.to_csv(index=False))
    print(f"campaign table: {len(table)} sessions × {table.shape[1]} columns -> {args.out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="metrics of one session: held-out views, velocity vs truth / 2D reference",
        description="Evaluate a session's fit: novel-view L1/PSNR/SSIM on held-out views "
        "(with --gt), bubble velocity error of the method and of the two-view centroid "
        "baseline against the truth (with --gt), the 2D single-view reference (always), "
        "Chamfer distance (with --gt and --meshes). Writes OUT/metrics.json, "
        "OUT/baseline_bubbles.csv and OUT/velocity_table.csv.",
    )
    p.add_argument("--session", default=None, help="session name (default: ingest meta.json)")
    p.add_argument("--ingest", required=True, help="ingest folder (cameras.json, meta.json)")
    p.add_argument("--masks", required=True, help="mask folder (<cam>_labels.npy)")
    p.add_argument("--fit", required=True, help="fit folder (bubbles.csv, surfels.npz)")
    p.add_argument("--gt", default=None, help="ground-truth folder (synthetic sessions)")
    p.add_argument("--meshes", default=None, help="the method's meshes (<frame:06d>.ply)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu")
    p.add_argument("--max-match-dist-mm", type=float, default=1.5, help="bubble matching gate, mm")
    p.add_argument("--include-nucleation", action="store_true", help="also compare bubble 0")
    p.add_argument("--reference-camera", default=None, help="view of the 2D reference")
    p.set_defaults(func=_run)

    t = subparsers.add_parser(
        "campaign-table",
        help="one CSV row per session from metrics.json files",
        description="Concatenate sessions' metrics.json into one table (pandas).",
    )
    t.add_argument("--metrics", nargs="+", required=True, help="metrics.json files")
    t.add_argument("--out", required=True, help="output CSV")
    t.set_defaults(func=_table)
