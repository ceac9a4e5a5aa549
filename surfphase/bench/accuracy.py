"""``surfphase bench accuracy``: the default workflow on the varied synthetic preset,
scored against the truth beside the classical two-view baseline.

Steps (:func:`run_accuracy_bench`):

1. the campaign: ``surfphase synth --preset bench`` (``--preset bench-mixed``: its
   settings recombined by the seed; ``bench-drawn``: settings drawn by the seed from
   the ranges it spans; or a given campaign), written once;
2. the workflow on it with the config ``surfphase new-campaign`` writes (the project's
   ``config/config.yaml``) and :data:`BENCH_CONFIG` on top — refinement off, ingest
   scale 0.5 (the presets' native frames are 208–336 px) — through its ``evaluate``
   stage (:func:`write_run_campaign`, then ``surfphase run``);
3. the classical baseline at the recordings' native resolution: the session ingested at
   scale 1 with the calibrated cameras, masked with the same ``masks:`` settings, mask
   centroids triangulated (:func:`surfphase.eval.baseline.baseline_bubbles`), velocities
   raw (finite differences) and smoothed along each track
   (:func:`surfphase.eval.baseline.smoothed_velocity`), the smoothing's window (seconds)
   and order chosen on a grid to minimise the baseline's own mean relative velocity
   error over the sessions scored (an oracle choice: the strongest bar);
4. per session the metrics of :func:`session_metrics` from the workflow's outputs
   (``fit/bubbles.csv``, ``mesh/*.ply``, ``evaluate/metrics.json``) and the truth
   (``gt/``), then one table: a row per session, the mean and the worst.

Matching (velocities, precision and recall): per frame, reported and true centroids are
paired one-to-one by the Hungarian algorithm on ``distance / r_eq`` of the true bubble,
gated at :data:`GATE_R_EQ` (0.5 r_eq) before the assignment
(:func:`surfphase.eval.velocity.gated_assignment`: most pairs within the gate first). Reported bubble-frames are the rows of the fit's
``bubbles.csv``: ids ≥ 1 count as real when matched, the nucleation region (id 0) when a
true bubble is attached to the plate in that frame (its surface within
:data:`ATTACHED_R_EQ` r_eq of it). Recall is over the free (not attached) true
bubble-frames seen in both input views (gt masks). "v rel" is over each table's own
matched bubble-frames, so a bubble-frame that only one of them reports counts for that
one alone; the "both report" columns score the method and the smoothed baseline on the
true bubble-frames both match, over one mean true speed
(:func:`~surfphase.bench.accuracy_metrics.paired_velocity_scores`), and give how many
there are. "recall, centre in both frames"
over those whose true centroid also projects inside both images (a bubble leaving the
frame is seen while its centre is already outside). "volume err %" is the meshes'
(the components each true bubble owns) over all the true bubble-frames seen in both
views, a bubble partly outside the frame included; "volume err %: reported" the volumes
of the evaluation's ``bubbles.csv`` over the reported bubble-frames matched to a true
bubble that have one, and "of which cut" the share of those the image border cuts in
some view (their sizes rest on silhouettes completed beyond the border).
Surfaces are compared on area-uniform samples
(:func:`surfphase.eval.geometry.sample_surface`): each true sample belongs to the true
bubble nearest in ``distance / r_eq`` to its centroid.

The per-session figures are :mod:`surfphase.bench.accuracy_metrics`; this module runs the
bench, chooses the smoothing and writes the table.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from surfphase.bench.accuracy_metrics import (
    GATE_R_EQ,
    SAMPLES,
    VEL,
    XYZ,
    nanmean,
    paired_velocity_scores,
    session_metrics,
    velocity_scores,
)
from surfphase.eval import baseline as bl
from surfphase.io import atomic_write_json, code_fingerprint

#: Config on top of ``surfphase new-campaign``'s defaults.
BENCH_CONFIG = {"ingest": {"scale": 0.5}, "refine": {"enabled": False}}
#: Grid of the baseline's track smoothing: windows (s) and polynomial orders.
SMOOTH_WINDOWS_S = (1e-3, 2e-3, 3e-3, 5e-3, 8e-3, 12e-3, 20e-3)
SMOOTH_ORDERS = (1, 2, 3)


def smoothed_table(base: pd.DataFrame, fps: float, window_s: float, order: int) -> pd.DataFrame:
    """The baseline's table with velocities from track smoothing (window s, order)."""
    out = base.copy()
    if len(out):
        out[VEL] = bl.smoothed_velocity(
            out["bubble"].to_numpy(), out["frame"].to_numpy(), out["time_s"].to_numpy(),
            out[XYZ].to_numpy(), fps, window_s, order,
        )  # fmt: skip
    return out


def method_track_inputs(fit_dir: Path) -> tuple:
    """What the method's ``bubbles.csv`` is computed from after the fit's optimisation:
    ``(table, anchors, nucleation, n_frames)`` — the surfels' per-bubble table
    (:func:`surfphase.fit.outputs.bubble_table`, unsmoothed), the masks' ``anchors.csv``
    (``None`` without ``fit: anchor_centres``), the nucleation region's frames and the
    frame count. Read once, for :func:`method_track_table` to smooth many ways."""
    from surfphase.fit.outputs import bubble_table, nucleation_frames
    from surfphase.folders.fit import read_fit_surfels
    from surfphase.folders.ingest import read_ingest
    from surfphase.folders.masks import read_anchors, read_masks

    arrays = read_fit_surfels(fit_dir)
    # The workflow's layout: results/<session>/{ingest,masks,fit}.
    ingest = read_ingest(Path(fit_dir).parent / "ingest")
    masks = Path(fit_dir).parent / "masks"
    anchors = read_anchors(masks, ingest.session)
    frames = np.asarray(arrays["frame"], dtype=np.int64)
    if anchors is None:
        return arrays, None, None, len(frames)
    cams = ingest.input_cameras()
    labels = list(read_masks(masks, cams, ingest.session).labels.values())
    nuc = nucleation_frames(labels, frames, cams)
    return bubble_table(arrays, arrays["time_s"], frames), anchors, nuc, len(frames)


def method_track_table(
    fit_dir: Path | tuple,
    window_s: float,
    order: int,
    min_track_frames: int | None = None,
    rules: tuple | None = None,
    min_visible: float | None = None,
) -> pd.DataFrame:
    """The method's ``bubbles.csv`` as ``fit: track_window_s = window_s`` (and
    ``track_order``; the other track settings ``rules``, as
    :func:`~surfphase.fit.outputs.track_rules` gives them, and ``track_min_visible =
    min_visible``, by default the fit's defaults) writes it, computed from the same fit's ``surfels.npz`` and, when the
    session's masks have them (``fit: anchor_centres``), their ``anchors.csv``
    (:func:`surfphase.fit.outputs.bubble_table`, :func:`~surfphase.fit.outputs.anchored_table`:
    the table is a function of these). ``fit_dir``: the fit's folder, or what
    :func:`method_track_inputs` read from it."""
    from surfphase.fit.outputs import anchored_table, bubble_table, track_rules
    from surfphase.fit.stage import DEFAULTS

    if rules is None:
        rules = track_rules(DEFAULTS)
    table, anchors, nuc, n_frames = (
        fit_dir if isinstance(fit_dir, tuple) else method_track_inputs(fit_dir)
    )
    if anchors is None:
        return bubble_table(table, table["time_s"], table["frame"], window_s, order, rules)
    if min_track_frames is None:
        min_track_frames = int(DEFAULTS["min_track_frames"])
    if min_visible is None:
        min_visible = float(DEFAULTS["track_min_visible"])
    return anchored_table(
        table, anchors, nuc, window_s, order, min_track_frames, n_frames, rules,
        min_visible, int(DEFAULTS["track_gap_frames"]),
    )  # fmt: skip


def track_consistency(pred: pd.DataFrame) -> float:
    """Mean |d/dt centroid − velocity| (m/s) over bubble-frames (ids ≥ 1) inside a run of
    the same id: the centroid track's own central difference against the reported
    velocity (0 when a user who differentiates the trajectory gets the same velocity)."""
    errs = []
    for _, g in pred[pred["bubble"] >= 1].sort_values("frame").groupby("bubble"):
        f = g["frame"].to_numpy()
        t = g["time_s"].to_numpy()
        x = g[XYZ].to_numpy(np.float64)
        v = g[VEL].to_numpy(np.float64)
        for i in range(1, len(g) - 1):
            if f[i - 1] == f[i] - 1 and f[i + 1] == f[i] + 1:
                d = (x[i + 1] - x[i - 1]) / (t[i + 1] - t[i - 1])
                if np.isfinite(v[i]).all():
                    errs.append(float(np.linalg.norm(d - v[i])))
    return float(np.mean(errs)) if errs else math.nan


def choose_method_smoothing(
    fits: dict[str, Path], truth: dict[str, pd.DataFrame]
) -> tuple[tuple[float, int], pd.DataFrame]:
    """As :func:`choose_smoothing`, for the method's own tracks (``fit: track_window_s``)."""
    return _best_on_grid(
        lambda w, o: [
            velocity_scores(method_track_table(d, w, o), truth[s])["relative_error"]
            for s, d in fits.items()
        ],
        SMOOTH_WINDOWS_S,
        SMOOTH_ORDERS,
    )


# --- the table ------------------------------------------------------------------------

#: (column title, getter, better: "low" | "high" | "one", format) of the table.
COLUMNS = [
    ("v rel: method", ("method", "relative_error"), "low", "{:.3f}"),
    ("v rel: baseline raw", ("baseline_raw", "relative_error"), "low", "{:.3f}"),
    ("v rel: baseline smoothed", ("baseline_smoothed", "relative_error"), "low", "{:.3f}"),
    ("v rel, both report: method", ("paired", "method"), "low", "{:.3f}"),
    ("v rel, both report: smoothed", ("paired", "baseline"), "low", "{:.3f}"),
    ("bubble-frames both report", ("paired", "matched"), "high", "{:.0f}"),
    ("v rel: method track-smoothed", ("method_smoothed", "relative_error"), "low", "{:.3f}"),
    ("d/dt track − v m/s: method", ("consistency", "method"), "low", "{:.4f}"),
    ("d/dt track − v: smoothed", ("consistency", "method_smoothed"), "low", "{:.4f}"),
    ("abs err vx/vy/vz m/s: method", ("method", "abs_v"), "low", None),
    ("abs err vx/vy/vz: raw", ("baseline_raw", "abs_v"), "low", None),
    ("abs err vx/vy/vz: smoothed", ("baseline_smoothed", "abs_v"), "low", None),
    ("precision", ("detection", "precision"), "high", "{:.3f}"),
    ("recall", ("detection", "recall"), "high", "{:.3f}"),
    ("recall, centre in both frames", ("detection", "recall_centred"), "high", "{:.3f}"),
    ("Chamfer mm", ("chamfer_mm",), "low", "{:.3f}"),
    ("Chamfer % r_eq", ("chamfer_pct_r_eq",), "low", "{:.0f}"),
    ("within 0.25 r_eq", ("near_share",), "high", "{:.3f}"),
    ("volume err %", ("volume_error_pct",), "low", "{:.0f}"),
    ("volume err %: reported", ("volume_reported", "error_pct"), "low", "{:.0f}"),
    ("of which cut", ("volume_reported", "cut_share"), "low", "{:.2f}"),
    ("bisector/across ÷ truth", ("extent_ratio_vs_truth",), "one", "{:.2f}"),
    ("held-out PSNR dB", ("psnr",), "high", "{:.2f}"),
    ("held-out SSIM", ("ssim",), "high", "{:.3f}"),
]


def _get(row: dict, path: tuple) -> float | tuple:
    if path[-1] == "abs_v":
        d = row.get(path[0]) or {}
        return tuple(d.get(f"abs_{k}", math.nan) for k in ("vx", "vy", "vz"))
    v = row
    for k in path:
        v = v.get(k, math.nan) if isinstance(v, dict) else math.nan
    return float(v) if v is not None else math.nan


def _fmt(v, fmt) -> str:
    if isinstance(v, tuple):
        return "/".join("–" if not np.isfinite(x) else f"{x:.3f}" for x in v)
    return "–" if not np.isfinite(v) else fmt.format(v)


def summary_rows(rows: Sequence[dict]) -> list[tuple[str, list]]:
    """``[(label, values)]``: each session, then ``mean`` and ``worst`` over sessions
    (NaNs skipped; worst = highest error, lowest score, farthest from 1 for the ratio)."""
    table = [(r["session"], [_get(r, c[1]) for c in COLUMNS]) for r in rows]
    mean, worst = [], []
    for k, (_, _, better, _) in enumerate(COLUMNS):
        vals = [t[1][k] for t in table]
        if isinstance(vals[0], tuple):
            arr = np.array(vals, dtype=np.float64)
            mean.append(tuple(nanmean(arr[:, i]) for i in range(3)))
            worst.append(tuple(_nanmax(arr[:, i]) for i in range(3)))
            continue
        arr = np.array(vals, dtype=np.float64)
        fin = arr[np.isfinite(arr)]
        mean.append(float(fin.mean()) if fin.size else math.nan)
        if not fin.size:
            worst.append(math.nan)
        elif better == "low":
            worst.append(float(fin.max()))
        elif better == "high":
            worst.append(float(fin.min()))
        else:
            worst.append(float(fin[np.argmax(np.abs(fin - 1))]))
    return [*table, ("mean", mean), ("worst", worst)]


def _nanmax(a) -> float:
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else math.nan


def format_table(rows: Sequence[dict]) -> str:
    """The markdown table of :func:`summary_rows`."""
    head = ["session", *(c[0] for c in COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, vals in summary_rows(rows):
        cells = [_fmt(v, c[3]) for v, c in zip(vals, COLUMNS, strict=True)]
        lines.append("| " + " | ".join([label, *cells]) + " |")
    return "\n".join(lines)


def choose_smoothing(
    raw: dict[str, tuple[pd.DataFrame, float]],
    truth: dict[str, pd.DataFrame],
    windows_s: Sequence[float] = SMOOTH_WINDOWS_S,
    orders: Sequence[int] = SMOOTH_ORDERS,
) -> tuple[tuple[float, int], pd.DataFrame]:
    """The (window s, order) of the baseline's track smoothing with the lowest mean
    relative velocity error over the sessions, and the whole grid
    (``window_s, order, mean_relative_error, worst_relative_error``).

    ``raw``: ``{session: (baseline table, fps)}``; ``truth``: ``{session: bubbles.csv}``.
    """
    return _best_on_grid(
        lambda w, o: [
            velocity_scores(smoothed_table(tab, fps, w, o), truth[s])["relative_error"]
            for s, (tab, fps) in raw.items()
        ],
        windows_s,
        orders,
    )


def _best_on_grid(errors, windows_s: Sequence[float], orders: Sequence[int]):
    """Evaluate ``errors(window_s, order)`` (per-session relative errors) on the grid;
    → ((best window, best order) by the mean, the grid as a DataFrame)."""
    grid = []
    for w in windows_s:
        for o in orders:
            errs = [e for e in errors(w, o) if np.isfinite(e)]
            grid.append(
                (w, o, float(np.mean(errs)) if errs else math.nan, max(errs, default=math.nan))
            )
    df = pd.DataFrame(
        grid, columns=["window_s", "order", "mean_relative_error", "worst_relative_error"]
    )
    fin = df[np.isfinite(df["mean_relative_error"])]
    if fin.empty:
        return (windows_s[0], orders[0]), df
    best = fin.loc[fin["mean_relative_error"].idxmin()]
    return (float(best["window_s"]), int(best["order"])), df


def grid_table(grid: pd.DataFrame) -> str:
    """Markdown table of :func:`choose_smoothing`'s grid."""
    lines = [
        "| window ms | order | mean v rel | worst v rel |",
        "| --- | --- | --- | --- |",
    ]
    for r in grid.itertuples():
        lines.append(
            f"| {r.window_s * 1e3:g} | {r.order} | {r.mean_relative_error:.4f} "
            f"| {r.worst_relative_error:.4f} |"
        )
    return "\n".join(lines)


# --- the workflow ---------------------------------------------------------------------


def bench_config(set_values: Sequence[str] = ()) -> dict:
    """The config ``surfphase new-campaign`` writes, with :data:`BENCH_CONFIG` and
    ``KEY.SUB=VALUE`` items (YAML values) on top."""
    from surfphase.commands.new_campaign import _config_text
    from surfphase.commands.run import project_root

    cfg = yaml.safe_load(_config_text(project_root() / "config" / "config.yaml"))
    for sec, vals in BENCH_CONFIG.items():
        cfg.setdefault(sec, {}).update(vals)
    for item in set_values:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects KEY.SUB=VALUE, not {item!r}")
        *path, last = key.split(".")
        node = cfg
        for k in path:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ValueError(f"--set {item}: {k} is not a section of the config")
        node[last] = yaml_value(value)
    return cfg


def yaml_value(text: str):
    """``text`` read as a YAML value, a number written with an exponent and no decimal
    point (``5e-5``, which YAML 1.1 reads as text) as that number."""
    value = yaml.safe_load(text)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def write_run_campaign(synth_dir: Path, run_dir: Path, config: dict) -> pd.DataFrame:
    """A campaign folder ``run_dir/config/`` (config, sheets, board) whose sheets point
    at the synthetic campaign's videos, calibration images and truth (absolute paths).
    Every session of the synthetic campaign is in the sheet (a run of some sessions, or
    a scoring with ``--skip-run``, leaves the others' results valid); returns the sheet."""
    synth_dir, run_dir = Path(synth_dir).resolve(), Path(run_dir).resolve()
    cdir = run_dir / "config"
    cdir.mkdir(parents=True, exist_ok=True)
    sheet = pd.read_csv(synth_dir / "sessions.tsv", sep="\t", dtype=str, keep_default_na=False)
    for col in ("cam0", "cam1", "gt"):
        sheet[col] = [str(synth_dir / p) for p in sheet[col]]
    rigs = pd.read_csv(synth_dir / "rigs.tsv", sep="\t", dtype=str, keep_default_na=False)
    rigs = rigs[rigs["rig"].isin(set(sheet["rig"]))].copy()
    for col in ("cam0", "cam1"):
        rigs[col] = [str(synth_dir / p) for p in rigs[col]]
    (cdir / "board.yaml").write_text((synth_dir / "board.yaml").read_text())
    sheet.to_csv(cdir / "sessions.tsv", sep="\t", index=False)
    rigs.to_csv(cdir / "rigs.tsv", sep="\t", index=False)
    cfg = dict(config)
    cfg["sessions"], cfg["rigs"], cfg["results"] = (
        "config/sessions.tsv",
        "config/rigs.tsv",
        "results",
    )
    (cdir / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return sheet


#: The sources the native baseline's frames and masks come from, as
#: :func:`~surfphase.io.code_fingerprint` parts (those of the workflow's ingest and mask
#: rules).
NATIVE_SOURCES = (
    "__init__.py", "cameras.py", "io.py", "ingest.py", "video.py", "labformats.py",
    "commands/ingest.py", "masks", "commands/mask.py",
)  # fmt: skip


def native_key(row: pd.Series, cameras_json: Path, mask_params: dict) -> dict:
    """What a session's cached native frames and masks (:func:`native_baseline`) were
    computed from: the sources' fingerprint, the calibration's SHA-256, the recordings
    and frame rate of the sheet's ``row``, and the mask settings."""
    cams = Path(cameras_json)
    return {
        "code": code_fingerprint(NATIVE_SOURCES),
        "cameras_sha256": hashlib.sha256(cams.read_bytes()).hexdigest(),
        "videos": {c: str(row[c]) for c in ("cam0", "cam1")},
        "fps": float(row["fps"]),
        "masks": json.loads(json.dumps(mask_params, sort_keys=True, default=str)),
    }


def native_baseline(
    session: str, row: pd.Series, cameras_json: Path, work: Path, mask_params: dict
) -> tuple[pd.DataFrame, float]:
    """The two-view centroid baseline from masks at the recordings' native resolution:
    ingest at scale 1 (undistorted, calibrated cameras), the mask stage, triangulation.
    Returns (baseline table, fps).

    The frames and masks are kept in ``work`` with ``inputs.json``, the
    :func:`native_key` they were made from, and reused only while it holds: a rescoring
    (``--skip-run``) after a change of the ingest or mask code, the calibration or the
    mask settings redoes them rather than scoring the old code's baseline."""
    from surfphase.cameras import load_cameras
    from surfphase.eval.stage import read_session
    from surfphase.ingest import ingest_session
    from surfphase.masks.stage import run_mask_stage

    ing, msk = work / "ingest", work / "masks"
    fps = float(row["fps"])
    key = native_key(row, cameras_json, mask_params)
    stamp = work / "inputs.json"
    if not stamp.is_file() or json.loads(stamp.read_text()) != key:
        # Frames and masks cached without a key, or from another code, calibration,
        # recording or setting: they would score another run's baseline. Redone.
        stamp.unlink(missing_ok=True)
        shutil.rmtree(ing, ignore_errors=True)
        shutil.rmtree(msk, ignore_errors=True)
    if not (ing / "meta.json").is_file():
        ingest_session(
            session,
            load_cameras(cameras_json),
            {"cam0": Path(row["cam0"]), "cam1": Path(row["cam1"])},
            fps,
            scale=1.0,
            out=ing,
        )
    if not (msk / "masks.json").is_file():
        run_mask_stage(ing, msk, mask_params)
    if not stamp.is_file():
        atomic_write_json(stamp, key)
    data = read_session(ing, msk)
    tab = bl.baseline_bubbles(data["cameras"], data["labels"], data["frames"], data["fps"])
    return tab, fps


def run_accuracy_bench(
    work: Path,
    campaign: Path | None = None,
    sessions: int | None = None,
    frames: int | None = None,
    seed: int = 0,
    cores: int = 2,
    set_values: Sequence[str] = (),
    skip_run: bool = False,
    samples: int = SAMPLES,
    log=print,
    preset: str = "bench",
) -> dict:
    """The whole benchmark (module docstring); ``preset``: the synth preset written when
    no ``campaign`` is given (``bench``, ``bench-mixed`` or ``bench-drawn``). Returns
    ``{"rows": [...], "table": str, "smoothing": {...}, "config": {...}, "timings":
    {...}}``; also written to ``work/accuracy.json`` and ``work/accuracy.md``."""
    work = Path(work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    timings = {}
    campaign = _bench_campaign(work, campaign, seed, sessions, frames, log, preset)
    timings["synth_s"] = round(time.perf_counter() - t0, 1)
    all_sessions = pd.read_csv(campaign / "sessions.tsv", sep="\t", dtype=str)["session"]
    names = list(all_sessions[: sessions or len(all_sessions)])
    cfg = bench_config(set_values)
    run_dir = work / "run"
    sheet = write_run_campaign(campaign, run_dir, cfg).set_index("session")
    t1 = time.perf_counter()
    if not skip_run:
        _run_sessions(run_dir, names, cores, log)
    timings["workflow_s"] = round(time.perf_counter() - t1, 1)
    t2 = time.perf_counter()
    res = run_dir / "results"
    truths = {s: pd.read_csv(Path(sheet.loc[s, "gt"]) / "bubbles.csv") for s in names}
    raw = _native_baselines(names, sheet, res, work, cfg, log)
    timings["baseline_s"] = round(time.perf_counter() - t2, 1)
    (window, order), grid = choose_smoothing(raw, truths)
    fits = {s: res / s / "fit" for s in names if (res / s / "fit" / "surfels.npz").is_file()}
    (m_window, m_order), m_grid = choose_method_smoothing(fits, truths)
    t3 = time.perf_counter()
    rows = [
        _session_row(s, sheet, res, raw, fits, truths, (window, order), (m_window, m_order),
                     samples)
        for s in names
    ]  # fmt: skip
    timings["metrics_s"] = round(time.perf_counter() - t3, 1)
    timings["total_s"] = round(time.perf_counter() - t0, 1)
    table = format_table(rows)
    notes = _notes((window, order), (m_window, m_order), set_values, cores)
    result = {
        "rows": rows,
        "table": table,
        "notes": notes,
        "smoothing": {"window_s": window, "order": order, "grid": grid.to_dict("records")},
        "method_smoothing": {
            "window_s": m_window,
            "order": m_order,
            "grid": m_grid.to_dict("records"),
        },
        "config": cfg,
        "campaign": str(campaign),
        "timings": timings,
    }
    (work / "accuracy.json").write_text(json.dumps(_finite(result), indent=1))
    md = [table, "", notes, "", "Baseline:", "", grid_table(grid), "", "Method:", "",
          grid_table(m_grid)]  # fmt: skip
    (work / "accuracy.md").write_text("\n".join(md) + "\n")
    return result


def _bench_campaign(
    work: Path, campaign, seed: int, sessions, frames, log, preset: str = "bench"
) -> Path:
    """The synthetic campaign: ``campaign``, or the ``preset`` (``bench``,
    ``bench-mixed``, ``bench-drawn``) written once into ``work/campaign``."""
    from surfphase.synth.campaign import write_campaign

    if campaign is None:
        campaign = work / "campaign"
        if not (campaign / "synth.json").is_file():
            log(f"writing the {preset} preset into {campaign}")
            write_campaign(campaign, preset=preset, seed=seed, sessions=sessions, frames=frames)
    campaign = Path(campaign).resolve()
    if not (campaign / "sessions.tsv").is_file():
        raise FileNotFoundError(f"{campaign}: not a synthetic campaign (no sessions.tsv)")
    return campaign


def _run_sessions(run_dir: Path, names: Sequence[str], cores: int, log) -> None:
    """The workflow through ``evaluate``, ``cores`` sessions at a time (one thread per
    job, the campaign default: one session per core), so that a run stopped early
    leaves whole sessions."""
    for i in range(0, len(names), max(1, cores)):
        group = list(names[i : i + max(1, cores)])
        cmd = [sys.executable, "-m", "surfphase", "run", "--campaign", str(run_dir)]
        cmd += ["--cores", str(cores), "--session", ",".join(group), "evaluate"]
        log("running: " + " ".join(cmd))
        rc = subprocess.call(cmd, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        if rc:
            log(f"sessions {', '.join(group)}: the workflow exited with {rc}; a session "
                "without its evaluation has no figures")  # fmt: skip


def _native_baselines(names, sheet: pd.DataFrame, res: Path, work: Path, cfg: dict, log) -> dict:
    """``{session: (native baseline table, fps)}`` of the sessions whose rig calibrated
    and whose baseline ran (the others are logged)."""
    raw = {}
    for s in names:
        cams = res / "calib" / sheet.loc[s, "rig"] / "cameras.json"
        if not cams.is_file():
            log(f"session {s}: no calibration ({cams}); no baseline")
            continue
        try:
            raw[s] = native_baseline(s, sheet.loc[s], cams, work / "native" / s, cfg["masks"])
        except (ValueError, FileNotFoundError) as e:
            log(f"session {s}: native baseline failed: {e}")
    return raw


def _session_row(s, sheet, res, raw, fits, truths, smoothing, method_smoothing, samples) -> dict:
    """One session's row: :func:`session_metrics`, the smoothed baseline and method
    velocities, the two scored on the bubble-frames both report, the tracks'
    consistency."""
    r = session_metrics(
        s,
        Path(sheet.loc[s, "gt"]),
        res / s / "fit",
        res / s / "mesh",
        res / s / "evaluate",
        raw[s][0] if s in raw else None,
        n=samples,
    )
    if s in raw:
        tab, fps = raw[s]
        smoothed = smoothed_table(tab, fps, *smoothing)
        r["baseline_smoothed"] = velocity_scores(smoothed, truths[s])
        if (res / s / "fit" / "bubbles.csv").is_file():
            pred = pd.read_csv(res / s / "fit" / "bubbles.csv")
            r["paired"] = paired_velocity_scores(pred, smoothed, truths[s])
    if s in fits:
        smooth = method_track_table(fits[s], *method_smoothing)
        r["method_smoothed"] = velocity_scores(smooth, truths[s])
        r["consistency"] = {
            "method": track_consistency(pd.read_csv(fits[s] / "bubbles.csv")),
            "method_smoothed": track_consistency(smooth),
        }
    return r


def _notes(smoothing, method_smoothing, set_values: Sequence[str], cores: int) -> str:
    """The table's notes: gate, smoothing chosen, config."""
    (window, order), (m_window, m_order) = smoothing, method_smoothing
    return (
        f"Gate: reported and true bubbles match when their centroids are within "
        f"{GATE_R_EQ:g} r_eq of the true bubble (Hungarian per frame). Baseline: a "
        f"bubble-frame whose triangulated centroid reprojects more than {bl.MAX_REPROJ_PX:g} "
        "px from its native mask centroid in a view is left out (off the epipolar "
        "geometry: a fragment, a merge the views see differently). Baseline smoothed: "
        f"Savitzky–Golay (deriv=1) over {window * 1e3:g} ms, order {order} (best of the "
        f"grid below on these sessions). Method track-smoothed: `fit: track_window_s: "
        f"{m_window:g}`, `track_order: {m_order}` (best of the same grid for the method; "
        "its other track settings the defaults), computed from the same fits' surfels. "
        "Config: `surfphase new-campaign` defaults + "
        f"{json.dumps(BENCH_CONFIG)}"
        + (f" + --set {' '.join(set_values)}" if set_values else "")
        + f"; {cores} cores."
    )


def _finite(obj):
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj
