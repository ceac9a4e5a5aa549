"""``surfphase render-views``: the stage-1 fit rendered into the orbit views."""

from __future__ import annotations

import argparse

from surfphase.commands import read_json_object


def _run(args: argparse.Namespace) -> int:
    import torch

    from surfphase.device import resolve_device
    from surfphase.views import render_views

    if args.threads:
        torch.set_num_threads(int(args.threads))
    params = read_json_object(args.params_json, what="view parameters")
    surfels = args.fit / "surfels.npz" if args.fit.is_dir() else args.fit
    s = render_views(surfels, args.ingest, args.out, params, resolve_device(args.device))
    print(
        f"render-views {s['session']}: {len(s['views'])} views × {s['frames']} frames "
        f"({s['size'][1]}×{s['size'][0]}) in {s['seconds']:.1f} s -> {args.out}"
    )
    return 0


def register(subparsers) -> None:
    from pathlib import Path

    p = subparsers.add_parser(
        "render-views",
        help="render the stage-1 fit into the orbit views (lossless frames and MP4)",
        description="Render every frame of a fit into orbit cameras about the scene centre "
        "(the closest point of the input cameras' optical axes; view k = the first input "
        "camera rotated k·30° about lab +y). Writes OUT/cameras.json, OUT/<view>.npy "
        "(uint16 T×H×W), OUT/<view>_alpha.npy (float16), OUT/<view>.mp4 and "
        "OUT/background.npy, all at once.",
    )
    p.add_argument("--fit", required=True, type=Path, help="fit folder or its surfels.npz")
    p.add_argument("--ingest", required=True, type=Path, help="ingest folder (cameras, meta)")
    p.add_argument("--out", required=True, type=Path, help="views folder to write")
    p.add_argument(
        "--params-json",
        default=None,
        help='view parameters as JSON (or a .json file), e.g. \'{"n_views": 11, "step_deg": 30, '
        '"reference": "cam0"}\'',
    )
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.set_defaults(func=_run)


def _oracle(args: argparse.Namespace) -> int:
    from surfphase.views import oracle_views

    info = oracle_views(args.gt, args.views, args.out)
    worst = max(info["offsets_m"].values(), default=0.0)
    print(
        f"bench oracle-views: {len(info['offsets_m'])} true orbit views from {info['source']} "
        f"-> {args.out} (camera centres within {worst * 1e3:.3f} mm of the orbit cameras); "
        f"run fit2 with --refine {args.out} to score stage 2 with a perfect prior"
    )
    return 0


def register_bench(bench_subparsers) -> None:
    from pathlib import Path

    p = bench_subparsers.add_parser(
        "oracle-views",
        help="the true orbit views of a synthetic session as a refinement folder "
        "(stage 2 with a perfect prior)",
        description="Write OUT/<view>.npy (uint16 T×H×W, like refine's) from the ground "
        "truth's noiseless images of the orbit cameras, for fit2 --refine OUT: the "
        "stage-2 fit scored as if the prior returned the true views.",
    )
    p.add_argument("--gt", required=True, type=Path, help="the session's gt folder")
    p.add_argument("--views", required=True, type=Path, help="render-views folder")
    p.add_argument("--out", required=True, type=Path, help="folder to write")
    p.set_defaults(func=_oracle)
