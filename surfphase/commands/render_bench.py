"""``surfphase bench render``: speed, memory and accuracy of the surfel rasterizer.

Only a benchmark is registered here; the ``render`` stage command lives elsewhere.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time


def register(subparsers) -> None:
    """No stage subcommand: this module only adds ``surfphase bench render``."""
    return None


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "render",
        help="rasterize_surfels forward+backward timings (and accuracy vs brute force)",
        description="Times forward + backward of rasterize_surfels on sphere scenes "
        "(surfphase.render.scenes.sphere_scene) and reports median seconds, pair counts "
        "and peak memory; --check also compares against the brute-force reference. "
        "With several --backends their repetitions are interleaved (a shared machine's "
        "load hits all alike) and, when sparse is one of them, the last line is each "
        "other backend's speedup over sparse per run.",
    )
    p.add_argument(
        "--runs",
        default="128:5000,256:20000",
        help="comma-separated SIZE:SURFELS image sizes (square) and surfel counts",
    )
    p.add_argument(
        "--backends",
        default="auto",
        help="comma-separated rasterizer backends to time: auto (fused on the CPU, torch "
        "on CUDA), fused, sparse (= torch)",
    )
    p.add_argument("--cameras", type=int, default=2, help="cameras per render")
    p.add_argument("--device", default="cpu", help="auto, cpu or cuda")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--repeats", type=int, default=7, help="timed repetitions per run")
    p.add_argument("--warmup", type=int, default=2, help="untimed repetitions per run")
    p.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    p.add_argument(
        "--max-pairs-per-chunk", type=int, default=4_000_000, help="rasterizer memory bound"
    )
    p.add_argument(
        "--forward-only", action="store_true", help="time the forward pass alone (no_grad)"
    )
    p.add_argument(
        "--check",
        action="store_true",
        help="also compare a 48×40 render with 60 surfels against the brute-force reference",
    )
    p.add_argument("--json", default=None, help="also write the results to this JSON file")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import torch

    from surfphase.device import resolve_device
    from surfphase.io import atomic_write_json

    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    dtype = getattr(torch, args.dtype)
    runs = []
    for item in args.runs.split(","):
        try:
            size, n = (int(v) for v in item.split(":"))
        except ValueError as e:
            raise ValueError(f"--runs: expected SIZE:SURFELS, got {item!r}") from e
        runs.append((size, n))
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    if not backends:
        raise ValueError("--backends: give at least one backend")
    results = {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "threads": args.threads,
        "cameras": args.cameras,
        "dtype": args.dtype,
        "max_pairs_per_chunk": args.max_pairs_per_chunk,
        "forward_only": args.forward_only,
        "backends": backends,
        "runs": [],
    }
    if args.check:
        results["check"] = {b: _check(device, b) for b in backends}
        print(f"accuracy vs reference: {json.dumps(results['check'])}", flush=True)
    speedups, cpu_speedups = [], []
    for size, n in runs:
        per_backend = _time_run(size, n, args, device, dtype, backends)
        for b, r in zip(backends, per_backend, strict=True):
            results["runs"].append(r)
            print(
                f"{b}: {args.cameras}x{size}x{size}, {n} surfels, {device.type}: "
                f"median {r['median_s']:.4f} s (min {r['min_s']:.4f}, "
                f"CPU {r['cpu_median_s']:.4f} s), "
                f"{r['pairs']} pairs, peak {r['peak_mib']:.0f} MiB "
                f"({r['peak_above_start_mib']:.0f} MiB above the start)",
                flush=True,
            )
        medians = {_canonical(b): r["median_s"] for b, r in zip(backends, per_backend, strict=True)}
        cpus = {
            _canonical(b): r["cpu_median_s"] for b, r in zip(backends, per_backend, strict=True)
        }
        others = [b for b in dict.fromkeys(map(_canonical, backends)) if b != "torch"]
        if "torch" in medians and others:
            ratios = ", ".join(f"{medians['torch'] / medians[b]:.1f}x" for b in others)
            speedups.append(f"{ratios} at {size}:{n}")
            ratios = ", ".join(f"{cpus['torch'] / cpus[b]:.1f}x" for b in others)
            cpu_speedups.append(f"{ratios} at {size}:{n}")
    if speedups:
        results["speedup_over_sparse"] = speedups
        results["cpu_time_speedup_over_sparse"] = cpu_speedups
    if args.json:
        atomic_write_json(args.json, results)
    if speedups:
        print(f"CPU-time speedup over sparse: {', '.join(cpu_speedups)}", flush=True)
        print(f"speedup over sparse: {', '.join(speedups)}", flush=True)
    return 0


def _canonical(backend: str) -> str:
    """Bench names → rasterizer backends: ``sparse`` is ``torch``."""
    return "torch" if backend == "sparse" else backend


def _time_run(size: int, n: int, args, device, dtype, backends: list[str]) -> list[dict]:
    """Time each backend on one scene, repetitions interleaved; one result per backend."""
    import torch

    from surfphase.render import rasterize_surfels
    from surfphase.render.scenes import sphere_scene

    scene = sphere_scene(n, args.cameras, size, seed=0, dtype=dtype, device=device)
    names = ["means", "quats", "scales", "opacities", "colors"]

    def once(backend: str) -> tuple[torch.Tensor, dict]:
        kw = dict(scene, max_pairs_per_chunk=args.max_pairs_per_chunk, backend=backend)
        if args.forward_only:
            with torch.no_grad():
                return rasterize_surfels(**kw)[1:]
        for k in names:
            kw[k] = scene[k].detach().requires_grad_(True)
        colors, alphas, meta = rasterize_surfels(**kw)
        loss = (
            colors.sum()
            + meta["depth_expected"].sum()
            + meta["depth_median"].sum()
            + meta["normals_world"].sum()
            + meta["normals_from_depth"].sum()
            + meta["distortion"].sum()
        )
        loss.backward()
        return alphas, meta

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    # Memory is measured from here (scene built, nothing rendered yet) to the end, over
    # all backends together.
    sync()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device) / 2**20
    else:
        base = _reset_peak_rss()
    for _ in range(args.warmup):
        for b in backends:
            once(b)
    sync()
    times = {b: [] for b in backends}
    cpu = {b: [] for b in backends}
    last = {}
    for _ in range(args.repeats):
        for b in backends:
            t0, c0 = time.perf_counter(), time.process_time()
            last[b] = once(b)
            sync()
            times[b].append(time.perf_counter() - t0)
            cpu[b].append(time.process_time() - c0)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        peak = _peak_rss_mib()
    out = []
    for b in backends:
        alphas, meta = last[b]
        out.append(
            {
                "backend": b,
                "size": size,
                "surfels": n,
                "median_s": statistics.median(times[b]),
                "min_s": min(times[b]),
                "times_s": times[b],
                # CPU seconds of the whole process (all threads): on a shared machine
                # much steadier than the wall clock.
                "cpu_median_s": statistics.median(cpu[b]),
                "pairs": meta["n_pairs"],
                "covered_fraction": float((alphas > 0.5).float().mean()),
                "visible": int(meta["visible"].sum()),
                "peak_mib": peak,
                "peak_above_start_mib": peak - base,
                "peak_kind": "cuda max_memory_allocated"
                if device.type == "cuda"
                else "process peak RSS (VmHWM, reset before the first render; all backends)",
            }
        )
    return out


def _check(device, backend: str = "auto") -> dict:
    import torch

    from surfphase.render import rasterize_surfels
    from surfphase.render.reference import rasterize_surfels_reference
    from surfphase.render.scenes import sphere_scene

    out = {}
    for dtype in (torch.float64, torch.float32):
        scene = sphere_scene(60, 2, 48, seed=1, dtype=dtype, device=device)
        scene["width"], scene["height"] = 48, 40
        colors, alphas, meta = rasterize_surfels(**scene, backend=_canonical(backend))
        ref = rasterize_surfels_reference(**scene)
        errs = {"colors": (colors - ref["colors"]).abs().max().item()}
        errs["alphas"] = (alphas - ref["alphas"]).abs().max().item()
        for k in (
            "depth_expected",
            "depth_median",
            "normals_camera",
            "normals_world",
            "normals_from_depth",
            "distortion",
        ):
            errs[k] = (meta[k] - ref[k]).abs().max().item()
        out[str(dtype).removeprefix("torch.")] = max(errs.values())
    return out


def _reset_peak_rss() -> float:
    """Reset the process's peak RSS (Linux ``clear_refs``) and return the current RSS, MiB."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return _status_mib("VmRSS")
    except OSError:
        return _peak_rss_mib()


def _peak_rss_mib() -> float:
    """Peak RSS since the last reset (VmHWM), else the lifetime maximum, MiB."""
    try:
        return _status_mib("VmHWM")
    except OSError:
        kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return kib / 1024 if sys.platform != "darwin" else kib / 2**20


def _status_mib(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    raise OSError(f"/proc/self/status has no {field}")
