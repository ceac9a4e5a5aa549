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
        fit_stage1_dir=args.fit_stage1,
        ablations=_named_dirs(args.ablation or [], "--ablation"),
        region_scale=args.region_scale,
        compare_meshes=_named_dirs(args.compare_meshes or [], "--compare-meshes"),
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
    parts += _heldout_words((m.get("heldout") or {}).get("mean"))
    others = {"stage1": m.get("stage1"), **(m.get("ablations") or {})}
    for label, res in others.items():
        if not res:
            continue
        rel = (res.get("velocity") or {}).get("relative_error")
        words = [f"velocity error {rel:.3f}"] if rel is not None else []
        words += _heldout_words((res.get("heldout") or {}).get("mean"))
        if words:
            parts.append(f"[{label}: " + ", ".join(words) + "]")
    print(" ".join(parts) + f" -> {args.out}")
    return 0


def _heldout_words(mean: dict | None) -> list[str]:
    """``held-out PSNR …`` (full frame, and the bubbles' region when present)."""
    if not mean or mean.get("psnr") is None:
        return []
    words = [f"held-out PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.3f}"]
    region = mean.get("region") or {}
    if region.get("psnr") is not None:
        words.append(f"bubble region {region['psnr']:.2f} dB, SSIM {region['ssim']:.3f}")
    return words


def _named_dirs(items: list[str], option: str) -> dict[str, str]:
    """``NAME=DIR`` arguments → ``{name: dir}``; a malformed or repeated one is an error."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, folder = item.partition("=")
        if not sep or not name or not folder:
            raise ValueError(f"{option} {item!r}: expected NAME=DIR")
        if name in out:
            raise ValueError(f"{option} {item!r}: {name} given twice")
        out[name] = folder
    return out


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
        "(with --gt; full frame and inside the true bubbles' region), bubble velocity "
        "error of the method and of the two-view centroid baseline against the truth "
        "(with --gt), the 2D single-view reference (always), Chamfer distance (with --gt "
        "and --meshes); the same for a stage-1 fit (--fit-stage1) and ablation fits "
        "(--ablation). Writes OUT/metrics.json, "
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
    p.add_argument(
        "--fit-stage1",
        default=None,
        help="the stage-1 fit folder (no refinement), scored beside the final --fit",
    )
    p.add_argument(
        "--ablation",
        action="append",
        metavar="NAME=DIR",
        help="an ablation's fit folder (e.g. no_sdf=results/s/ablations/no_sdf/fit); repeat",
    )
    p.add_argument(
        "--compare-meshes",
        action="append",
        metavar="NAME=DIR",
        help="meshes of stage 1 (stage1=DIR) or an ablation, for their Chamfer (with --gt); repeat",
    )
    p.add_argument(
        "--region-scale",
        type=float,
        default=1.5,
        help="bubble region: projected spheres of this × the true r_eq (with --gt)",
    )
    p.set_defaults(func=_run)

    t = subparsers.add_parser(
        "campaign-table",
        help="one CSV row per session from metrics.json files",
        description="Concatenate sessions' metrics.json into one table (pandas).",
    )
    t.add_argument("--metrics", nargs="+", required=True, help="metrics.json files")
    t.add_argument("--out", required=True, help="output CSV")
    t.set_defaults(func=_table)
