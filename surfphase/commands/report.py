"""``surfphase plots``: one session's report figures; ``surfphase campaign-page``: the
campaign's HTML page."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _plots(args: argparse.Namespace) -> int:
    from surfphase.io import atomic_write_text
    from surfphase.report.plots import copy_overlays, session_metrics_table, velocity_plots

    fit, evaluate, out = Path(args.fit), Path(args.evaluate), Path(args.out)
    metrics_path = evaluate / "metrics.json"
    if not metrics_path.is_file():
        raise FileNotFoundError(f"{metrics_path}: session {args.session}: metrics not found")
    try:
        metrics = json.loads(metrics_path.read_text())
    except ValueError as e:
        raise ValueError(f"{metrics_path}: session {args.session}: not valid JSON ({e})") from e
    fps = args.fps or metrics.get("fps")
    if not fps:
        raise ValueError(f"{metrics_path}: session {args.session}: no fps (give --fps)")
    gt_csv = None
    if args.gt:
        gt_csv = Path(args.gt) / "bubbles.csv" if Path(args.gt).is_dir() else Path(args.gt)
    baseline = evaluate / "baseline_bubbles.csv"
    shown = velocity_plots(
        fit / "bubbles.csv",
        baseline if baseline.is_file() else None,
        gt_csv,
        float(fps),
        out / "velocity.png",
        session=args.session,
        max_bubbles=args.max_bubbles,
    )
    table = session_metrics_table(metrics)
    atomic_write_text(
        out / "metrics.html",
        f"<h3>{args.session} metrics</h3>\n"
        + table.to_html(index=False, float_format=lambda v: f"{v:.4g}", na_rep="–"),
    )
    n_overlays = 0
    if args.masks:
        n_overlays = len(copy_overlays(args.masks, out / "masks", args.overlays))
    with_truth = sum("truth" in s for s in shown.values())
    print(
        f"plots {args.session}: {len(shown)} bubbles ({with_truth} paired with the truth), "
        f"{len(table)} metrics, {n_overlays} mask overlays -> {out}"
    )
    return 0


def _page(args: argparse.Namespace) -> int:
    from surfphase.report.plots import campaign_page

    figures, overlays = {}, {}
    for item in args.session_report or []:
        session, sep, folder = item.partition("=")
        if not sep or not session or not folder:
            raise ValueError(f"--session-report {item!r}: expected SESSION=FOLDER")
        folder = Path(folder)
        if not (folder / "velocity.png").is_file():
            raise FileNotFoundError(f"{folder / 'velocity.png'}: session {session}: not found")
        figures[session] = [folder / "velocity.png"]
        overlays[session] = sorted((folder / "masks").glob("*.png"))
    summary = campaign_page(args.metrics, args.out, figures, overlays, title=args.title)
    print(f"campaign page: {len(summary)} sessions, {len(figures)} with figures -> {args.out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "plots",
        help="one session's report figures: velocity over time, metrics, mask overlays",
        description="Write OUT/velocity.png (vx, vy over time per bubble: method, two-view "
        "baseline, ground truth with --gt), OUT/metrics.html (the session's metrics) and, "
        "with --masks, a few mask overlays in OUT/masks/.",
    )
    p.add_argument("--session", required=True, help="session name")
    p.add_argument("--fit", required=True, help="fit folder (bubbles.csv)")
    p.add_argument(
        "--evaluate", required=True, help="evaluate folder (metrics.json, baseline_bubbles.csv)"
    )
    p.add_argument("--gt", default=None, help="ground-truth folder or its bubbles.csv")
    p.add_argument("--masks", default=None, help="mask folder (overlays/*.png)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--fps", type=float, default=None, help="frame rate (default: metrics.json)")
    p.add_argument("--max-bubbles", type=int, default=8, help="bubbles in the velocity plot")
    p.add_argument("--overlays", type=int, default=4, help="mask overlays to copy")
    p.set_defaults(func=_plots)

    c = subparsers.add_parser(
        "campaign-page",
        help="one self-contained HTML page: campaign metrics and each session's figures",
        description="Write a self-contained HTML page with the campaign metrics table and, "
        "per --session-report SESSION=FOLDER (a `surfphase plots` output), its velocity "
        "plot and mask overlays embedded.",
    )
    c.add_argument("--metrics", required=True, help="campaign metrics CSV (campaign-table)")
    c.add_argument("--out", required=True, help="output HTML")
    c.add_argument(
        "--session-report", nargs="*", metavar="SESSION=FOLDER", help="per-session figures"
    )
    c.add_argument("--title", default="SurfPhase campaign", help="page title")
    c.set_defaults(func=_page)
