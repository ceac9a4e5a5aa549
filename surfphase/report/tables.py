"""Metrics tables of the report: each session's fits side by side, and the campaign
summary.

Both read the flattened metrics (``velocity.method.relative_error`` …: a row of the
campaign table, or one ``metrics.json`` flattened with :func:`flatten`), so the same
code serves the per-session page and the campaign page.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping

import pandas as pd

#: Columns of the comparison table: heading → (group, key); the key is looked up under
#: each row's prefix for the group (see :func:`comparison_table`).
COMPARISON_COLUMNS = {
    "velocity rel. error": ("velocity", "relative_error"),
    "velocity mean abs. error m/s": ("velocity", "mean_abs_error_mps"),
    "matched bubble-frames": ("velocity", "matched"),
    "vy rel. error vs 2D ref.": ("reference2d", "relative_error_y"),
    "held-out PSNR dB": ("heldout", "psnr"),
    "held-out SSIM": ("heldout", "ssim"),
    "held-out L1": ("heldout", "l1"),
    "bubble-region PSNR dB": ("region", "psnr"),
    "bubble-region SSIM": ("region", "ssim"),
    "bubble-region L1": ("region", "l1"),
    "held-out PSNR dB, whole image predicted": ("whole", "psnr"),
    "held-out SSIM, whole image predicted": ("whole", "ssim"),
    "Chamfer mm": ("chamfer", "mean_mm"),
}


def flatten(obj: Mapping, prefix: str = "") -> dict:
    """Nested dicts → ``{"a.b.c": value}``; lists are left out."""
    out = {}
    for k, v in obj.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        elif not isinstance(v, list):
            out[key] = v
    return out


def _sources(flat: Mapping) -> dict[str, dict[str, str]]:
    """Row label → ``{group: key prefix}`` for every fit present in ``flat``."""
    rows = {
        "method (final fit)": {
            "velocity": "velocity.method.",
            "reference2d": "reference2d.method.",
            "heldout": "heldout.mean.",
            "region": "heldout.mean.region.",
            "whole": "heldout_whole.mean.",
            "chamfer": "chamfer_mm.",
        },
        "stage 1 (no refinement)": {
            "velocity": "stage1.velocity.",
            "reference2d": "stage1.reference2d.",
            "heldout": "stage1.heldout.mean.",
            "region": "stage1.heldout.mean.region.",
            "whole": "stage1.heldout_whole.mean.",
            "chamfer": "stage1.chamfer_mm.",
        },
        "baseline (two-view triangulation)": {
            "velocity": "velocity.baseline.",
            "reference2d": "reference2d.baseline.",
        },
    }
    names = sorted({m.group(1) for k in flat if (m := re.match(r"ablations\.([^.]+)\.", k))})
    for a in names:
        p = f"ablations.{a}."
        rows[f"ablation {a} (stage 1)"] = {
            "velocity": p + "velocity.",
            "reference2d": p + "reference2d.",
            "heldout": p + "heldout.mean.",
            "region": p + "heldout.mean.region.",
            "whole": p + "heldout_whole.mean.",
            "chamfer": p + "chamfer_mm.",
        }
    return rows


def _present(value) -> bool:
    if value is None:
        return False
    try:
        return not math.isnan(float(value))
    except (TypeError, ValueError):
        return True


def comparison_table(flat: Mapping) -> pd.DataFrame:
    """One row per fit of a session — the method (final fit), stage 1, the two-view
    baseline, each ablation — and one column per :data:`COMPARISON_COLUMNS` metric;
    rows with no value at all (a fit that was not scored) and columns empty in every
    row are left out. Missing values are NaN."""
    rows = []
    for label, groups in _sources(flat).items():
        row = {"fit": label}
        for heading, (group, key) in COMPARISON_COLUMNS.items():
            prefix = groups.get(group)
            value = flat.get(prefix + key) if prefix else None
            row[heading] = value if _present(value) else float("nan")
        if any(_present(row[h]) for h in COMPARISON_COLUMNS):
            rows.append(row)
    table = pd.DataFrame(rows, columns=["fit", *COMPARISON_COLUMNS])
    keep = ["fit"] + [h for h in COMPARISON_COLUMNS if table[h].map(_present).any()]
    return table[keep]


#: Fixed columns of the campaign summary, in order, with their headings; stage-1 and
#: ablation columns are added after the method's (see :func:`summary_table`).
SUMMARY_COLUMNS = {
    "session": "session",
    # Only in a campaign table written after a run in which sessions failed
    # (`surfphase run`): finished / failed, and why it failed.
    "status": "status",
    "error": "error",
    "velocity.method.relative_error": "velocity rel. error (method)",
    "velocity.baseline.relative_error": "velocity rel. error (baseline)",
    "stage1.velocity.relative_error": "velocity rel. error (stage 1)",
    "velocity.method.mean_abs_error_mps": "velocity mean abs. error m/s (method)",
    "velocity.baseline.mean_abs_error_mps": "velocity mean abs. error m/s (baseline)",
    "reference2d.method.relative_error_y": "vy rel. error vs 2D ref. (method)",
    "reference2d.baseline.relative_error_y": "vy rel. error vs 2D ref. (baseline)",
    "heldout.mean.psnr": "held-out PSNR dB",
    "heldout.mean.ssim": "held-out SSIM",
    "heldout.mean.l1": "held-out L1",
    "heldout.mean.region.psnr": "bubble-region PSNR dB",
    "heldout.mean.region.ssim": "bubble-region SSIM",
    "stage1.heldout.mean.psnr": "held-out PSNR dB (stage 1)",
    "stage1.heldout.mean.region.psnr": "bubble-region PSNR dB (stage 1)",
    "heldout_whole.mean.psnr": "held-out PSNR dB, whole image predicted",
    "heldout_whole.mean.ssim": "held-out SSIM, whole image predicted",
    "chamfer_mm.mean_mm": "Chamfer mm",
    "stage1.chamfer_mm.mean_mm": "Chamfer mm (stage 1)",
    "chamfer_mm.whole_truth_mean_mm": "Chamfer mm against the whole truth",
    "frames": "frames",
}


def summary_table(table: pd.DataFrame) -> pd.DataFrame:
    """The campaign summary: :data:`SUMMARY_COLUMNS` present in ``table`` (the campaign
    metrics, one row per session), with each ablation's velocity relative error and
    held-out PSNR (full frame and region) inserted before the Chamfer column."""
    cols = dict((c, h) for c, h in SUMMARY_COLUMNS.items() if c in table.columns)
    names = sorted(
        {m.group(1) for c in table.columns if (m := re.match(r"ablations\.([^.]+)\.", c))}
    )
    extra = {}
    for a in names:
        for key, what in (
            ("velocity.relative_error", "velocity rel. error"),
            ("heldout.mean.psnr", "held-out PSNR dB"),
            ("heldout.mean.region.psnr", "bubble-region PSNR dB"),
            ("chamfer_mm.mean_mm", "Chamfer mm"),
        ):
            c = f"ablations.{a}.{key}"
            if c in table.columns:
                extra[c] = f"{what} ({a})"
    order = list(cols)
    at = order.index("chamfer_mm.mean_mm") if "chamfer_mm.mean_mm" in order else len(order)
    order[at:at] = list(extra)
    headings = {**cols, **extra}
    return table[order].rename(columns=headings)
