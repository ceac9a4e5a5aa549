"""``surfphase bench velocity-limits``: where the method's velocity loses to the smoothed
baseline on a run of ``surfphase bench accuracy``, is it the smoothing or the centres?

Both the method and the classical baseline triangulate silhouette centres and smooth
them along each track; they differ in the centres (the method's are sub-pixel, from the
mask stage's anchors; the baseline's the native masks' binary centroids) and in the
smoothing (the method's fixed in ``fit:``; the baseline's the best of a grid over the
draw, an oracle choice). Per session of each bench work folder, from its existing
results (nothing is run again):

* ``bar``: the smoothed baseline's relative velocity error, at the draw's chosen
  smoothing (the bar of ``accuracy.md``), and ``method``: the method's (``bubbles.csv``);
* ``method_best``: the least error of the method's tracks over the grid of
  :data:`~surfphase.bench.accuracy.SMOOTH_WINDOWS_S` × :data:`~surfphase.bench.accuracy.SMOOTH_ORDERS`
  for the first moving polynomial (``fit: track_window_s``, ``track_order``), its other
  track rules the defaults, chosen per session with the truth: an oracle no fixed setting
  can beat on that session; ``plain_best``: the same with plain Savitzky–Golay smoothing
  of the same centres (no end, blend, outlier or weighting rule); ``baseline_best``: the
  baseline's own least error over the grid on that session;
* the centres' own errors against the true centres on the bubble-frames both match
  (:func:`centre_noise`): rms, and rms of the frame-to-frame change of the error (the
  jitter that a velocity differentiates), µm;
* ``paired``: the method and the bar on the true bubble-frames both match (the "both
  report" columns of ``accuracy.md``); each other error is over the bubble-frames its
  own table matches (``matched``: the baseline leaves out centres its views disagree
  on, the method reports them), as in its "v rel" columns;
* ``method_only``: the bubble-frames whose velocity the method reports and the bar
  does not (both matched to the truth), their count, how many of them the image border
  cuts or another bubble hides in a view (``anchors.csv``'s ``visible`` under 1) and
  the range of that share, and their mean |error| (m/s) beside the mean over the
  bubble-frames both report;
* ``min_visible``: the method's error, and the bubble-frames it gives a velocity, at
  each ``fit: track_min_visible`` of :data:`MIN_VISIBLE_GRID` (a centre with less of
  its silhouette inside a view gets none), the other track settings the defaults;
* ``limit`` where the method loses (``method`` > ``bar``): ``frames`` when it wins on
  the bubble-frames both report (the loss is on bubble-frames the baseline leaves
  out); else ``smoothing`` when some smoothing of its centres on the grid would reach
  the bar, over its own bubble-frames or those both report (its track rules or plain
  Savitzky–Golay); else ``centres``: no choice of window and order does.

Over all the sessions given, :func:`fixed_sweep` counts the wins and the mean error of
every fixed setting of the grid (the method's rules, and plain Savitzky–Golay): how far
one setting for all sessions gets; :func:`visible_sweep` the same for each
``track_min_visible``.

Matching and errors: :mod:`surfphase.bench.accuracy_metrics` (gate 0.5 r_eq).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from surfphase.bench import accuracy as acc
from surfphase.bench.accuracy_metrics import (
    GATE_R_EQ,
    XYZ,
    known_velocity_matches,
    paired_velocity_scores,
    velocity_scores,
)
from surfphase.eval import velocity

#: ``fit: track_min_visible`` values scored (:func:`session_limits`' ``min_visible``):
#: 0 gives every centre a velocity; 1 none to a bubble the border cuts or another hides.
MIN_VISIBLE_GRID = (0.0, 0.25, 0.4, 0.5, 0.6, 0.75, 1.0)

#: The track rules off (:func:`surfphase.fit.outputs.track_rules`' order: end window,
#: end t, blend window, blend order, outlier k, reproj px): plain Savitzky–Golay.
PLAIN_RULES = (0.0, 0.0, 0.0, 2, 0.0, 0.0)


def centre_errors(
    pred: pd.DataFrame, truth: pd.DataFrame, gate_r_eq: float = GATE_R_EQ
) -> pd.DataFrame:
    """Per reported bubble-frame (ids ≥ 1) matched to a true bubble within ``gate_r_eq``
    (:func:`surfphase.eval.velocity.match_bubbles_relative`): ``frame, gt_bubble,
    gt_r_eq, ex, ey, ez``, the reported centre minus the true one (m)."""
    m = velocity.match_bubbles_relative(pred[pred["bubble"] >= 1], truth, gate_r_eq)
    m = m[["frame", "bubble", "gt_bubble", "gt_r_eq"]].merge(
        pred[["frame", "bubble", *XYZ]], on=["frame", "bubble"]
    )
    t = truth[["frame", "bubble", *XYZ]].rename(
        columns={"bubble": "gt_bubble", **{a: f"t{a}" for a in XYZ}}
    )
    m = m.merge(t, on=["frame", "gt_bubble"])
    for a in XYZ:
        m[f"e{a}"] = m[a] - m[f"t{a}"]
    return m[["frame", "gt_bubble", "gt_r_eq", "ex", "ey", "ez"]]


def centre_noise(errors: pd.DataFrame) -> tuple[float, float]:
    """``(rms, jitter)`` (m) of centre errors (:func:`centre_errors`' columns): the rms
    3D error, and the rms 3D change of the error between consecutive frames of one true
    bubble (what a velocity differentiates; a constant offset has none). NaN where
    nothing counts."""
    e = errors[["ex", "ey", "ez"]].to_numpy(np.float64)
    steps = []
    for _, g in errors.sort_values(["gt_bubble", "frame"]).groupby("gt_bubble"):
        f = g["frame"].to_numpy()
        d = np.diff(g[["ex", "ey", "ez"]].to_numpy(np.float64), axis=0)
        steps.append(d[np.diff(f) == 1])
    d = np.concatenate(steps) if steps else np.zeros((0, 3))
    rms = float(np.sqrt((e**2).sum(axis=1).mean())) if len(e) else math.nan
    jitter = float(np.sqrt((d**2).sum(axis=1).mean())) if len(d) else math.nan
    return rms, jitter


def _grid_errors(
    table: Callable[[float, int], pd.DataFrame], truth: pd.DataFrame, bar: pd.DataFrame | None
) -> tuple[dict, dict]:
    """On the grid, ``{(window_s, order): relative error}`` of ``table(window_s, order)``
    over its own matched bubble-frames, and ``{(window_s, order): (error, bar's error)}``
    on the true bubble-frames that it and ``bar`` both match
    (:func:`~surfphase.bench.accuracy_metrics.paired_velocity_scores`; empty when
    ``bar`` is None)."""
    own, paired = {}, {}
    for w in acc.SMOOTH_WINDOWS_S:
        for o in acc.SMOOTH_ORDERS:
            t = table(w, o)
            own[(w, o)] = velocity_scores(t, truth)["relative_error"]
            if bar is not None:
                p = paired_velocity_scores(t, bar, truth)
                paired[(w, o)] = (p["method"], p["baseline"])
    return own, paired


def method_only(
    pred: pd.DataFrame, bar: pd.DataFrame, truth: pd.DataFrame, anchors: pd.DataFrame | None
) -> dict:
    """The true bubble-frames that ``pred`` (ids ≥ 1) matches with a known velocity and
    ``bar`` does not: ``n``; ``partial``, how many of them have ``anchors``' ``visible``
    share under 1 (cut by the border or hidden in a view; NaN without anchors) and its
    ``visible_min``/``visible_max`` over them; ``mean_abs_mps`` their mean |velocity
    error| and ``both_mean_abs_mps`` that over the bubble-frames both match (m/s)."""
    keys = ["frame", "gt_bubble"]
    mine, theirs = (known_velocity_matches(t, truth) for t in (pred, bar))
    both = mine.merge(theirs[keys], on=keys, how="left", indicator=True)["_merge"] == "both"
    only = mine[~both.to_numpy()]
    out = {
        "n": int(len(only)),
        "mean_abs_mps": float(only["abs_error_mps"].mean()) if len(only) else math.nan,
        "both_mean_abs_mps": float(mine[both.to_numpy()]["abs_error_mps"].mean())
        if both.any()
        else math.nan,
        "partial": math.nan,
        "visible_min": math.nan,
        "visible_max": math.nan,
    }
    if anchors is not None and "visible" in anchors.columns and len(only):
        vis = (
            only[["frame", "bubble"]]
            .merge(anchors[["frame", "bubble", "visible"]], on=["frame", "bubble"], how="left")[
                "visible"
            ]
            .to_numpy(np.float64)
        )
        part = vis[vis < 1]
        out["partial"] = int(len(part))
        if len(part):
            out["visible_min"], out["visible_max"] = float(part.min()), float(part.max())
    return out


def _best(grid: dict) -> tuple[float, tuple[float, int] | None]:
    """The least finite error of a grid and its (window_s, order)."""
    fin = [(e, k) for k, e in grid.items() if np.isfinite(e)]
    return min(fin) if fin else (math.nan, None)


def session_limits(
    fit_dir: Path, base: pd.DataFrame, fps: float, truth: pd.DataFrame, bar_smoothing
) -> dict:
    """One session's figures (module docstring). ``base``: its native baseline table
    (:func:`surfphase.eval.baseline.baseline_bubbles`); ``bar_smoothing``: the draw's
    ``(window_s, order)`` for the baseline."""
    from surfphase.fit.outputs import track_rules
    from surfphase.fit.stage import DEFAULTS

    inputs = acc.method_track_inputs(fit_dir)
    rules = track_rules(DEFAULTS)
    bar_table = acc.smoothed_table(base, fps, *bar_smoothing)
    bar_scores = velocity_scores(bar_table, truth)
    landed = pd.read_csv(Path(fit_dir) / "bubbles.csv")
    scores = velocity_scores(landed, truth)
    bar, method = bar_scores["relative_error"], scores["relative_error"]
    same = paired_velocity_scores(landed, bar_table, truth)
    tables = {
        "method": lambda w, o: acc.method_track_table(inputs, w, o, None, rules),
        "plain": lambda w, o: acc.method_track_table(inputs, w, o, None, PLAIN_RULES),
        "baseline": lambda w, o: acc.smoothed_table(base, fps, w, o),
    }
    grids, paired = {}, {}
    for name, table in tables.items():
        # The baseline's own grid needs no pairing with itself.
        paired_with = None if name == "baseline" else bar_table
        grids[name], paired[name] = _grid_errors(table, truth, paired_with)
    default = (float(DEFAULTS["track_window_s"]), int(DEFAULTS["track_order"]))
    visible = []
    for v in MIN_VISIBLE_GRID:
        t = acc.method_track_table(inputs, *default, None, rules, v)
        n_v = int(np.isfinite(t.loc[t["bubble"] >= 1, "vx"].to_numpy(np.float64)).sum())
        visible.append([v, velocity_scores(t, truth)["relative_error"], n_v])
    raw = acc.method_track_table(inputs, 0.0, 1, None, PLAIN_RULES)
    em, eb = centre_errors(raw, truth), centre_errors(base, truth)
    both = em.merge(eb, on=["frame", "gt_bubble", "gt_r_eq"], suffixes=("", "_b"))
    m_rms, m_jit = centre_noise(both)
    b_rms, b_jit = centre_noise(
        both[["frame", "gt_bubble", "ex_b", "ey_b", "ez_b"]].set_axis(
            ["frame", "gt_bubble", "ex", "ey", "ez"], axis=1
        )
    )
    out = {"fps": fps, "bar": bar, "method": method}
    out["matched"] = {"method": int(scores["matched"]), "bar": int(bar_scores["matched"])}
    for name, grid in grids.items():
        e, k = _best(grid)
        out[f"{name}_best"], out[f"{name}_best_setting"] = e, k
    out["paired"] = {"n": same["matched"], "method": same["method"], "bar": same["baseline"]}
    reach = np.nanmin([out["method_best"], out["plain_best"], np.inf]) <= bar or any(
        m <= b for name in ("method", "plain") for m, b in paired[name].values()
    )
    if method <= bar:
        out["limit"] = ""
    elif same["method"] <= same["baseline"]:
        out["limit"] = "frames"
    else:
        out["limit"] = "smoothing" if reach else "centres"
    out["centres"] = {
        "n": int(len(both)),
        "r_eq_um": 1e6 * float(both["gt_r_eq"].mean()) if len(both) else math.nan,
        "rms_um": {"method": 1e6 * m_rms, "baseline": 1e6 * b_rms},
        "jitter_um": {"method": 1e6 * m_jit, "baseline": 1e6 * b_jit},
    }
    out["grids"] = {name: [[w, o, e] for (w, o), e in grid.items()] for name, grid in grids.items()}
    out["method_only"] = method_only(landed, bar_table, truth, inputs[1])
    out["min_visible"] = visible
    return out


def draw_limits(work: Path, log=print) -> dict[str, dict]:
    """:func:`session_limits` for every scored session of a ``bench accuracy`` work
    folder (its ``accuracy.json``, run campaign and native baseline cache)."""
    work = Path(work).resolve()
    result = work / "accuracy.json"
    if not result.is_file():
        raise FileNotFoundError(f"{work}: no accuracy.json (run `surfphase bench accuracy` first)")
    res = json.loads(result.read_text())
    sheet = pd.read_csv(
        work / "run" / "config" / "sessions.tsv", sep="\t", dtype=str, keep_default_na=False
    ).set_index("session")
    names = [r["session"] for r in res["rows"]]
    results = work / "run" / "results"
    raw = acc._native_baselines(names, sheet, results, work, res["config"], log)
    bar = (float(res["smoothing"]["window_s"]), int(res["smoothing"]["order"]))
    out = {}
    for s in names:
        fit = results / s / "fit"
        if s not in raw or not (fit / "bubbles.csv").is_file():
            log(f"{work.name} {s}: no fit or no baseline; left out")
            continue
        truth = pd.read_csv(Path(sheet.loc[s, "gt"]) / "bubbles.csv")
        out[s] = session_limits(fit, raw[s][0], raw[s][1], truth, bar)
    return out


def fixed_sweep(draws: dict[str, dict[str, dict]]) -> pd.DataFrame:
    """Every fixed setting of the grid over all sessions: ``family`` (``method``: the
    method's track rules; ``plain``: Savitzky–Golay), ``window_s``, ``order``, ``wins``
    (sessions whose error is at most their ``bar``), ``sessions``, ``mean``, ``worst``."""
    rows = []
    for family in ("method", "plain"):
        acc_rows: dict[tuple, list] = {}
        for sessions in draws.values():
            for r in sessions.values():
                for w, o, e in r["grids"][family]:
                    acc_rows.setdefault((w, o), []).append((e, r["bar"]))
        for (w, o), pairs in acc_rows.items():
            e = np.array([p[0] for p in pairs], np.float64)
            b = np.array([p[1] for p in pairs], np.float64)
            rows.append(
                [family, w, o, int((e <= b).sum()), len(e), float(np.nanmean(e)),
                 float(np.nanmax(e))]
            )  # fmt: skip
    return pd.DataFrame(
        rows, columns=["family", "window_s", "order", "wins", "sessions", "mean", "worst"]
    )


def visible_sweep(draws: dict[str, dict[str, dict]]) -> pd.DataFrame:
    """Each ``track_min_visible`` of :data:`MIN_VISIBLE_GRID` over all sessions:
    ``min_visible``, ``wins`` (sessions whose error is at most their ``bar``),
    ``sessions``, ``mean``, ``worst``, ``velocities`` (bubble-frames given one)."""
    acc_rows: dict[float, list] = {}
    for sessions in draws.values():
        for r in sessions.values():
            for v, e, n in r.get("min_visible", []):
                acc_rows.setdefault(v, []).append((e, r["bar"], n))
    rows = []
    for v, trip in sorted(acc_rows.items()):
        e = np.array([t[0] for t in trip], np.float64)
        b = np.array([t[1] for t in trip], np.float64)
        rows.append(
            [v, int((e <= b).sum()), len(e), float(np.nanmean(e)), float(np.nanmax(e)),
             int(sum(t[2] for t in trip))]
        )  # fmt: skip
    return pd.DataFrame(
        rows, columns=["min_visible", "wins", "sessions", "mean", "worst", "velocities"]
    )


def _setting(k) -> str:
    return "" if k is None else f"{1e3 * k[0]:g} ms, {k[1]}"


def format_limits(
    draws: dict[str, dict[str, dict]],
    sweep: pd.DataFrame,
    top: int = 3,
    visible: pd.DataFrame | None = None,
) -> str:
    """Markdown: one row per session the method loses, the counts, the sweep's best
    fixed settings of each family and, given, the ``track_min_visible`` sweep."""
    cols = [
        "draw", "session", "fps", "bar: baseline smoothed", "method",
        "both report: method / bar (n)", "method, best of grid (setting)",
        "plain SG, best of grid (setting)", "baseline, best of grid (setting)",
        "bubble-frames: method / baseline", "centre rms µm: method / baseline",
        "centre jitter µm: method / baseline",
        "method only: bubble-frames (in part outside or hidden; visible), mean err m/s "
        "(both report)",
        "limit",
    ]  # fmt: skip
    lines = ["| " + " | ".join(cols) + " |", "| " + " | ".join(["---"] * len(cols)) + " |"]
    counts = dict.fromkeys(("sessions", "wins", "frames", "smoothing", "centres"), 0)
    for draw, sessions in draws.items():
        for s, r in sessions.items():
            counts["sessions"] += 1
            if not r["limit"]:
                counts["wins"] += 1
                continue
            counts[r["limit"]] += 1
            c, p = r["centres"], r["paired"]
            cells = [
                draw, s, f"{r['fps']:.0f}", f"{r['bar']:.4f}", f"{r['method']:.4f}",
                f"{p['method']:.4f} / {p['bar']:.4f} ({p['n']})",
                f"{r['method_best']:.4f} ({_setting(r['method_best_setting'])})",
                f"{r['plain_best']:.4f} ({_setting(r['plain_best_setting'])})",
                f"{r['baseline_best']:.4f} ({_setting(r['baseline_best_setting'])})",
                f"{r['matched']['method']} / {r['matched']['bar']}",
                f"{c['rms_um']['method']:.1f} / {c['rms_um']['baseline']:.1f}",
                f"{c['jitter_um']['method']:.1f} / {c['jitter_um']['baseline']:.1f}",
                _only(r.get("method_only")),
                r["limit"],
            ]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        f"{counts['sessions']} sessions: the method at most the bar on {counts['wins']}; of "
        f"the others, {counts['frames']} where it wins on the bubble-frames both report, "
        f"{counts['smoothing']} where a smoothing of its centres chosen per session with "
        f"the truth would reach the bar, {counts['centres']} where none on the grid does.",
        "",
        "| fixed setting (all sessions) | window ms | order | wins | mean | worst |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for family, g in sweep.groupby("family", sort=False):
        for _, r in g.sort_values(["wins", "mean"], ascending=[False, True]).head(top).iterrows():
            lines.append(
                f"| {family} | {1e3 * r['window_s']:g} | {r['order']} | "
                f"{r['wins']} / {r['sessions']} | {r['mean']:.4f} | {r['worst']:.4f} |"
            )
    if visible is not None and len(visible):
        lines += [
            "",
            "| fit: track_min_visible (all sessions) | wins | mean | worst "
            "| bubble-frames with a velocity |",
            "| --- | --- | --- | --- | --- |",
        ]
        for r in visible.to_dict("records"):
            lines.append(
                f"| {r['min_visible']:g} | {int(r['wins'])} / {int(r['sessions'])} | "
                f"{r['mean']:.4f} | {r['worst']:.4f} | {int(r['velocities'])} |"
            )
    return "\n".join(lines)


def _only(m: dict | None) -> str:
    """A :func:`method_only` cell (its NaNs may come back from JSON as None)."""
    if not m or not m["n"]:
        return "0"
    f = {k: math.nan if m[k] is None else float(m[k]) for k in m}
    vis = f"{f['visible_min']:.2f}–{f['visible_max']:.2f}" if np.isfinite(f["visible_min"]) else "–"
    part = f"{f['partial']:.0f}" if np.isfinite(f["partial"]) else "–"
    return f"{m['n']} ({part}; {vis}), {f['mean_abs_mps']:.4f} ({f['both_mean_abs_mps']:.4f})"


def run_velocity_limits(works: Sequence[Path], log=print) -> dict:
    """:func:`draw_limits` of each work folder, :func:`fixed_sweep` over them all and
    the table; each folder's figures also written to ``W/velocity_limits.json``."""
    draws = {}
    for w in works:
        w = Path(w)
        draws[w.name] = draw_limits(w, log)
        (w / "velocity_limits.json").write_text(json.dumps(acc._finite(draws[w.name]), indent=1))
    sweep, visible = fixed_sweep(draws), visible_sweep(draws)
    table = format_limits(draws, sweep, visible=visible)
    return {"draws": draws, "sweep": sweep, "visible_sweep": visible, "table": table}
