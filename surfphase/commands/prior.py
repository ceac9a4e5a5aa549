"""``surfphase train-prior`` and ``surfphase refine``: the video prior and SDEdit per view.

``surfphase bench prior`` times training of the embedded prior and refinement of one
view on the CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from surfphase.commands import read_json_object


def _set_threads(n: int | None) -> None:
    if n:
        import torch

        torch.set_num_threads(int(n))


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train-prior",
        help="train the video prior on the campaign's monocular clips",
        description="Train the embedded video prior from scratch, or LoRA-fine-tune Wan 2.1 "
        "(local weights), on monocular clips; writes OUT/prior.json, the weights, "
        "OUT/samples.png (training frames on top, samples from noise below) and OUT/train.json.",
    )
    p.add_argument("--clips", required=True, help="folder of clip folders / .npy stacks, or a glob")
    p.add_argument("--out", required=True, type=Path, help="prior folder to write")
    p.add_argument("--backend", default="embedded", choices=["embedded", "wan"])
    p.add_argument(
        "--params-json", help="backend parameters: a JSON object or a .json file (see docs)"
    )
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--device", default="cpu", help="auto, cpu or cuda (default cpu)")
    p.add_argument(
        "--samples", type=_at_least_one, default=4, help="videos in samples.png (default 4, ≥ 1)"
    )
    p.set_defaults(func=_train)

    r = subparsers.add_parser(
        "refine",
        help="refine one view's video with the prior (SDEdit)",
        description="SDEdit one video with a trained prior. With --video (a folder of frames "
        "or an .npy stack (T, H, W)): writes OUT.npy (float32 in [0, 1]) and the PNG frames "
        "OUT/ (OUT given with or without .npy), plus OUT/refine.json. With --views DIR "
        "--view NAME (a render-views folder): writes OUT/NAME.npy (uint16, T×H×W), "
        "OUT/NAME.mp4 (at the session's fps) and OUT/NAME.json, the .npy last.",
    )
    r.add_argument("--prior", required=True, type=Path, help="prior folder (train-prior --out)")
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", type=Path, help="frame folder or .npy stack")
    src.add_argument("--views", type=Path, help="render-views folder (with --view)")
    r.add_argument("--view", help="view name in --views, e.g. orbit04")
    r.add_argument("--strength", required=True, type=float, help="SDEdit strength in [0, 1]")
    r.add_argument(
        "--out", required=True, type=Path, help="output stem (--video) or folder (--views)"
    )
    r.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    r.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    r.add_argument("--device", default="cpu", help="auto, cpu or cuda (default cpu)")
    r.add_argument("--bit-depth", type=int, default=8, choices=[8, 16], help="PNG bit depth")
    r.set_defaults(func=_refine)


def _at_least_one(text: str) -> int:
    """argparse type: an integer ≥ 1."""
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def sample_grid(real: list[np.ndarray], samples: np.ndarray, gap: int = 2) -> np.ndarray:
    """uint8 image: rows of training windows above rows of samples, frames left to right.

    Args:
        real: (F, H, W) [0, 1] windows of training clips.
        samples: (n, F, H, W) [0, 1] generated videos.
    A black band of ``gap``·3 pixels separates the two groups.
    """
    rows = list(real) + [None] + list(samples)
    f, h, w = samples.shape[1:]
    tiles = []
    for r in rows:
        if r is None:
            tiles.append(np.zeros((3 * gap, f * (w + gap) - gap)))
            continue
        line = np.ones((h, f * (w + gap) - gap))
        for k in range(f):
            line[:, k * (w + gap) : k * (w + gap) + w] = r[k]
        tiles.append(line)
        tiles.append(np.ones((gap, line.shape[1])))
    img = np.concatenate(tiles[:-1])
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def train_prior(
    clips_spec: str,
    out: Path,
    backend: str = "embedded",
    params: dict | None = None,
    device: str = "cpu",
    n_samples: int = 4,
    log=print,
) -> dict:
    """Train a prior and write the whole OUT folder at once (built aside, then renamed)."""
    import cv2

    from surfphase.device import resolve_device
    from surfphase.io import atomic_dir, atomic_write_json
    from surfphase.prior.clips import find_clips, read_clips
    from surfphase.prior.interface import new_prior

    dev = resolve_device(device)
    find_clips(clips_spec)  # a missing clips folder fails before any model is built
    prior = new_prior(backend, params, device=dev)  # missing Wan weights fail here
    names, clips = read_clips(clips_spec)
    t0 = time.perf_counter()
    kwargs = {"names": names} if backend == "wan" else {}
    train_log = prior.train(clips, log=log, **kwargs)
    train_s = time.perf_counter() - t0
    frames = int(prior.params["frames"])
    frames = min(frames, min(c.shape[0] for c in clips))
    if backend == "wan":
        frames = 4 * ((frames - 1) // 4) + 1
    size = int(min(min(c.shape[1:]) for c in clips))
    t1 = time.perf_counter()
    samples = prior.sample(n_samples, frames, size, seed=int(prior.params["seed"]))
    sample_s = time.perf_counter() - t1
    real = [c[:frames, :size, :size] for c in clips[: min(2, len(clips))]]
    out = Path(out)
    with atomic_dir(out) as tmp:
        prior.save(tmp)
        if not cv2.imwrite(str(tmp / "samples.png"), sample_grid(real, samples)):
            raise OSError(f"could not write {out / 'samples.png'}")
        report = {
            "backend": backend,
            "clips": [str(c) for c in names],
            "clip_shapes": [list(c.shape) for c in clips],
            "params": prior.params,
            "device": str(dev),
            "threads": _torch_threads(),
            "train_s": round(train_s, 2),
            "sample_s": round(sample_s, 2),
            "samples_png": "samples: rows below the black band; training clips above",
            **{k: v for k, v in train_log.items() if k != "seconds"},
        }
        atomic_write_json(tmp / "train.json", report)
    return report


def _torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def _train(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    rep = train_prior(
        args.clips,
        args.out,
        args.backend,
        read_json_object(args.params_json),
        args.device,
        args.samples,
    )
    print(f"wrote {args.out} (training {rep['train_s']:.1f} s, samples {rep['sample_s']:.1f} s)")
    return 0


def refine_video(
    prior_dir: Path, video: Path, strength: float, out: Path, seed: int = 0, device="cpu",
    bit_depth: int = 8,
) -> dict:  # fmt: skip
    """Refine one view: read ``video``, SDEdit it, write ``out.npy`` and ``out/`` PNGs."""
    from surfphase.device import resolve_device
    from surfphase.io import atomic_write_json
    from surfphase.prior.clips import read_video, write_video
    from surfphase.prior.interface import load_prior
    from surfphase.prior.sdedit import check_strength

    check_strength(strength)
    frames = read_video(video)
    prior = load_prior(prior_dir, device=resolve_device(device))
    t0 = time.perf_counter()
    refined = prior.refine(frames, strength, seed)
    seconds = time.perf_counter() - t0
    out = Path(out)
    base = out.with_suffix("") if out.suffix == ".npy" else out
    info = {
        "prior": str(prior_dir),
        "backend": prior.backend,
        "video": str(video),
        "shape": list(refined.shape),
        "strength": strength,
        "seed": seed,
        "refine_s": round(seconds, 2),
        "mean_abs_change": float(np.abs(refined - frames).mean()),
    }
    base.mkdir(parents=True, exist_ok=True)
    atomic_write_json(base / "refine.json", info)
    write_video(base, refined, bit_depth)  # OUT.npy last
    return info


def refine_view(
    prior_dir: Path, views_dir: Path, view: str, strength: float, out_dir: Path, seed: int = 0,
    device="cpu",
) -> dict:  # fmt: skip
    """Refine orbit view ``view`` of a render-views folder into ``out_dir``.

    Writes ``out_dir/<view>.json`` (settings, timing), ``<view>.mp4`` (H.264 at the
    session's fps) and ``<view>.npy`` ((T, H, W) uint16, value·65535), in that order,
    each renamed into place from a private temporary folder ``.<view>.part-*`` that is
    created before the work starts; a stale one (left by a killed run) is removed first,
    so a rerun starts clean and gives the same arrays (the noise is seeded).
    """
    from surfphase.device import resolve_device
    from surfphase.folders.frames import to_uint16
    from surfphase.folders.views import read_views, write_refined
    from surfphase.io import part_dir
    from surfphase.prior.interface import load_prior
    from surfphase.prior.sdedit import check_strength

    check_strength(strength)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.glob(f".{view}.part-*"):
        shutil.rmtree(stale, ignore_errors=True)
    views = read_views(views_dir)
    frames, fps = views.frames(view), views.fps
    part = part_dir(out_dir / view)
    try:
        prior = load_prior(prior_dir, device=resolve_device(device))
        t0 = time.perf_counter()
        refined = prior.refine(frames, strength, seed)
        seconds = time.perf_counter() - t0
        stack = to_uint16(refined)
        info = {
            "prior": str(prior_dir),
            "backend": prior.backend,
            "views": str(views_dir),
            "view": view,
            "shape": list(stack.shape),
            "strength": strength,
            "seed": seed,
            "fps": fps,
            "threads": _torch_threads(),
            "refine_s": round(seconds, 2),
            "mean_abs_change": float(np.abs(stack / 65535.0 - frames).mean()),
        }
        write_refined(part, out_dir, view, refined, fps, info)
    finally:
        shutil.rmtree(part, ignore_errors=True)
    return info


def _refine(args: argparse.Namespace) -> int:
    _set_threads(args.threads)
    if args.views is not None:
        if not args.view:
            raise ValueError("refine: --views needs --view NAME (e.g. orbit04)")
        info = refine_view(
            args.prior, args.views, args.view, args.strength, args.out, args.seed, args.device
        )
        src = args.views / f"{args.view}.npy"
    else:
        info = refine_video(
            args.prior, args.video, args.strength, args.out, args.seed, args.device,
            args.bit_depth,
        )  # fmt: skip
        src = args.video
    print(
        f"refined {src} at strength {args.strength} in {info['refine_s']:.1f} s "
        f"(mean |change| {info['mean_abs_change']:.4f})"
    )
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "prior",
        help="time training of the embedded prior and SDEdit refinement of one view",
        description="Train the embedded prior on monocular clips (default: the demo's 8 "
        "synthetic clips of 24 frames at 128×128, generated into a temporary folder) and "
        "refine a 24-frame view at the near and far strengths; prints JSON.",
    )
    p.add_argument("--clips", help="clips to train on (default: generate the demo's)")
    p.add_argument("--params-json", help="embedded prior parameters (JSON object or file)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--device", default="cpu", help="auto, cpu or cuda (default cpu)")
    p.add_argument("--strengths", default="0.2,0.35", help="comma-separated SDEdit strengths")
    p.add_argument("--out", type=Path, help="keep the prior (with samples.png) here")
    p.set_defaults(func=_bench)


def _bench(args: argparse.Namespace) -> int:
    import torch

    from surfphase.prior.clips import read_clips

    _set_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="surfphase-bench-prior-") as tmp:
        clips_spec = args.clips
        clips_s = None
        if clips_spec is None:
            from surfphase.synth.monoclips import write_clip

            t0 = time.perf_counter()
            for k in range(8):
                seed = int(np.random.default_rng([0, 9001, k]).integers(0, 2**31))
                write_clip(Path(tmp) / "clips" / f"clip{k:03d}", seed, 24, 128, 8)
            clips_s = round(time.perf_counter() - t0, 2)
            clips_spec = str(Path(tmp) / "clips")
        out = args.out or Path(tmp) / "prior"
        c0 = time.process_time()
        rep = train_prior(
            clips_spec, out, "embedded", read_json_object(args.params_json), args.device
        )
        train_cpu = time.process_time() - c0
        _, clips = read_clips(clips_spec)
        view = clips[0]
        refines = []
        for s in (float(v) for v in args.strengths.split(",")):
            view_path = Path(tmp) / "view.npy"
            np.save(view_path, view)
            c1 = time.process_time()
            info = refine_video(out, view_path, s, Path(tmp) / f"refined_{s}", 0, args.device)
            refines.append(
                {
                    "strength": s,
                    "frames": int(view.shape[0]),
                    "size": list(view.shape[1:]),
                    "refine_s": info["refine_s"],
                    "cpu_s": round(time.process_time() - c1, 2),
                    "mean_abs_change": round(info["mean_abs_change"], 4),
                }
            )
    result = {
        "bench": "prior",
        "backend": "embedded",
        "device": args.device,
        "threads": torch.get_num_threads(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "clips_generate_s": clips_s,
        "clips": rep["clip_shapes"],
        "train_s": rep["train_s"],
        "train_and_sample_cpu_s": round(train_cpu, 2),
        "steps": rep["steps"],
        "loss_first50": round(rep["loss_first50"], 4),
        "loss_last50": round(rep["loss_last50"], 4),
        "sample_s": rep["sample_s"],
        "refine": refines,
        "params": rep["params"],
    }
    print(json.dumps(result, indent=1))
    return 0
