"""``surfphase mask``: bubble instance masks of one session; ``surfphase bench masks``."""

from __future__ import annotations

import argparse
from pathlib import Path

from surfphase.commands import read_json_object


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
    params.update(read_json_object(args.params_json))
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
    p.add_argument(
        "--params-json",
        help="the masks section as a JSON object (or a .json file); overrides --config",
    )
    p.set_defaults(func=_run)


def _ingest_for_bench(campaign: Path, session: str, scale: float, out: Path):
    """Ingest one synthetic session with its *true* cameras (the bench judges masks,
    not calibration). Returns (ingest folder, gt folder, true cameras)."""
    import pandas as pd

    from surfphase.cameras import load_cameras
    from surfphase.ingest import ingest_session

    table = pd.read_csv(campaign / "sessions.tsv", sep="\t", dtype=str).fillna("")
    rows = table[table.session == session]
    if rows.empty:
        raise ValueError(f"{campaign / 'sessions.tsv'}: no session {session!r}")
    row = rows.iloc[0]
    gt = campaign / row["gt"]
    true = load_cameras(gt / "cameras.json")
    cams = {c: true[c] for c in ("cam0", "cam1")}
    videos = {c: campaign / row[c] for c in cams}
    if not (out / "meta.json").is_file():
        ingest_session(
            session,
            cams,
            videos,
            float(row["fps"]),
            frames=row["frames"] or None,
            scale=scale,
            out=out,
        )
    return out, gt, cams


def _bench(args: argparse.Namespace) -> int:
    import json
    import time

    import cv2
    import numpy as np

    from surfphase.folders.ingest import read_ingest
    from surfphase.folders.masks import read_masks
    from surfphase.masks import classical
    from surfphase.masks.metrics import mask_metrics, warp_labels
    from surfphase.masks.stage import merge_params, run_mask_stage

    campaign = Path(args.campaign)
    if not (campaign / "sessions.tsv").is_file():
        from surfphase.synth.campaign import write_campaign

        print(f"generating the demo campaign in {campaign} ...", flush=True)
        write_campaign(campaign, preset="demo", seed=0)
    work = Path(args.work) if args.work else campaign / "_bench_masks"
    params = merge_params(_load_config(args.config))
    cv2.setNumThreads(1)
    results: dict = {"session": args.session, "backend": params["backend"]}

    ingest, gt, true = _ingest_for_bench(campaign, args.session, 0.25, work / "ingest_128")
    t0 = time.perf_counter()
    run_mask_stage(ingest, work / "masks", params)
    results["stage_seconds"] = round(time.perf_counter() - t0, 3)
    folder = read_ingest(ingest)
    seen = folder.cameras
    truth = {c: warp_labels(np.load(gt / "masks" / f"{c}.npy"), true[c], seen[c]) for c in true}
    masks = read_masks(work / "masks", [seen[c] for c in true], folder.session)
    pred = {c: np.array(lab) for c, lab in masks.labels.items()}
    results["accuracy"] = mask_metrics(truth, pred)
    acc = results["accuracy"]
    print(
        f"session {args.session} of {campaign} ({params['backend']} backend, "
        f"{pred['cam0'].shape[2]}x{pred['cam0'].shape[1]} px, {pred['cam0'].shape[0]} frames)"
    )
    print(
        f"  mean mask IoU per matched bubble : {acc['mean_iou']:.3f} "
        f"({acc['matched_bubble_frames']} matched of {acc['truth_bubble_frames']} truth "
        f"bubble-frames, recall {acc['detection_recall']:.3f}, "
        f"{acc['false_positives']} unmatched predictions)"
    )
    print(
        f"  cross-view identity correct      : {acc['cross_view_identity']:.3f} "
        f"of {acc['cross_view_bubble_frames']} bubble-frames seen in both views"
    )
    print(
        f"  same id over a bubble's life     : {acc['temporal_identity_frames']:.3f} of "
        f"bubble-frames (per bubble: mean {acc['temporal_identity_mean']:.3f}, min "
        f"{acc['temporal_identity_min']:.3f}, {acc['tracked_bubbles']} bubble-views)"
    )
    low = [b for b in acc["temporal_identity_per_bubble"] if b["kept"] < 0.95 * b["frames"]]
    print(
        f"  bubbles at >= 95 % of their life : {acc['temporal_identity_ok_frac']:.3f} of "
        f"bubble-views; below: "
        + (
            ", ".join(f"{b['camera']} truth {b['truth']} {b['kept']}/{b['frames']}" for b in low)
            or "none"
        )
    )
    print(f"  ids shared by two truth bubbles  : {acc['shared_ids']}")
    if not args.skip_timing:
        results["timing"] = {}
        for scale, size in ((0.25, 128), (1.0, 512)):
            ing, _, _ = _ingest_for_bench(campaign, args.session, scale, work / f"ingest_{size}")
            stack = read_ingest(ing).stacks["cam0"]
            n = min(int(args.timing_frames), stack.shape[0])
            cp = params["classical"]
            t0 = time.perf_counter()
            bg = classical.session_background(stack, cp)
            t_session = time.perf_counter() - t0
            t0 = time.perf_counter()
            for t in range(n):
                classical.segment_frame(np.asarray(stack[t]), cp, bg)
            per = (time.perf_counter() - t0) / n
            results["timing"][f"{size}x{size}"] = {
                "seconds_per_frame": round(per, 4),
                "session_background_seconds": round(t_session, 4),
                "frames": n,
            }
            print(
                f"  classical time per frame {size}x{size}: {per * 1e3:.1f} ms "
                f"(+ {t_session * 1e3:.0f} ms once per session and camera for the "
                f"background; {n} frames, 1 OpenCV thread)"
            )
    if args.json:
        from surfphase.io import atomic_write_json

        atomic_write_json(args.json, results)
    print(json.dumps(results, indent=1, default=float))
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "masks",
        help="mask accuracy against synthetic truth, and classical time per frame",
        description="On session01 of the demo campaign (generated when missing): mean mask "
        "IoU per matched bubble, cross-view identity and temporal identity; then the "
        "classical backend's time per frame at 128×128 and 512×512.",
    )
    p.add_argument(
        "--campaign",
        default="demo",
        help="campaign folder (the demo preset is generated there if missing)",
    )
    p.add_argument("--session", default="session01")
    p.add_argument("--work", default=None, help="scratch folder (default: CAMPAIGN/_bench_masks)")
    p.add_argument("--config", help="config YAML; its masks: section is used")
    p.add_argument("--timing-frames", type=int, default=10)
    p.add_argument("--skip-timing", action="store_true")
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.set_defaults(func=_bench)
