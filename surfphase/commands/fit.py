"""``surfphase fit`` / ``surfphase fit2``: the stage-1 and stage-2 fits of one session;
``surfphase bench fit``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from surfphase.commands import read_json_object


def _read_config(path: str) -> dict:
    """The top-level mapping of a config YAML/JSON file (errors name the file)."""
    import yaml

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: config file not found")
    try:
        cfg = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{p}: not valid YAML ({e})") from e
    if not isinstance(cfg, dict):
        raise ValueError(f"{p}: expected a mapping at the top level")
    return cfg


def _load_config(path: str | None) -> tuple[dict, str | None]:
    """Fit parameters from a YAML/JSON config: its ``fit:`` section (or the whole file),
    and the top-level ``device`` if any."""
    if not path:
        return {}, None
    p, cfg = Path(path), _read_config(path)
    if "fit" in cfg:
        fit = cfg["fit"] or {}
    else:
        fit = {k: v for k, v in cfg.items() if k != "device"}
    if not isinstance(fit, dict):
        raise ValueError(f"{p}: 'fit' must be a mapping")
    return dict(fit), cfg.get("device")


def _run(args: argparse.Namespace) -> int:
    import torch

    from surfphase.fit.stage import run_fit

    params, cfg_device = _load_config(args.config)
    params.update(read_json_object(args.params_json, what="fit parameters"))
    if args.frames is not None:
        params["frames"] = args.frames
    if args.no_sdf:
        params["use_sdf"] = False
    if args.no_guidance:
        params["guidance"] = False
    if args.threads:
        torch.set_num_threads(args.threads)
    device = args.device or cfg_device or "auto"
    summary = run_fit(
        args.ingest, args.masks, args.out, params, device=device, checkpoint_dir=args.checkpoint
    )
    print(
        f"fit {summary['session']}: {summary['frames']} frames, "
        f"input-view PSNR {summary['psnr_mean']:.2f} dB, "
        f"{summary['seconds_per_iter'] * 1000:.1f} ms/iteration -> {args.out}"
    )
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="stage-1 fit of one session: SDF surfels, bubble tracking, velocities",
        description="Fit SDF surfels frame by frame to a session's undistorted frames and "
        "bubble masks; write surfels.npz, bubbles.csv (m, m/s, lab frame), curves.csv, "
        "summary.json and renders/. Resumes from the checkpoint folder when killed.",
    )
    p.add_argument(
        "--ingest", required=True, help="ingest folder (<cam>.npy, cameras.json, meta.json)"
    )
    p.add_argument("--masks", required=True, help="mask folder (<cam>_labels.npy)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="config YAML (its 'fit:' section overrides the defaults)")
    p.add_argument(
        "--params-json",
        default=None,
        help="fit parameters as a JSON object or .json file (over --config; see "
        "surfphase.fit.stage.DEFAULTS)",
    )
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None)
    p.add_argument("--frames", type=int, default=None, help="fit only the first N frames")
    p.add_argument("--no-sdf", action="store_true", help="ablation: free opacities, no SDF")
    p.add_argument("--no-guidance", action="store_true", help="ablation: no bubble guidance")
    p.add_argument("--checkpoint", default=None, help="checkpoint folder (default OUT.ckpt)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.set_defaults(func=_run)
    _register_fit2(subparsers)


def _load_config2(path: str | None) -> tuple[dict, dict, str | None]:
    """(``fit:``, ``fit2:``, ``device``) of a config YAML/JSON file."""
    if not path:
        return {}, {}, None
    p, cfg = Path(path), _read_config(path)
    fit, fit2 = cfg.get("fit") or {}, cfg.get("fit2") or {}
    if not isinstance(fit, dict) or not isinstance(fit2, dict):
        raise ValueError(f"{p}: 'fit' and 'fit2' must be mappings")
    return dict(fit), dict(fit2), cfg.get("device")


def _run2(args: argparse.Namespace) -> int:
    import torch

    from surfphase.fit.stage2 import run_fit_stage2

    fit, fit2, cfg_device = _load_config2(args.config)
    fit.update(read_json_object(args.fit_json, "--fit-json"))
    fit2.update(read_json_object(args.params_json))
    if args.frames is not None:
        fit2["frames"] = args.frames
    if args.threads:
        torch.set_num_threads(args.threads)
    summary = run_fit_stage2(
        args.ingest,
        args.masks,
        args.stage1,
        args.views,
        args.refine,
        args.out,
        params=fit2,
        fit_params=fit,
        device=args.device or cfg_device or "auto",
        checkpoint_dir=args.checkpoint,
    )
    print(
        f"fit2 {summary['session']}: {summary['frames']} frames, "
        f"input-view PSNR {summary['psnr_mean']:.2f} dB, "
        f"{summary['seconds_per_iter'] * 1000:.1f} ms/iteration -> {args.out}"
    )
    return 0


def _register_fit2(subparsers) -> None:
    p = subparsers.add_parser(
        "fit2",
        help="stage-2 fit of one session: stage 1 restarted with the refined orbit views",
        description="Refit a session from the stage-1 surfels of its first frame, with the "
        "refined orbit views as extra supervision (weights: inputs 1.0, near views 0.5, far "
        "views 0.25); same loop, binding and guidance as stage 1. Writes the stage-1 "
        "outputs (surfels.npz, bubbles.csv, curves.csv, summary.json, renders/) and "
        "stage2.json. Resumes from the checkpoint folder when killed.",
    )
    p.add_argument("--ingest", required=True, help="ingest folder (<cam>.npy, cameras.json)")
    p.add_argument("--masks", required=True, help="mask folder (<cam>_labels.npy)")
    p.add_argument("--stage1", required=True, help="stage-1 fit folder (surfels.npz)")
    p.add_argument("--views", required=True, help="orbit views folder (cameras.json, alpha)")
    p.add_argument("--refine", required=True, help="refined views folder (<view>.npy)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="config YAML: its 'fit:' and 'fit2:' sections")
    p.add_argument(
        "--fit-json",
        default=None,
        help="stage-1 fit settings as a JSON object or .json file (over 'fit:')",
    )
    p.add_argument(
        "--params-json",
        default=None,
        help="stage-2 settings as a JSON object or .json file (over 'fit2:'; "
        "surfphase.fit.stage2.DEFAULTS and any fit key)",
    )
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None)
    p.add_argument("--frames", type=int, default=None, help="fit only the first N frames")
    p.add_argument("--checkpoint", default=None, help="checkpoint folder (default OUT.ckpt)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.set_defaults(func=_run2)


def _bench(args: argparse.Namespace) -> int:
    from surfphase.bench.fit import run_benchmark

    result = run_benchmark(
        Path(args.out),
        frames=args.frames,
        threads=args.threads,
        device=args.device,
        variants=tuple(v for v in args.variants.split(",") if v),
        params=read_json_object(args.params, "--params", "fit parameters"),
    )
    print(json.dumps(result, indent=1))
    return 0


def _bench2(args: argparse.Namespace) -> int:
    from surfphase.bench.fit_stage2 import run_benchmark as run_benchmark2

    result = run_benchmark2(
        args.ingest,
        args.masks,
        args.stage1,
        args.views,
        args.refine,
        views_per_step=[int(k) for k in args.views_per_step.split(",") if k],
        iters=args.iters,
        repeats=args.repeats,
        threads=args.threads,
    )
    text = json.dumps(result, indent=1)
    if args.json:
        from surfphase.io import atomic_write_text

        atomic_write_text(Path(args.json), text)
    print(text)
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "fit",
        help="stage-1 fit on the synthetic demo session: PSNR, velocity error, timings",
    )
    p.add_argument("--out", default="bench/fit", help="working folder")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu")
    p.add_argument(
        "--variants",
        default="guided,no_guidance",
        help="comma-separated runs: guided, no_guidance, no_sdf (default guided,no_guidance)",
    )
    p.add_argument(
        "--params", default=None, help="fit parameter overrides: a JSON object or .json file"
    )
    p.set_defaults(func=_bench)
    q = bench_subparsers.add_parser(
        "fit2",
        help="stage-2 fit: seconds per step against stage 1, per number of refined views",
    )
    q.add_argument("--ingest", required=True, help="ingest folder")
    q.add_argument("--masks", required=True, help="mask folder")
    q.add_argument("--stage1", required=True, help="stage-1 fit folder (surfels.npz)")
    q.add_argument("--views", required=True, help="orbit views folder")
    q.add_argument("--refine", required=True, help="refined views folder")
    q.add_argument(
        "--views-per-step", default="0,4,2", help="refined views per step to time (0: all)"
    )
    q.add_argument("--iters", type=int, default=10, help="steps per timed run")
    q.add_argument("--repeats", type=int, default=3, help="turns of every variant")
    q.add_argument("--threads", type=int, default=2)
    q.add_argument("--json", default=None, help="also write the result here")
    q.set_defaults(func=_bench2)
