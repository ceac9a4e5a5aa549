"""``surfphase bench fit``: the stage-1 fit on the default synthetic session.

Builds (once, cached under the working folder) session01 of the ``demo`` campaign
(``surfphase.synth.campaign.write_campaign(..., preset="demo", seed=0, sessions=1,
clips=0)``: 2 input views, 24 frames at 1500 fps), ingests it at the fit scale (0.25:
128×128) with the true calibration, segments it with the mask stage's defaults, and
fits it with and without bubble guidance. Reports input-view PSNR, held-out ``mid``
view PSNR, the bubble velocity error against the ground truth and timings.

This benchmark imports :mod:`surfphase.synth` for its ground truth; the fit stage
(:mod:`surfphase.fit`) never does.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.optimize import linear_sum_assignment

from surfphase.cameras import load_cameras
from surfphase.fit.outputs import load_surfels, render_surfels


def match_bubbles(pred: pd.DataFrame, gt: pd.DataFrame, max_dist: float) -> pd.DataFrame:
    """Match predicted to true bubbles per frame (Hungarian on centroid distance, metres).

    Both tables have ``frame, bubble, x, y, z, vx, vy, vz``. Pairs further apart than
    ``max_dist`` are dropped. Returns one row per match: ``frame, bubble, gt_bubble,
    dist, vx, vy, vz, gvx, gvy, gvz``.
    """
    rows = []
    for f, p in pred.groupby("frame"):
        g = gt[gt.frame == f]
        if g.empty:
            continue
        P, G = p[["x", "y", "z"]].to_numpy(), g[["x", "y", "z"]].to_numpy()
        d = np.linalg.norm(P[:, None] - G[None], axis=-1)
        ri, ci = linear_sum_assignment(d)
        for i, j in zip(ri, ci, strict=True):
            if d[i, j] > max_dist:
                continue
            rows.append(
                {
                    "frame": int(f),
                    "bubble": int(p.bubble.iloc[i]),
                    "gt_bubble": int(g.bubble.iloc[j]),
                    "dist": float(d[i, j]),
                    **{k: float(p[k].iloc[i]) for k in ("vx", "vy", "vz")},
                    **{f"g{k}": float(g[k].iloc[j]) for k in ("vx", "vy", "vz")},
                }
            )
    cols = ["frame", "bubble", "gt_bubble", "dist", "vx", "vy", "vz", "gvx", "gvy", "gvz"]
    return pd.DataFrame(rows, columns=cols)


def velocity_error(matches: pd.DataFrame) -> float:
    """Mean over bubble-frames of ``|v − v_gt|`` divided by the mean ``|v_gt|``."""
    m = matches.dropna(subset=["vx", "vy", "vz"])
    if m.empty:
        return float("nan")
    v = m[["vx", "vy", "vz"]].to_numpy()
    g = m[["gvx", "gvy", "gvz"]].to_numpy()
    return float(np.linalg.norm(v - g, axis=1).mean() / np.linalg.norm(g, axis=1).mean())


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-12))


def prepare_demo(work: Path) -> dict:
    """Build (or reuse) the demo session's campaign, ingest and masks under ``work``."""
    camp = work / "campaign"
    sess = camp / "session01"
    if not (sess / "gt" / "bubbles.csv").exists():
        from surfphase.synth.campaign import write_campaign

        write_campaign(camp, preset="demo", seed=0, overwrite=True, sessions=1, clips=0)
    gt_json = json.loads((sess / "gt" / "cameras.json").read_text())
    cams = load_cameras(sess / "gt" / "cameras.json")
    fps = float(gt_json["fps"])
    scale = float(gt_json.get("fit_scale", 0.25))
    ingest, masks = work / "ingest", work / "masks"
    if not (ingest / "meta.json").exists():
        from surfphase.ingest import ingest_session

        ingest_session(
            "session01",
            {n: cams[n] for n in ("cam0", "cam1")},
            {n: sess / n for n in ("cam0", "cam1")},
            fps=fps,
            scale=scale,
            out=ingest,
        )
    if not (masks / "instances.csv").exists():
        from surfphase.masks.stage import run_mask_stage

        run_mask_stage(ingest, masks)
    return {"session": sess, "ingest": ingest, "masks": masks, "cameras": cams, "fps": fps}


def heldout_psnr(out: Path, sess: Path, cams: dict, device: str) -> list[float]:
    """PSNR (dB) of the fit rendered into the held-out ``mid`` camera, per frame.

    The fit reconstructs the bubbles only; behind them the held-out view sees the mean of
    the input views' background images (backlight and plate are not reconstructed).
    """
    from surfphase.eval.heldout import read_view

    surfels = load_surfels(out / "surfels.npz")
    mid = cams["mid"]
    bg = surfels["bg_images"].mean(axis=0, keepdims=True)
    vals = []
    for t, f in enumerate(surfels["frame"]):
        path = sess / "gt" / "views" / "mid" / f"{int(f):06d}.png"
        if not path.exists():
            continue
        gt = read_view(path)  # by the PNG's bit depth
        rgb = render_surfels(surfels, t, [mid], device, bg)[0, ..., 0]
        vals.append(psnr(rgb, gt))
    return vals


def evaluate(out: Path, sess: Path, cams: dict, device: str, max_dist: float) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    pred = pd.read_csv(out / "bubbles.csv")
    gt = pd.read_csv(sess / "gt" / "bubbles.csv")
    res = {
        "input_psnr_mean_db": summary["psnr_mean"],
        "input_psnr_min_db": float(np.min(summary["psnr_per_frame"])),
        "seconds_first_frame": summary["seconds_first_frame"],
        "seconds_per_later_frame": summary["seconds_per_later_frame"],
        "seconds_per_iter": summary["seconds_per_iter"],
        "n_surfels_final": summary["n_surfels"][-1],
    }
    mid = heldout_psnr(out, sess, cams, device)
    res["heldout_mid_psnr_mean_db"] = float(np.mean(mid)) if mid else None
    for label, sel in (("bubbles", pred.bubble >= 1), ("all_regions", pred.bubble >= 0)):
        m = match_bubbles(pred[sel], gt, max_dist)
        res[f"velocity_error_{label}"] = velocity_error(m)
        res[f"matched_bubble_frames_{label}"] = int(m.dropna(subset=["vx"]).shape[0])
        m.to_csv(out / f"velocity_matches_{label}.csv", index=False)
    res["gt_bubble_frames"] = int(gt[gt.frame.isin(pred.frame.unique())].shape[0])
    return res


#: Benchmark variants: fit parameters added to the run's own.
VARIANTS = {
    "guided": {},
    "no_guidance": {"guidance": False},
    "no_sdf": {"use_sdf": False},
}


def run_benchmark(
    work: Path,
    frames: int = 24,
    threads: int = 2,
    device: str = "cpu",
    variants: tuple[str, ...] = ("guided", "no_guidance"),
    params: dict | None = None,
    max_dist: float = 1.5e-3,
) -> dict:
    """Run the benchmark variants; write ``work/result_<variant>.json`` and
    ``work/result.json`` (every variant found in ``work``), return the latter.

    ``max_dist`` (m) gates the matching of predicted to true bubbles.
    """
    from surfphase.fit.stage import run_fit

    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"bench fit: unknown variants {unknown}; known: {sorted(VARIANTS)}")
    torch.set_num_threads(threads)
    # The first optimiser a process builds imports torch._dynamo (1.5-2.5 s here), which
    # the first frame's steps would otherwise carry: build one before the timings.
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    demo = prepare_demo(work)
    prepare_s = time.perf_counter() - t0
    for name in variants:
        out = work / f"fit_{name}"
        t1 = time.perf_counter()
        run_fit(
            demo["ingest"],
            demo["masks"],
            out,
            {**(params or {}), **VARIANTS[name], "frames": frames},
            device=device,
            checkpoint_dir=work / f"fit_{name}.ckpt",
        )
        r = evaluate(out, demo["session"], demo["cameras"], device, max_dist)
        r.update(
            {
                "wall_s": time.perf_counter() - t1,
                "frames": frames,
                "threads": threads,
                "device": device,
                "params": params or {},
            }
        )
        (work / f"result_{name}.json").write_text(json.dumps(r, indent=1))
    result: dict = {"prepare_s": prepare_s}
    for name in VARIANTS:
        f = work / f"result_{name}.json"
        if f.exists():
            result[name] = json.loads(f.read_text())
    if "guided" in result and "no_guidance" in result:
        g = result["guided"]["velocity_error_bubbles"]
        u = result["no_guidance"]["velocity_error_bubbles"]
        result["no_guidance_over_guided"] = u / g if g else None
    (work / "result.json").write_text(json.dumps(result, indent=1))
    return result
