"""After a run in which some sessions failed: the campaign table and page of the sessions
that finished, with a row per failed session and its error."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from surfphase.io import atomic_write_text
from surfphase.runner.locate import read_config
from surfphase.runner.status import campaign_status, last_line, stage_columns


def campaign_sessions(camp: Path) -> list[str]:
    """The session ids of the campaign's sessions sheet (config ``sessions``)."""
    import pandas as pd

    sheet = camp / str(read_config(camp).get("sessions", "config/sessions.tsv"))
    try:
        df = pd.read_csv(sheet, sep="\t", dtype=str, comment="#", keep_default_na=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{sheet}: cannot read the sessions sheet ({e})") from e
    df.columns = [c.strip() for c in df.columns]
    if "session" not in df.columns:
        raise ValueError(f"{sheet}: no 'session' column")
    return [v.strip() for v in df["session"] if v.strip()]


def session_outcomes(
    table: dict[str, dict[str, dict]], camp: Path, sessions: list[str]
) -> dict[str, str]:
    """``{session: ""}`` for each of ``sessions`` whose every stage is done, else
    ``{session: why}``: the first failed stage and the last line of its log, or the
    first stage not run and why (a failed calibration)."""
    calib_failed = [
        f"calibrate {u} failed: {last_line(camp / c['logs'][0]) if c['logs'] else 'no log'}"
        for u, cells in sorted(table.items())
        if u.startswith("calib/")
        for c in cells.values()
        if c["state"] == "failed"
    ]
    out = {}
    for unit, cells in table.items():
        if unit not in sessions:
            continue  # the campaign's own outputs, a rig's calibration, the prior
        order = stage_columns({unit: cells})
        failed = [s for s in order if cells[s]["state"] == "failed"]
        waiting = [s for s in order if cells[s]["state"] != "done"]
        if failed:
            s = failed[0]
            log = cells[s]["logs"][0] if cells[s]["logs"] else ""
            last = last_line(camp / log) if log else ""
            out[unit] = f"{s} failed" + (f" (log {log}): {last}" if log else "")
        elif waiting:
            out[unit] = f"{waiting[0]} not run ({cells[waiting[0]]['state']})" + (
                f"; {'; '.join(calib_failed)}" if calib_failed else ""
            )
        else:
            out[unit] = ""
    return out


def partial_campaign(snakefile: Path, camp: Path, out=None) -> bool:
    """After a run in which some sessions failed: write the campaign table and page
    (``RESULTS/campaign/metrics.csv``, ``index.html``) of the sessions that finished,
    with a row per failed session: its ``status`` and ``error``.

    Snakemake does not take them for its own: they get the modification time 0 (older
    than any input), so the next run rewrites both from every session. Returns whether
    they were written (not when nothing finished or the campaign outputs are up to date).
    """
    from surfphase.eval.stage import campaign_table
    from surfphase.report.plots import campaign_page

    out = out or sys.stdout
    table = campaign_status(snakefile, camp)
    stages = table.get("campaign", {})
    if "campaign_table" not in stages or all(c["state"] == "done" for c in stages.values()):
        return False
    results = camp / str(read_config(camp).get("results", "results"))
    outcomes = session_outcomes(table, camp, campaign_sessions(camp))
    done = sorted(s for s, why in outcomes.items() if not why)
    failed = sorted(s for s, why in outcomes.items() if why)
    if not done:
        out.write("No session finished: no campaign table or page.\n")
        return False
    rows = []
    for s in done:
        rows.append({**json.loads((results / s / "evaluate" / "metrics.json").read_text())})
        rows[-1]["session"], rows[-1]["status"], rows[-1]["error"] = s, "finished", ""
    rows += [{"session": s, "status": "failed", "error": outcomes[s]} for s in failed]
    metrics_csv = results / "campaign" / "metrics.csv"
    atomic_write_text(metrics_csv, campaign_table(rows).to_csv(index=False))
    media: dict[str, dict[str, list[Path]]] = {k: {} for k in ("figures", "overlays", "meshes")}
    media["videos"] = {}
    for s in done:
        rep = results / s / "report"
        media["figures"][s] = [rep / "velocity.png"] if (rep / "velocity.png").is_file() else []
        media["overlays"][s] = sorted((rep / "masks").glob("*.png"))
        media["meshes"][s] = sorted((rep / "meshes").glob("*.png"))
        media["videos"][s] = sorted((rep / "videos").glob("*.mp4"))
    prior = results / "prior" / "samples.png"
    page = results / "campaign" / "index.html"
    campaign_page(
        metrics_csv,
        page,
        media["figures"],
        media["overlays"],
        f"SurfPhase campaign (partial: {len(done)} of {len(outcomes)} sessions finished)",
        meshes=media["meshes"],
        videos=media["videos"],
        prior_samples=prior if prior.is_file() else None,
    )
    for f in (metrics_csv, page):
        os.utime(f, (0, 0))  # older than every input: Snakemake reruns them
    out.write(
        f"Campaign table and page of the {len(done)} finished sessions (failed: "
        f"{', '.join(failed)}): {metrics_csv.relative_to(camp)}, {page.relative_to(camp)}; "
        "the next run rewrites them.\n"
    )
    out.flush()
    return True
