"""``surfphase bench stability``: how far the bubble tracks move when the input frames
get a tiny amount of noise.

A campaign working folder where the workflow already ran (e.g. ``bench accuracy``'s
``WORK/run``) gives the inputs: its config, calibration and ingested frame stacks
(float32 in [0, 1]). For each session the mask stage and the stage-1 fit run twice, in
working folders of their own, with this code and that config: on the frames as they are
(the reference) and with Gaussian noise of standard deviation ``noise`` (1e-4 of the
range: ~6 grey levels of 16 bits) added. The noisy ``bubbles.csv`` is matched to the
reference one frame by frame (Hungarian on the
centroids, gate 0.5 mm) and the changes of centroid and velocity are reported, mean and
worst, leaving out each bubble's frames within ``event_margin`` frames of a merge or a
split it takes part in (each run's own ``masks/events.csv``: the runs' ids may differ,
so rows are matched on position first), where a last-bit change may
legitimately move the frame a merge is detected at. The target: the worst velocity
change below 1 % of the session's mean bubble speed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[2]
GATE_M = 0.5e-3  # matching gate of noisy to reference bubbles, metres


def add_noise(stack: np.ndarray, noise: float, seed: int) -> np.ndarray:
    """(T, H, W) frames plus N(0, noise²) of their range, clipped to it: float32 frames
    in [0, 1], or integer frames (the ingest's native uint16) over their dtype's range,
    rounded back to that dtype."""
    rng = np.random.default_rng(seed)
    a = np.asarray(stack)
    full = float(np.iinfo(a.dtype).max) if np.issubdtype(a.dtype, np.integer) else 1.0
    out = a.astype(np.float32) / np.float32(full)
    out = np.clip(out + rng.normal(0.0, noise, a.shape).astype(np.float32), 0.0, 1.0)
    if full == 1.0:
        return out
    return np.round(out * full).astype(a.dtype)


def event_bubble_frames(events_csv: Path, margin: int) -> set[tuple[int, int]]:
    """``(frame, bubble)`` within ``margin`` frames of a merge or a split that bubble
    takes part in (as a parent or a child) in ``events.csv``."""
    if not events_csv.is_file():
        return set()
    ev = pd.read_csv(events_csv, dtype={"parents": str, "children": str})
    ev = ev[ev["event"].isin(["merge", "split"])]
    out: set[tuple[int, int]] = set()
    for f, parents, children in ev[["frame", "parents", "children"]].itertuples(index=False):
        ids = {
            int(b) for b in f"{parents}+{children}".split("+") if b.strip().lstrip("-").isdigit()
        }
        out |= {(int(f) + d, b) for b in ids for d in range(-margin, margin + 1)}
    return out


def track_changes(
    ref: pd.DataFrame,
    noisy: pd.DataFrame,
    skip_ref: set[tuple[int, int]],
    skip_noisy: set[tuple[int, int]] | None = None,
) -> dict:
    """Centroid (m) and velocity (m/s) changes of matched bubble-frames, ids ≥ 1; plus
    the reference's mean speed and the unmatched counts.

    The two tables are matched frame by frame on position first (their ids may differ:
    ids are numbered in order of appearance); a matched pair is then left out when
    either side's ``(frame, bubble)`` is in its own run's skip set (``skip_ref``,
    ``skip_noisy``, default the same); a reference row without a match within the gate
    counts as unmatched unless it is in ``skip_ref``."""
    from surfphase.eval.velocity import match_bubbles

    skip_noisy = skip_ref if skip_noisy is None else skip_noisy

    def in_skip(frames, bubbles, skip) -> np.ndarray:
        pairs = zip(np.asarray(frames, int), np.asarray(bubbles, int), strict=True)
        return np.array([p in skip for p in pairs], dtype=bool)

    r, n = ref[ref["bubble"] >= 1], noisy[noisy["bubble"] >= 1]
    m = match_bubbles(n, r, max_dist=GATE_M)
    matched_ref = set(zip(m["frame"].astype(int), m["gt_bubble"].astype(int), strict=True))
    if len(m):
        m = m[
            ~in_skip(m["frame"], m["bubble"], skip_noisy)
            & ~in_skip(m["frame"], m["gt_bubble"], skip_ref)
        ]
    r = r[~in_skip(r["frame"], r["bubble"], skip_ref)]
    n_unmatched = int(sum(p not in matched_ref for p in zip(r["frame"], r["bubble"], strict=True)))
    dv = m["abs_error_mps"].to_numpy(np.float64)
    dv = dv[np.isfinite(dv)]
    speed = np.linalg.norm(r[["vx", "vy", "vz"]].to_numpy(np.float64), axis=1)
    mean_speed = float(np.nanmean(speed)) if len(speed) else float("nan")
    out = {
        "bubble_frames_ref": int(len(r)),
        "matched": int(len(m)),
        "unmatched_ref": n_unmatched,
        "mean_speed_mps": mean_speed,
        "centroid_mean_um": float(m["dist_m"].mean() * 1e6) if len(m) else float("nan"),
        "centroid_worst_um": float(m["dist_m"].max() * 1e6) if len(m) else float("nan"),
        "velocity_mean_mps": float(dv.mean()) if len(dv) else float("nan"),
        "velocity_worst_mps": float(dv.max()) if len(dv) else float("nan"),
    }
    out["velocity_worst_pct_of_speed"] = 100.0 * out["velocity_worst_mps"] / mean_speed
    return out


def perturbed_run(ref_dir: Path, work: Path, session: str, noise: float, seed: int,
                  cores: int) -> Path:  # fmt: skip
    """Copy the reference's config, calibration and ``session``'s ingest (with noise)
    into ``work``; rerun mask and fit there; return the noisy ``bubbles.csv``."""
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(ref_dir / "config", work / "config")
    res_ref, res = ref_dir / "results", work / "results"
    shutil.copytree(res_ref / "calib", res / "calib")
    ing_ref, ing = res_ref / session / "ingest", res / session / "ingest"
    shutil.copytree(ing_ref, ing)
    # The fitted frames, and the native ones the mask stage segments (ingest/native/).
    cams = sorted(ing_ref.glob("*.npy")) + sorted(ing_ref.glob("native/*.npy"))
    for k, p in enumerate(cams):
        if noise > 0:
            stack = np.load(p, mmap_mode="r")
            np.save(ing / p.relative_to(ing_ref), add_noise(stack, noise, seed * 1000 + k))
    # The copies are the newest files: only the mask stage and the fit are out of date
    # (and only modification times decide: the copies carry no Snakemake records).
    now = time.time()
    for p in res.rglob("*"):
        os.utime(p, (now, now))
    target = f"results/{session}/fit/bubbles.csv"
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work),
           "--cores", str(cores), target, "--rerun-triggers", "mtime"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"session {session}: the rerun failed (logs in {work}/logs)")
    if (work / "logs" / "ingest").exists() or (work / "logs" / "calibrate").exists():
        raise RuntimeError(f"session {session}: the rerun redid the ingest (noise lost)")
    return work / target


def run_stability(ref_dir: Path, work: Path, sessions: list[str] | None, noise: float,
                  seed: int, margin: int, cores: int, log=print) -> list[dict]:  # fmt: skip
    """Every session of the reference folder (or ``sessions``) → one row each."""
    ref_dir, work = Path(ref_dir).resolve(), Path(work).resolve()
    found = sorted(p.parent.name for p in (ref_dir / "results").glob("*/ingest"))
    names = sessions or found
    rows = []
    for s in names:
        if not (ref_dir / "results" / s / "ingest").is_dir():
            raise FileNotFoundError(f"session {s}: no ingest in {ref_dir / 'results' / s}")
        ref_csv = perturbed_run(ref_dir, work / s / "clean", s, 0.0, seed, cores)
        noisy = perturbed_run(ref_dir, work / s / "noisy", s, noise, seed, cores)
        skip = [event_bubble_frames(work / s / run / "results" / s / "masks" / "events.csv",
                                    margin) for run in ("clean", "noisy")]  # fmt: skip
        changes = track_changes(pd.read_csv(ref_csv), pd.read_csv(noisy), *skip)
        row = {"session": s, **changes}
        rows.append(row)
        log(f"{s}: worst velocity change {row['velocity_worst_mps']:.4f} m/s = "
            f"{row['velocity_worst_pct_of_speed']:.2f} % of the mean speed")  # fmt: skip
    return rows


def format_rows(rows: list[dict], noise: float, margin: int) -> str:
    """Markdown table of :func:`run_stability`'s rows, with mean and worst rows."""
    cols = [("centroid_mean_um", "Δcentroid mean µm", "{:.1f}"),
            ("centroid_worst_um", "Δcentroid worst µm", "{:.1f}"),
            ("velocity_mean_mps", "Δv mean m/s", "{:.4f}"),
            ("velocity_worst_mps", "Δv worst m/s", "{:.4f}"),
            ("velocity_worst_pct_of_speed", "Δv worst % of mean speed", "{:.2f}"),
            ("matched", "matched", "{:d}"), ("unmatched_ref", "unmatched", "{:d}")]  # fmt: skip
    head = "| session | " + " | ".join(c[1] for c in cols) + " |"
    lines = [head, "|" + " --- |" * (len(cols) + 1)]
    for r in rows:
        lines.append(f"| {r['session']} | " + " | ".join(f.format(r[k]) for k, _, f in cols) + " |")
    for name, agg in (("mean", np.nanmean), ("worst", np.nanmax)):
        vals = [agg([r[k] for r in rows]) for k, _, _ in cols]
        lines.append(f"| **{name}** | " + " | ".join(
            (f.format(int(v)) if "d" in f else f.format(v)) for v, (_, _, f) in zip(vals, cols, strict=True)
        ) + " |")  # fmt: skip
    lines.append("")
    lines.append(f"Noise σ = {noise:g} of the range on every ingested frame; each bubble's "
                 f"frames within {margin} of a merge or split it takes part in left out; "
                 f"gate {GATE_M * 1e3:g} mm; "
                 "target: Δv worst < 1 % of the mean speed.")  # fmt: skip
    return "\n".join(lines)


def main(args) -> int:
    rows = run_stability(Path(args.run), Path(args.work), args.session or None, args.noise,
                         args.seed, args.margin, args.cores)  # fmt: skip
    text = format_rows(rows, args.noise, args.margin)
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0
