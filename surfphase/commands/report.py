"""``surfphase plots``: one session's report figures; ``surfphase mesh-snapshots``: its
meshes drawn coloured by speed; ``surfphase report-videos``: its novel-view videos for
the report; ``surfphase campaign-page``: the campaign's HTML page."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def _plots(args: argparse.Namespace) -> int:
    from surfphase.io import atomic_write_text
    from surfphase.report.plots import copy_overlays, session_metrics_table, velocity_plots
    from surfphase.report.tables import comparison_table, flatten

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
    comparison = comparison_table(flatten(metrics))
    atomic_write_text(
        out / "metrics.html",
        f"<h3>{args.session}: the fits compared</h3>\n"
        + comparison.to_html(index=False, float_format=_fmt, na_rep="–")
        + f"\n<h3>{args.session}: every metric</h3>\n"
        + table.to_html(index=False, float_format=_fmt, na_rep="–"),
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


def _snapshots(args: argparse.Namespace) -> int:
    from surfphase.report.snapshots import mesh_snapshots

    pngs = mesh_snapshots(args.meshes, args.out, args.frames, args.speed_max, args.session)
    print(f"mesh snapshots {args.session}: {len(pngs)} frames -> {args.out}")
    return 0


def _videos(args: argparse.Namespace) -> int:
    from surfphase.report.plots import copy_videos, videos_page

    if args.views is None and args.refine is None:
        raise ValueError(f"report-videos {args.session}: give --views and/or --refine")
    out = Path(args.out)
    copies = copy_videos(args.views, args.refine, out / "videos")
    title = f"{args.session} novel views".strip()
    n_views = videos_page(copies, out / "videos.html", title)
    print(f"report videos {args.session}: {len(copies)} videos of {n_views} views -> {out}")
    return 0


def _page(args: argparse.Namespace) -> int:
    from surfphase.report.plots import campaign_page

    figures, overlays, meshes, videos = {}, {}, {}, {}
    for item in args.session_report or []:
        session, sep, folder = item.partition("=")
        if not sep or not session or not folder:
            raise ValueError(f"--session-report {item!r}: expected SESSION=FOLDER")
        folder = Path(folder)
        if not (folder / "velocity.png").is_file():
            raise FileNotFoundError(f"{folder / 'velocity.png'}: session {session}: not found")
        figures[session] = [folder / "velocity.png"]
        overlays[session] = sorted((folder / "masks").glob("*.png"))
        meshes[session] = sorted((folder / "meshes").glob("*.png"))
        videos[session] = sorted((folder / "videos").glob("*.mp4"))
    summary = campaign_page(
        args.metrics,
        args.out,
        figures,
        overlays,
        args.title,
        meshes=meshes,
        videos=videos,
        prior_samples=args.prior_samples,
    )
    n_videos = sum(map(len, videos.values()))
    print(
        f"campaign page: {len(summary)} sessions, {len(figures)} with figures, "
        f"{n_videos} videos -> {args.out}"
    )
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

    m = subparsers.add_parser(
        "mesh-snapshots",
        help="a session's meshes drawn from the front and side, coloured by speed",
        description="Write OUT/<frame:06d>.png for a few meshes of the mesh stage (evenly "
        "spread over the frames): orthographic front (along −z) and side (along −x) "
        "views, triangles coloured by their speed (viridis over [0, speed max] m/s).",
    )
    m.add_argument("--session", default="", help="session name (titles and messages)")
    m.add_argument("--meshes", required=True, help="mesh folder (<frame:06d>.ply, mesh.json)")
    m.add_argument("--out", required=True, help="output folder")
    m.add_argument("--frames", type=int, default=4, help="how many frames to draw")
    m.add_argument(
        "--speed-max",
        type=float,
        default=None,
        help="m/s at the top of the colour map (default: mesh.json's, else 0.4)",
    )
    m.set_defaults(func=_snapshots)

    v = subparsers.add_parser(
        "report-videos",
        help="a session's novel-view videos (raw and refined) gathered for the report",
        description="Copy VIEWS/<v>.mp4 to OUT/videos/<v>_raw.mp4 and REFINE/<v>.mp4 to "
        "OUT/videos/<v>_refined.mp4, and write OUT/videos.html, a self-contained page with "
        "them side by side (one row per view).",
    )
    v.add_argument("--session", default="", help="session name (messages)")
    v.add_argument("--views", default=None, help="novel-view folder (render_views: <v>.mp4)")
    v.add_argument("--refine", default=None, help="refined-view folder (refine: <v>.mp4)")
    v.add_argument("--out", required=True, help="output folder")
    v.set_defaults(func=_videos)

    c = subparsers.add_parser(
        "campaign-page",
        help="one self-contained HTML page: campaign metrics and each session's figures",
        description="Write a self-contained HTML page with the campaign metrics table and, "
        "per --session-report SESSION=FOLDER (a `surfphase plots` output folder), its fits "
        "compared, velocity plot, mesh snapshots (FOLDER/meshes/*.png), novel-view videos "
        "(FOLDER/videos/*.mp4) and mask overlays embedded.",
    )
    c.add_argument("--metrics", required=True, help="campaign metrics CSV (campaign-table)")
    c.add_argument("--out", required=True, help="output HTML")
    c.add_argument(
        "--session-report", nargs="*", metavar="SESSION=FOLDER", help="per-session figures"
    )
    c.add_argument("--title", default="SurfPhase campaign", help="page title")
    c.add_argument(
        "--prior-samples", default=None, help="the video prior's samples.png (train-prior)"
    )
    c.set_defaults(func=_page)
