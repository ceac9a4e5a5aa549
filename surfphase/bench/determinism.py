"""``surfphase bench determinism``: one campaign run twice, idle and beside a CPU-bound
process, every output compared byte for byte (timing fields aside).

The same inputs, config, seed and thread count must give the same bytes on the CPU,
whatever else the machine is doing. The run is sized so that the fit holds more than
10,000 surfels, where threaded reductions with a run-dependent order (the backward of
``x[idx]`` with repeated indices) once made two runs differ within a few frames.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from surfphase.bench.compare import TIMING_KEYS, compare_trees

ROOT = Path(__file__).resolve().parents[2]


def _spin(stop_after: float) -> None:  # pragma: no cover - runs in a child process
    end = time.monotonic() + stop_after
    x = 0
    while time.monotonic() < end:
        x += 1


def write_config(work: Path, campaign: Path, settings: dict) -> Path:
    """The run's ``config/config.yaml`` in ``work``, reading ``campaign``'s sheets."""
    import yaml

    cfg = {
        "sessions": str(campaign / "sessions.tsv"),
        "rigs": str(campaign / "rigs.tsv"),
        "results": "results",
        "device": "cpu",
        "threads": int(settings["threads"]),
        "ingest": {"scale": float(settings["scale"])},
        "fit": {
            "n_init": int(settings["n_init"]),
            "max_surfels": int(settings["n_init"]),
            "hull_grid": int(settings["hull_grid"]),
            "iters_first": int(settings["iters_first"]),
            "iters_next": int(settings["iters_next"]),
        },
        "mesh": {"voxels": int(settings["voxels"]), "n_orbit": int(settings["n_orbit"])},
        "refine": {"enabled": bool(settings["stage2"])},
        "report": {"videos": False},
    }
    if settings["stage2"]:
        cfg["prior"] = {"clips": str(campaign / "clips"), "embedded": {"steps": 20}}
        cfg["refine"]["n_views"] = 3
        cfg["fit2"] = {"iters_first": 10, "iters_next": int(settings["iters_next"])}
    (work / "config").mkdir(parents=True, exist_ok=True)
    path = work / "config" / "config.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def run_twice(work: Path, settings: dict, log=print) -> dict:
    """Generate the campaign, run it idle and loaded, compare → a summary dict."""
    from surfphase.synth.campaign import write_campaign

    work = Path(work)
    campaign = work / "campaign"
    if not (campaign / "synth.json").is_file():
        write_campaign(
            campaign, preset="tiny", seed=int(settings["seed"]), overwrite=True, sessions=1,
            frames=int(settings["frames"]), native=int(settings["native"]),
        )  # fmt: skip
    target = {
        "evaluate": "results/session01/evaluate/metrics.json",
        "mesh": "results/session01/mesh",
        "fit": "results/session01/fit/surfels.npz",
    }[settings.get("target", "evaluate")]
    runs = {}
    for name in ("idle", "loaded"):
        wd = work / name
        write_config(wd, campaign, settings)
        load = []
        if name == "loaded":
            load = [mp.Process(target=_spin, args=(3600.0,), daemon=True)
                    for _ in range(int(settings["load_processes"]))]  # fmt: skip
            for p in load:
                p.start()
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(wd),
               "--cores", str(settings["threads"]), "--forceall", target]  # fmt: skip
        res = subprocess.run(cmd, capture_output=True, text=True)
        for p in load:
            p.terminate()
            p.join()
        if res.returncode != 0:
            raise RuntimeError(f"{name} run failed (see {wd}/logs):\n{res.stderr[-3000:]}")
        runs[name] = round(time.perf_counter() - t0, 1)
        log(f"{name} run: {runs[name]} s")
    cmp = compare_trees(work / "idle" / "results", work / "loaded" / "results")
    with np.load(work / "idle" / "results" / "session01" / "fit" / "surfels.npz") as z:
        surfels = int(z["alive"].sum(axis=1).max())
    return {
        "settings": settings,
        "seconds": runs,
        "max_surfels": surfels,
        "files_compared": len(cmp["same"]) + len(cmp["differ"]),
        "identical": not (cmp["differ"] or cmp["only_a"] or cmp["only_b"]),
        "differ": cmp["differ"],
        "only_idle": cmp["only_a"],
        "only_loaded": cmp["only_b"],
        "timing_keys_ignored": sorted(TIMING_KEYS),
    }


def report(summary: dict) -> str:
    """Human-readable lines of :func:`run_twice`'s summary."""
    s = summary
    lines = [
        f"max surfels in a frame: {s['max_surfels']}; files compared: {s['files_compared']}",
        f"run times: idle {s['seconds']['idle']} s, loaded {s['seconds']['loaded']} s",
        "timing fields ignored: " + ", ".join(s["timing_keys_ignored"]),
    ]
    for rel, why in s["differ"].items():
        lines.append(f"DIFFERS {rel}: {why}")
    for rel in s["only_idle"] + s["only_loaded"]:
        lines.append(f"ONLY IN ONE RUN {rel}")
    lines.append("identical" if s["identical"] else "NOT identical")
    return "\n".join(lines)


def main(args) -> int:
    settings = {k: getattr(args, k) for k in (
        "frames", "native", "scale", "n_init", "hull_grid", "iters_first", "iters_next", "voxels",
        "n_orbit", "threads", "seed", "load_processes", "stage2", "target")}  # fmt: skip
    summary = run_twice(Path(args.work), settings)
    print(report(summary))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1))
    return 0 if summary["identical"] else 1
