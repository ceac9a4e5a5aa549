"""``surfphase mask``: bubble instance masks of one session; ``surfphase bench masks``."""

from __future__ import annotations

import argparse
from pathlib import Path


def _load_config(path: str | None) -> dict:
    """The ``masks`` section of a config YAML (empty without a file)."""
    if not path:
        return {}
    import yaml

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: config file not found")
    try:
        cfg = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{p}: not valid YAML ({e})") from e
    masks = cfg.get("masks", {}) or {}
    if not isinstance(masks, dict):
        raise ValueError(f"{p}: masks must be a mapping")
    return masks


def _run(args: argparse.Namespace) -> int:
    from surfphase.masks.stage import run_mask_stage

    params = dict(_load_config(args.config))
    if args.backend:
        params["backend"] = args.backend
    run_mask_stage(Path(args.ingest), Path(args.out), params)
    print(f"masks written to {args.out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "mask",
        help="bubble instance masks of one session (after ingest)",
        description="Segment every frame (classical or SAM/ONNX backend), associate the "
        "instances across views and time, write label stacks, instances.csv, events.csv "
        "and overlay pictures.",
    )
    p.add_argument("--ingest", required=True, help="ingest folder of the session")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--backend", choices=["classical", "sam"], help="override masks.backend")
    p.add_argument("--config", help="config YAML; its masks: section is used")
    p.set_defaults(func=_run)


def _bench(args: argparse.Namespace) -> int:
    from surfphase.masks.bench import run_bench

    return run_bench(args)


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "masks",
        help="mask accuracy against synthetic truth, and classical time per frame",
        description="On session01 of the demo campaign (generated when missing): mean mask "
        "IoU per matched bubble, cross-view identity and temporal identity; then the "
        "classical backend's time per frame at 128×128 and 512×512.",
    )
    p.add_argument("--campaign", default="demo", help="campaign folder (generated if missing)")
    p.add_argument("--session", default="session01")
    p.add_argument("--work", default=None, help="scratch folder (default: CAMPAIGN/_bench_masks)")
    p.add_argument("--config", help="config YAML; its masks: section is used")
    p.add_argument("--timing-frames", type=int, default=10)
    p.add_argument("--skip-timing", action="store_true")
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.set_defaults(func=_bench)
