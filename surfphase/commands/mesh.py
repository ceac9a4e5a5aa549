"""``surfphase mesh``: one PLY mesh per fitted frame, with per-vertex velocity."""

from __future__ import annotations

import argparse

from surfphase.commands import read_json_object


def _run(args: argparse.Namespace) -> int:
    from surfphase.mesh.stage import mesh_params, run_mesh, run_mesh_window

    params = read_json_object(args.params_json, what="mesh parameters")
    # Only the fused surface renders, with torch; the hull (the default) never imports
    # it, whose import costs 2-4 s a job.
    if args.threads and mesh_params(params)["surface"] == "fused":
        import torch

        torch.set_num_threads(args.threads)
    if (args.window is None) != (args.window_size is None):
        raise ValueError("--window and --window-size go together")
    if args.window is not None:
        info = run_mesh_window(
            args.fit, args.ingest, args.out, args.window, args.window_size, params, args.device,
            masks_dir=args.masks,
        )  # fmt: skip
        print(
            f"mesh {info['session']}: window {args.window} ({len(info['frames'])} frames) "
            f"-> {args.out}"
        )
        return 0
    summary = run_mesh(
        args.fit, args.ingest, args.out, params, device=args.device, masks_dir=args.masks
    )
    rows = summary["frames"]
    n_v = sum(r["vertices"] for r in rows)
    print(f"mesh {summary['session']}: {len(rows)} frames, {n_v} vertices -> {args.out}")
    return 0


def _gather(args: argparse.Namespace) -> int:
    from surfphase.mesh.stage import gather_mesh

    summary = gather_mesh(args.windows, args.out)
    rows = summary["frames"]
    print(
        f"mesh {summary['session']}: {len(rows)} frames from {len(args.windows)} windows "
        f"-> {args.out}"
    )
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "mesh",
        help="one mesh per fitted frame (PLY, metres, per-vertex velocity in m/s)",
        description="Fuse the fitted surfels' rendered depth (input and orbit views) into "
        "a truncated signed distance volume, run marching cubes, clean with pymeshlab and "
        "write OUT/<frame:06d>.ply (x y z in m, vx vy vz in m/s, speed colour), for "
        "ParaView OUT/vtk/<frame:06d>.vtp (point arrays velocity and speed, m/s) and "
        "OUT/<session>.pvd (the time series, s), and OUT/mesh.json. Finished frames are kept in OUT.partial/, so a killed run, rerun, "
        "goes on where it stopped. With --window K --window-size N only the K-th window "
        "of N frames is meshed, into a window folder for `surfphase mesh-gather`.",
    )
    p.add_argument("--fit", required=True, help="fit folder (surfels.npz)")
    p.add_argument("--ingest", required=True, help="ingest folder (cameras.json, meta.json)")
    p.add_argument(
        "--masks",
        default=None,
        help="the session's mask folder: the meshes are carved by its silhouettes (carve_px)",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--params-json",
        default=None,
        help='mesh parameters as JSON, e.g. \'{"voxels": 80, "frames": [0, 1]}\', or a .json file',
    )
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--window", type=int, default=None, help="window index (0-based)")
    p.add_argument("--window-size", type=int, default=None, help="frames per window")
    p.set_defaults(func=_run)

    g = subparsers.add_parser(
        "mesh-gather",
        help="gather mesh window folders into one mesh folder (as a single mesh job)",
        description="Read the window folders written by `surfphase mesh --window` and write "
        "OUT/<frame:06d>.ply, OUT/vtk/, OUT/<session>.pvd and OUT/mesh.json, the same files "
        "as one `surfphase mesh` run.",
    )
    g.add_argument("--windows", nargs="+", required=True, help="window folders")
    g.add_argument("--out", required=True, help="output folder")
    g.set_defaults(func=_gather)


def _bench(args: argparse.Namespace) -> int:
    import torch

    from surfphase.bench.mesh import bench_mesh

    torch.set_num_threads(args.threads)
    params = read_json_object(args.params_json, what="mesh parameters")
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
        help="Chamfer distance (mm, %% of true r_eq) of the meshes to ground-truth meshes",
    )
    p.add_argument("--fit", required=True, help="fit folder (surfels.npz)")
    p.add_argument("--ingest", required=True, help="ingest folder (cameras.json)")
    p.add_argument("--gt", required=True, help="ground-truth folder (meshes/, bubbles.csv)")
    p.add_argument("--out", required=True, help="folder for the meshes")
    p.add_argument("--frames", default="0,8,16", help="frame positions, comma-separated")
    p.add_argument("--params-json", default=None, help="mesh parameters as JSON (or a .json file)")
    p.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"])
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.set_defaults(func=_bench)
