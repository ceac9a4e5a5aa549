"""Per-session figures and the campaign page.

* :func:`velocity_series` — per bubble of the fit, its velocity over time from the
  method (fit ``bubbles.csv``), the two-view baseline (``baseline_bubbles.csv``, same
  mask ids) and, for synthetic sessions, the ground truth (``bubbles.csv`` of the truth,
  whose ids are its own: each fit bubble is paired with the true bubble nearest on
  average over their common frames);
* :func:`velocity_plots` — those series drawn, vx and vy against time, one row per bubble;
* :func:`copy_overlays` — a few mask overlays of the mask stage, for the report;
* :func:`copy_videos` — the novel-view videos (raw renders, refined), for the report;
* :func:`session_metrics_table` — one session's ``metrics.json`` as a two-column table;
* :func:`campaign_page` — one self-contained HTML page: the campaign table and each
  session's fits compared, figures, mesh snapshots and videos embedded as data.

Mesh snapshots: :mod:`surfphase.report.snapshots`; tables: :mod:`surfphase.report.tables`.

Units: metres, seconds, m/s; lab frame (+y up). Time is ``frame / fps`` for every source.
"""

from __future__ import annotations

import base64
import html
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.folders.fit import BUBBLE_COLUMNS, read_csv_table
from surfphase.io import atomic_path, atomic_write_text
from surfphase.report.tables import (
    SUMMARY_COLUMNS,  # noqa: F401 (re-exported: the campaign summary's columns)
    comparison_table,
    flatten,
    summary_table,
)

FIT_COLUMNS = BUBBLE_COLUMNS
GT_MAX_DIST = 1.5e-3  # metres: a fit bubble farther than this from every true one is unpaired


def read_bubbles(path: str | os.PathLike, what: str) -> pd.DataFrame:
    """A bubble table (``frame, bubble, x, y, z, vx, vy, vz``, m and m/s) from a CSV."""
    return read_csv_table(Path(path), FIT_COLUMNS, what)


def pair_truth(
    fit: pd.DataFrame, gt: pd.DataFrame, max_dist: float = GT_MAX_DIST
) -> dict[int, int]:
    """``{fit bubble: true bubble}``: for each fit bubble the true bubble whose centroid is
    nearest on average (metres) over the frames both have, if that mean is ≤ ``max_dist``.

    Only true bubbles present in at least half of the fit bubble's frames are candidates,
    so that a true bubble seen once near a long track does not win on a single frame.

    Args:
        fit, gt: bubble tables with ``frame, bubble, x, y, z`` (metres).
        max_dist: largest mean centroid distance of a pair, metres.
    """
    pairs = {}
    for b, fb in fit.groupby("bubble"):
        merged = fb.merge(gt, on="frame", suffixes=("", "_gt"))
        if merged.empty:
            continue
        d = np.sqrt(
            (merged["x"] - merged["x_gt"]) ** 2
            + (merged["y"] - merged["y_gt"]) ** 2
            + (merged["z"] - merged["z_gt"]) ** 2
        )
        by_gt = d.groupby(merged["bubble_gt"])
        mean = by_gt.mean()[by_gt.size() * 2 >= fb["frame"].nunique()]
        if len(mean) and mean.min() <= max_dist:
            pairs[int(b)] = int(mean.idxmin())
    return pairs


def velocity_series(
    fit: pd.DataFrame,
    baseline: pd.DataFrame | None,
    gt: pd.DataFrame | None,
    fps: float,
    include_nucleation: bool = False,
    max_dist: float = GT_MAX_DIST,
) -> dict[int, dict[str, pd.DataFrame]]:
    """Per fit bubble, ``{source: DataFrame(t_s, vx, vy, vz)}`` sorted by time.

    Sources: ``method`` (always), ``baseline`` (rows of ``baseline`` with the same bubble
    id, if any), ``truth`` (the paired true bubble, see :func:`pair_truth`, on the fit's
    frames only). Bubble 0, the nucleation region, is left out unless
    ``include_nucleation``. ``t_s = frame / fps`` (seconds).
    """
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if not include_nucleation:
        fit = fit[fit["bubble"] != 0]
    pairs = pair_truth(fit, gt, max_dist) if gt is not None else {}
    cols = ["t_s", "vx", "vy", "vz"]

    def series(df: pd.DataFrame) -> pd.DataFrame:
        out = df.assign(t_s=df["frame"] / fps).sort_values("t_s")
        return out[cols].reset_index(drop=True)

    result: dict[int, dict[str, pd.DataFrame]] = {}
    for b, fb in fit.groupby("bubble"):
        b = int(b)
        result[b] = {"method": series(fb)}
        if baseline is not None:
            bb = baseline[baseline["bubble"] == b]
            if not bb.empty:
                result[b]["baseline"] = series(bb)
        if b in pairs:
            gb = gt[(gt["bubble"] == pairs[b]) & gt["frame"].isin(fb["frame"])]
            result[b]["truth"] = series(gb)
    return result


STYLES = {
    "method": {"color": "tab:blue", "marker": "o", "ms": 3, "lw": 1.5},
    "baseline": {"color": "tab:orange", "marker": "s", "ms": 3, "lw": 1.0, "ls": "--"},
    "truth": {"color": "black", "marker": "x", "ms": 4, "lw": 1.0, "ls": ":"},
}


def velocity_plots(
    fit_bubbles_csv: str | os.PathLike,
    baseline_csv: str | os.PathLike | None,
    gt_bubbles_csv: str | os.PathLike | None,
    fps: float,
    out_png: str | os.PathLike,
    session: str = "",
    max_bubbles: int = 8,
    include_nucleation: bool = False,
) -> dict[int, dict[str, pd.DataFrame]]:
    """Draw vx and vy (m/s) over time (ms) per bubble: method, baseline, truth; write a PNG.

    One row per bubble (the ``max_bubbles`` bubbles with the most frames, by id), two
    columns (vx, vy). Returns the plotted series (:func:`velocity_series`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fit = read_bubbles(fit_bubbles_csv, f"session {session} fit bubbles".replace("  ", " "))
    baseline = read_bubbles(baseline_csv, "baseline bubbles") if baseline_csv else None
    gt = read_bubbles(gt_bubbles_csv, "ground-truth bubbles") if gt_bubbles_csv else None
    series = velocity_series(fit, baseline, gt, fps, include_nucleation)
    if not series:
        raise ValueError(f"{fit_bubbles_csv}: session {session}: no bubble to plot")
    longest = sorted(series, key=lambda b: -len(series[b]["method"]))[:max_bubbles]
    shown = sorted(longest)
    fig, axes = plt.subplots(
        len(shown), 2, figsize=(9, 2.2 * len(shown) + 0.6), squeeze=False, sharex=True
    )
    for row, b in enumerate(shown):
        for col, comp in enumerate(("vx", "vy")):
            ax = axes[row, col]
            for source, df in series[b].items():
                ax.plot(df["t_s"] * 1e3, df[comp], label=source, **STYLES[source])
            ax.set_ylabel(f"bubble {b}\n{comp} (m/s)")
            ax.grid(alpha=0.3)
    for col in range(2):
        axes[-1, col].set_xlabel("time (ms)")
    axes[0, 0].set_title("vx (horizontal)")
    axes[0, 1].set_title("vy (up)")
    handles = {}
    for ax in axes.ravel():
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    fig.legend(handles.values(), handles.keys(), loc="upper right", ncol=len(handles))
    fig.suptitle(f"{session} bubble velocities".strip(), x=0.02, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return {b: series[b] for b in shown}


def copy_overlays(
    masks_dir: str | os.PathLike, out_dir: str | os.PathLike, max_count: int = 4
) -> list[Path]:
    """Copy up to ``max_count`` PNGs of ``masks_dir/overlays`` (evenly spread, by name)
    into ``out_dir`` (created, emptied of PNGs first); returns the copies."""
    src = Path(masks_dir) / "overlays"
    if not src.is_dir():
        raise FileNotFoundError(f"{src}: no mask overlays")
    pngs = sorted(src.glob("*.png"))
    if len(pngs) > max_count:
        pick = np.unique(np.linspace(0, len(pngs) - 1, max_count).round().astype(int))
        pngs = [pngs[i] for i in pick]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("*.png"):
        old.unlink()
    copies = []
    for p in pngs:
        with atomic_path(out / p.name) as tmp:
            shutil.copyfile(p, tmp)
        copies.append(out / p.name)
    return copies


def copy_videos(
    views_dir: str | os.PathLike | None,
    refine_dir: str | os.PathLike | None,
    out_dir: str | os.PathLike,
) -> list[Path]:
    """Copy the novel-view videos into ``out_dir`` (created, emptied of MP4s first):
    ``views_dir/<v>.mp4`` (the raw renders of the fit) as ``<v>_raw.mp4`` and
    ``refine_dir/<v>.mp4`` (the refined ones) as ``<v>_refined.mp4``; returns the copies,
    raw and refined of each view next to each other."""
    found: list[tuple[Path, str]] = []
    for folder, kind in ((views_dir, "raw"), (refine_dir, "refined")):
        if folder is None:
            continue
        folder = Path(folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: no {kind} novel-view videos (folder not found)")
        mp4s = sorted(folder.glob("*.mp4"))
        if not mp4s:
            raise FileNotFoundError(f"{folder}: no {kind} novel-view videos (*.mp4)")
        found += [(p, f"{p.stem}_{kind}.mp4") for p in mp4s]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("*.mp4"):
        old.unlink()
    copies = []
    for src, name in sorted(found, key=lambda item: item[1]):
        with atomic_path(out / name) as tmp:
            shutil.copyfile(src, tmp)
        copies.append(out / name)
    return copies


def session_metrics_table(metrics: Mapping) -> pd.DataFrame:
    """A ``metrics.json`` dict as rows ``metric, value`` (nested keys joined by dots;
    lists and per-frame Chamfer values left out)."""
    flat = {k: v for k, v in flatten(metrics).items() if ".per_frame." not in k}
    return pd.DataFrame({"metric": list(flat), "value": list(flat.values())})


def _img_tag(png: Path, alt: str) -> str:
    data = base64.b64encode(png.read_bytes()).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _video_tag(mp4: Path, caption: str) -> str:
    data = base64.b64encode(mp4.read_bytes()).decode("ascii")
    return (
        f"<figure><video controls loop muted playsinline "
        f'src="data:video/mp4;base64,{data}"></video>'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


PAGE_STYLE = """
body { font-family: sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; font-size: 0.9em; margin-bottom: 1.5em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.3em; }
.overlays img { max-width: 30%; }
.meshes img { max-width: 48%; }
.videos { display: flex; flex-wrap: wrap; }
.videos figure { margin: 0.3em; text-align: center; font-size: 0.8em; }
.videos video { width: 192px; image-rendering: pixelated; border: 1px solid #ddd; }
details { margin-bottom: 1.5em; }
"""


def videos_page(
    videos: Sequence[str | os.PathLike], out_html: str | os.PathLike, title: str = ""
) -> int:
    """Write a self-contained HTML page with the novel-view videos (as written by
    :func:`copy_videos`: ``<v>_raw.mp4``, ``<v>_refined.mp4``) embedded, one row per view,
    raw beside refined; returns the number of views."""
    rows: dict[str, dict[str, Path]] = {}
    for p in map(Path, videos):
        view, _, kind = p.stem.rpartition("_")
        if kind not in ("raw", "refined") or not view:
            raise ValueError(f"{p}: expected <view>_raw.mp4 or <view>_refined.mp4")
        rows.setdefault(view, {})[kind] = p
    kinds = [k for k in ("raw", "refined") if any(k in r for r in rows.values())]
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{PAGE_STYLE}</style></head><body>",
        f"<h2>{html.escape(title)}</h2>" if title else "",
        "<table><tr><th>view</th>" + "".join(f"<th>{k}</th>" for k in kinds) + "</tr>",
    ]
    for view in sorted(rows):
        cells = [
            f"<td>{_video_tag(rows[view][k], f'{view} {k}')}</td>"
            if k in rows[view]
            else "<td></td>"
            for k in kinds
        ]
        parts.append(f"<tr><td>{html.escape(view)}</td>{''.join(cells)}</tr>")
    parts += ["</table>", "</body></html>"]
    atomic_write_text(out_html, "\n".join(parts) + "\n")
    return len(rows)


def _fmt(v) -> str:
    return f"{v:.4g}"


def _read_campaign_table(metrics_csv: Path) -> pd.DataFrame:
    """The campaign table (one row per session, ``session`` as text)."""
    if not metrics_csv.is_file():
        raise FileNotFoundError(f"{metrics_csv}: campaign metrics not found")
    try:
        table = pd.read_csv(metrics_csv)
    except (ValueError, pd.errors.ParserError) as e:
        raise ValueError(f"{metrics_csv}: not a readable CSV ({e})") from e
    if "session" not in table.columns:
        raise ValueError(f"{metrics_csv}: no 'session' column")
    table["session"] = table["session"].astype(str)
    return table


def _page_head(table: pd.DataFrame, summary: pd.DataFrame, title: str) -> list[str]:
    """The page's head, introduction, summary table and every metric (folded)."""
    full = table.set_index("session").T
    full.index.name = "metric"
    return [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{PAGE_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>{len(table)} sessions. Velocities in m/s (lab frame, +y up); relative errors "
        "are mean |v − v<sub>true</sub>| / mean |v<sub>true</sub>|. Held-out metrics: "
        "mean over the held-out cameras, over the full frame and inside the bubble region "
        "(the projected true bubbles), where the full frame is dominated by the heated "
        "plate and backlight that the fit does not reconstruct. Ablations are stage-1 "
        "fits: compare them with stage 1.</p>",
        "<h2>Summary</h2>",
        summary.to_html(index=False, float_format=_fmt, na_rep="–"),
        "<details><summary>All metrics</summary>",
        full.to_html(float_format=_fmt, na_rep="–"),
        "</details>",
    ]


def _prior_section(prior_samples: str | os.PathLike | None) -> list[str]:
    """The video prior's sample grid, or nothing."""
    if prior_samples is None:
        return []
    prior_samples = Path(prior_samples)
    if not prior_samples.is_file():
        raise FileNotFoundError(f"{prior_samples}: prior sample grid not found")
    return [
        "<h2>Video prior</h2>",
        "<p>Training clips above the black band; below it, videos the prior generated "
        "from pure noise (frames left to right).</p>",
        _img_tag(prior_samples, "video prior samples"),
    ]


def _session_section(row: pd.Series, media: Mapping[str, Mapping]) -> list[str]:
    """One session's heading, comparison of its fits, figures, meshes, videos, overlays."""
    session = row["session"]
    files = {k: [Path(p) for p in v.get(session, ())] for k, v in media.items()}
    for p in (p for group in files.values() for p in group):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: session {session}: figure not found")
    anchor = html.escape(session)
    parts = [f'<h2 id="{anchor}">{anchor}</h2>']
    comparison = comparison_table(row.to_dict())
    if len(comparison.columns) > 1 and len(comparison):
        parts.append(comparison.to_html(index=False, float_format=_fmt, na_rep="–"))
    parts += [_img_tag(p, f"{session} {p.stem}") for p in files["figures"]]
    if files["meshes"]:
        parts.append("<h3>Meshes coloured by speed</h3>")
        parts.append('<div class="meshes">')
        parts += [_img_tag(p, f"{session} mesh {p.stem}") for p in files["meshes"]]
        parts.append("</div>")
    if files["videos"]:
        parts.append("<h3>Novel views</h3>")
        parts.append('<div class="videos">')
        parts += [_video_tag(p, p.stem.replace("_", " ")) for p in files["videos"]]
        parts.append("</div>")
    if files["overlays"]:
        parts.append("<h3>Mask overlays</h3>")
        parts.append('<div class="overlays">')
        parts += [_img_tag(p, f"{session} mask overlay {p.stem}") for p in files["overlays"]]
        parts.append("</div>")
    return parts


def campaign_page(
    metrics_csv: str | os.PathLike,
    out_html: str | os.PathLike,
    figures: Mapping[str, Sequence[str | os.PathLike]] | None = None,
    overlays: Mapping[str, Sequence[str | os.PathLike]] | None = None,
    title: str = "SurfPhase campaign",
    meshes: Mapping[str, Sequence[str | os.PathLike]] | None = None,
    videos: Mapping[str, Sequence[str | os.PathLike]] | None = None,
    prior_samples: str | os.PathLike | None = None,
) -> pd.DataFrame:
    """Write one self-contained HTML page of the campaign; returns its summary table.

    The page holds the summary table (:func:`surfphase.report.tables.summary_table`),
    the full table transposed (one row per metric, one column per session), and per
    session the comparison of its fits (method, stage 1, baseline, ablations; full frame
    and bubble region: :func:`surfphase.report.tables.comparison_table`), its
    ``figures``, mesh snapshots, novel-view videos and mask ``overlays`` (embedded as
    base64 data, so the page needs no other file).

    Args:
        metrics_csv: the campaign table (``surfphase campaign-table``), one row per session.
        out_html: the page to write.
        figures: ``{session: [png, ...]}`` shown full width (velocity plots); sessions
            absent from the CSV are an error (for every mapping here).
        overlays: ``{session: [png, ...]}`` shown three to a row (mask overlays).
        meshes: ``{session: [png, ...]}`` shown two to a row (mesh snapshots).
        videos: ``{session: [mp4, ...]}`` (novel-view videos; the file name is the caption).
        prior_samples: the video prior's sample grid (``train-prior``'s ``samples.png``:
            training clips above the black band, videos generated from noise below).
    """
    metrics_csv = Path(metrics_csv)
    table = _read_campaign_table(metrics_csv)
    media = {
        "figures": dict(figures or {}),
        "overlays": dict(overlays or {}),
        "meshes": dict(meshes or {}),
        "videos": dict(videos or {}),
    }
    unknown = sorted(set().union(*map(set, media.values())) - set(table["session"]))
    if unknown:
        raise ValueError(f"{metrics_csv}: figures given for sessions not in the table: {unknown}")
    summary = summary_table(table)
    parts = _page_head(table, summary, title) + _prior_section(prior_samples)
    for _, row in table.iterrows():
        parts += _session_section(row, media)
    parts.append("</body></html>")
    atomic_write_text(out_html, "\n".join(parts) + "\n")
    return summary
