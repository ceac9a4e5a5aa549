"""Per session and stage of a campaign: done, failed, outdated or pending, as Snakemake's
``--detailed-summary`` sees every output of the DAG (the DAG is never re-implemented),
and running, as the job events of a live ``surfphase run`` say."""

from __future__ import annotations

import csv
import io
import os
import re
import subprocess
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

from surfphase.runner.events import EVENTS_FILE, EventFile, running_jobs
from surfphase.runner.locate import read_config, snakemake_base, tail_lines
from surfphase.runner.locks import lock_note, lock_state, read_run_file

# The workflow's rules (``snakemake --list-rules``, with ``mesh: window`` > 0 for
# ``mesh_window``) in the order of docs/method.md §1; rules not listed are shown after
# them (``tests/test_run_events.py`` checks the names against the Snakefile).
STAGE_ORDER = [
    "session_sheet",
    "calibrate",
    "ingest",
    "mask",
    "fit",
    "render_views",
    "train_prior",
    "refine",
    "fit_stage2",
    "fit_ablation",
    "mesh_window",
    "mesh",
    "mesh_compare",
    "evaluate",
    "plots",
    "mesh_snapshots",
    "report_videos",
    "campaign_table",
    "campaign_page",
]


@dataclass
class OutputState:
    """One output file of the campaign's DAG, as Snakemake's detailed summary sees it."""

    path: str
    rule: str
    status: str  # Snakemake's: ok, missing, incomplete, ...
    plan: str  # Snakemake's: no update, update pending
    logs: list[str] = field(default_factory=list)


def detailed_summary(
    snakefile: Path, camp: Path, extra: list[str] | None = None
) -> list[OutputState]:
    """Every output of the DAG with its rule and state (``snakemake --detailed-summary``)."""
    cmd = snakemake_base(snakefile, camp) + ["--detailed-summary", "--cores", "1"] + (extra or [])
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise ValueError(
            f"campaign {camp}: Snakemake could not read the workflow:\n{tail_lines(res.stderr, 15)}"
        )
    text = res.stdout[res.stdout.find("output_file\t") :]
    rows = []
    for row in csv.DictReader(io.StringIO(text), delimiter="\t"):
        if not row.get("output_file"):
            continue
        logs = [s for s in (row.get("log-file(s)") or "").split(",") if s and s != "-"]
        rows.append(
            OutputState(
                path=row["output_file"],
                rule=row.get("rule") or "?",
                status=(row.get("status") or "").strip(),
                plan=(row.get("plan") or "").strip(),
                logs=[s.strip() for s in logs],
            )
        )
    return rows


def unit_of(path: str, results: str) -> str:
    """Which part of the campaign an output belongs to: a session, ``calib/<rig>`` or
    ``campaign`` (outputs under ``results/<session>/...`` and ``results/calib/<rig>/...``)."""
    parts = Path(os.path.normpath(path)).parts
    res = Path(os.path.normpath(results)).parts
    if parts[: len(res)] != res or len(parts) <= len(res) + 1:
        return "campaign"
    head = parts[len(res)]
    if head == "calib" and len(parts) > len(res) + 2:
        return f"calib/{parts[len(res) + 1]}"
    return head


def output_state(o: OutputState, camp: Path) -> str:
    """done / failed / outdated / pending for one output."""
    if o.status == "incomplete":
        return "failed"
    # A temporary output (e.g. a mesh window) removed after its consumer ran was made.
    if o.status in ("ok", "removed temp file") or (camp / o.path).exists():
        return "outdated" if o.plan == "update pending" else "done"
    if any((camp / log).is_file() for log in o.logs):
        return "failed"
    return "pending"


def campaign_status(
    snakefile: Path, camp: Path, sessions: list[str] | None = None
) -> dict[str, dict[str, dict]]:
    """``{unit: {stage: {"state": ..., "outputs": n, "logs": [...]}}}`` of a campaign.

    A unit is a session, ``calib/<rig>`` or ``campaign``; a stage is a rule. A stage is
    failed if any output failed, else pending if any is pending, else outdated if any is
    outdated, else done; while `surfphase run` runs in the campaign, a stage with a job
    that its events file (:mod:`surfphase.runner.events`) says has started and not
    ended is running instead of failed or pending.
    """
    results = str(read_config(camp).get("results", "results"))
    table: dict[str, dict[str, dict]] = {}
    rank = {"failed": 3, "pending": 2, "outdated": 1, "done": 0}
    for o in detailed_summary(snakefile, camp):
        unit = unit_of(o.path, results)
        if sessions and unit not in sessions:
            continue
        state = output_state(o, camp)
        cell = table.setdefault(unit, {}).setdefault(
            o.rule, {"state": "done", "outputs": 0, "logs": []}
        )
        cell["outputs"] += 1
        if rank[state] > rank[cell["state"]]:
            cell["state"] = state
        if state == "failed":
            cell["logs"] += [log for log in o.logs if log not in cell["logs"]]
    if read_run_file(camp) and lock_state(camp)["live"]:  # `surfphase run` runs now
        mark_running(table, running_jobs(EventFile(camp / EVENTS_FILE).new()), results)
    return table


def mark_running(table: dict[str, dict[str, dict]], jobs: list[dict], results: str) -> None:
    """Cells of ``table`` (see :func:`campaign_status`) with a running job (``job_info``
    events of :func:`surfphase.runner.events.running_jobs`; the job's unit is that of its
    outputs, :func:`unit_of`) become ``running`` when not all their outputs are there
    (failed or pending)."""
    for job in jobs:
        for unit in {unit_of(path, results) for path in job.get("output") or []}:
            cell = table.get(unit, {}).get(job.get("rule", ""))
            if cell and cell["state"] in ("failed", "pending"):
                cell["state"], cell["logs"] = "running", []


def stage_columns(table: dict[str, dict[str, dict]]) -> list[str]:
    seen = {s for cells in table.values() for s in cells}
    return [s for s in STAGE_ORDER if s in seen] + sorted(seen - set(STAGE_ORDER))


def format_status(table: dict[str, dict[str, dict]], camp: Path) -> str:
    stages = stage_columns(table)
    units = sorted(table, key=lambda u: (u == "campaign", not u.startswith("calib/"), u))
    width = max([len("session")] + [len(u) for u in units]) + 2
    colw = [max(len(s), 8) + 2 for s in stages]
    lines = [
        "session".ljust(width) + "".join(s.ljust(w) for s, w in zip(stages, colw, strict=True))
    ]
    for u in units:
        cells = [table[u].get(s, {}).get("state", "-") for s in stages]
        lines.append(u.ljust(width) + "".join(c.ljust(w) for c, w in zip(cells, colw, strict=True)))
    counts: dict[str, int] = {}
    for cells in table.values():
        for c in cells.values():
            counts[c["state"]] = counts.get(c["state"], 0) + 1
    lines.append("")
    lines.append(
        "stages: "
        + ", ".join(f"{counts.get(k, 0)} {k}" for k in ("done", "failed", "outdated", "pending"))
        + (f", {counts['running']} running" if counts.get("running") else "")
    )
    for u in units:
        for s in stages:
            cell = table[u].get(s)
            if cell and cell["state"] == "failed":
                for log in cell["logs"] or ["(no log)"]:
                    last = last_line(camp / log) if cell["logs"] else ""
                    lines += failure_lines(f"failed: {s} {u}: {log}", last)
    lines += lock_note(camp)
    return "\n".join(lines)


def failure_lines(head: str, last: str, width: int = 100) -> list[str]:
    """``head  | last`` on one line when it fits in ``width``, else ``last`` wrapped
    under ``head`` (never cut: a log's last line often ends with the file at fault)."""
    if not last:
        return [head]
    if len(head) + 4 + len(last) <= width:
        return [f"{head}  | {last}"]
    wrapped = textwrap.wrap(last, width - 6, break_long_words=False, break_on_hyphens=False) or [
        last
    ]
    return [head, *(f"    | {ln}" for ln in wrapped)]


def middle_cut(text: str, width: int) -> str:
    """``text`` cut to ``width`` characters in the middle, keeping its start and end."""
    if len(text) <= width:
        return text
    keep = max(width - 1, 2)
    head = keep // 3
    return text[:head] + "…" + text[len(text) - (keep - head) :]


def last_line(path: Path, max_bytes: int = 4096) -> str:
    """The last non-empty line of a (log) file, or '' (at most 1000 characters: longer
    ones are cut in the middle, keeping the end)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            text = f.read().decode(errors="replace")
    except OSError:
        return ""
    lines = [ln.strip() for ln in re.split(r"[\r\n]", text) if ln.strip()]
    return middle_cut(lines[-1], 1000) if lines else ""
