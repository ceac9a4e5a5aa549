"""``surfphase mesh``: one PLY mesh per fitted frame, with per-vertex velocity."""

from __future__ import annotations

import argparse
import json


def _run(args: argparse.Namespace) -> int:
    from surfphase.mesh.stage import run_mesh

    params = {}
    if args.params_json:
        try:
            params = json.loads(args.params_json)
        except ValueError as e:
            raise ValueError(f"--params-json: not valid JSON ({e})") from e
        if not isinstance(params, dict):
            raise ValueError("--params-json: expected a JSON object of mesh parameters")
    summary = run_mesh(args.fit, args.ingest, args.out, params, device=args.device)
    rows = summary["frames"]
    n_v = sum(r["vertices"] for r in rows)
    print(f"mesh {summary['session']}: {len(rows)} frames, {n_v} vertices -> {args.out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "mesh",
        help="one mesh per fitted frame (PLY, metres, per-vertex velocity in m/s)",
        description="Fuse the fitted surfels' rendered depth (input and orbit views) into "
        "a truncated signed distance volume, run marching cubes, clean with pymeshlab and "
        "write OUT/<frame:06d>.ply (x y z in m, vx vy vz in m/s, speed colour) and "
        "OUT/mesh.json.",
    )
    p.add_argument("--fit", required=True, help="fit folder (surfels.npz)")
    p.add_argument("--ingest", required=True, help="ingest folder (cameras.json, meta.json)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--params-json",
        default=None,
        help='mesh parameters as JSON, e.g. \'{"voxels": 80, "frames": [0, 1]}\'',
    )
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    p.set_defaults(func=_run)


def _bench(args: argparse.Namespace) -> int:
    import torch

    from surfphase.mesh.bench import bench_mesh

    torch.set_num_threads(args.threads)
    params = json.loads(args.params_json) if args.params_json else {}
    frames = [int(f) for f in args.frames.split(",")]
    df = bench_mesh(args.fit, args.ingest, args.gt, args.out, frames, params, args.device)
    print(df.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    print(
        f"mean Chamfer {df['chamfer_mm'].mean():.3f} mm = "
        f"{df['chamfer_pct_r_eq'].mean():.1f}% of the mean true r_eq "
        f"(target ≤ 10%); total {df.attrs['seconds_total']:.1f} s"
    )
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "mesh",
        help="Chamfer distance (mm, % of true r_eq) of the meshes to ground-truth meshes",
    )
    p.add_argument("--fit", required=True, help="fit folder (surfels.npz)")
    p.add_argument("--ingest", required=True, help="ingest folder (cameras.json)")
    p.add_argument("--gt", required=True, help="ground-truth folder (meshes/, bubbles.csv)")
    p.add_argument("--out", required=True, help="folder for the meshes")
    p.add_argument("--frames", default="0,8,16", help="frame positions, comma-separated")
    p.add_argument("--params-json", default=None, help="mesh parameters as JSON")
    p.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"])
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.set_defaults(func=_bench)
