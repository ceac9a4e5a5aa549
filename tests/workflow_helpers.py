"""Shared pieces of the workflow tests (test_workflow_run, test_workflow_faults): a
Snakemake working directory on the tiny campaign (conftest's ``tiny``), sheet edits."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SESSIONS = ("session01", "session02")
# Bad-input and resume tests drive the DAG up to the frame stacks: that is where a
# session's input is read. The full run uses a very short fit.
INGEST_TARGETS = [f"results/{s}/ingest" for s in SESSIONS]
SHORT_FIT = (
    "ingest:\n  scale: 0.25\n"
    "fit:\n  iters_first: 15\n  iters_next: 4\n  n_init: 300\n  render_frames: 1\n"
    "mesh:\n  voxels: 32\n  n_orbit: 3\n"
)


def make_workdir(tmp_path: Path, campaign: Path) -> Path:
    """A Snakemake working directory whose config points at ``campaign``'s sheets."""
    work = tmp_path / "work"
    (work / "config").mkdir(parents=True)
    shutil.copy(campaign / "sessions.tsv", work / "config" / "sessions.tsv")
    shutil.copy(campaign / "rigs.tsv", work / "config" / "rigs.tsv")
    for sheet in ("sessions.tsv", "rigs.tsv"):
        text = (work / "config" / sheet).read_text()
        lines = text.splitlines()
        # Re-root the sheet's relative paths at the campaign folder.
        head, rows = lines[0], lines[1:]
        cols = head.split("\t")
        path_cols = [i for i, c in enumerate(cols) if c.startswith("cam") or c in ("gt", "board")]
        fixed = []
        for row in rows:
            cells = row.split("\t")
            for i in path_cols:
                if i < len(cells) and cells[i] and not os.path.isabs(cells[i]):
                    cells[i] = str((campaign / cells[i]).resolve())
            fixed.append("\t".join(cells))
        (work / "config" / sheet).write_text("\n".join([head, *fixed]) + "\n")
    (work / "config" / "config.yaml").write_text(
        "sessions: config/sessions.tsv\nrigs: config/rigs.tsv\nresults: results\n"
        "device: cpu\nthreads: 1\ncalibrate:\n  min_images: 6\n" + SHORT_FIT
    )
    return work


def snakemake(work: Path, *args: str, **kw) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work)]
    return subprocess.run(
        [*cmd, "--cores", "2", *args], capture_output=True, text=True, timeout=900, **kw
    )


def sheet_value(path: Path, session: str, column: str) -> str:
    lines = path.read_text().splitlines()
    cols = lines[0].split("\t")
    row = next(r.split("\t") for r in lines[1:] if r.split("\t")[0] == session)
    return row[cols.index(column)]


def edit_sheet(path: Path, session: str, column: str, value: str) -> None:
    lines = path.read_text().splitlines()
    cols = lines[0].split("\t")
    i = cols.index(column)
    out = [lines[0]]
    for row in lines[1:]:
        cells = row.split("\t")
        if cells[0] == session:
            cells[i] = value
        out.append("\t".join(cells))
    path.write_text("\n".join(out) + "\n")
