"""The workflow reads and validates the campaign sheets before any job runs."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    """Run Snakemake on the project's Snakefile in its own working directory."""
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(workdir)]
    return subprocess.run(
        [*cmd, "--cores", "1", *args], capture_output=True, text=True, timeout=300
    )


@pytest.fixture
def campaign(tmp_path: Path) -> Path:
    """A working directory holding a copy of the demo configuration."""
    shutil.copytree(ROOT / "config", tmp_path / "config")
    return tmp_path


def test_lint_is_clean():
    r = subprocess.run(
        [sys.executable, "-m", "snakemake", "--lint", "--cores", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Congratulations" in r.stdout + r.stderr


def test_dry_run_lists_jobs_per_rig_and_session(campaign: Path):
    r = snakemake(campaign, "-n")
    assert r.returncode == 0, r.stdout + r.stderr
    out = r.stdout + r.stderr
    for job, count in [("calibrate", 1), ("ingest", 2)]:
        line = next(x for x in out.splitlines() if x.split()[:1] == [job])
        assert int(line.split()[1]) == count


def test_missing_column_names_sheet_and_column(campaign: Path):
    sheet = campaign / "config" / "sessions.tsv"
    lines = sheet.read_text().splitlines()
    header = lines[0].split("\t")
    drop = header.index("fps")
    sheet.write_text(
        "\n".join("\t".join(c for i, c in enumerate(x.split("\t")) if i != drop) for x in lines)
    )
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    out = r.stdout + r.stderr
    # One line says it (no schema dump): the sheet, the column, what is required.
    line = next(x for x in out.splitlines() if "missing column" in x)
    assert "config/sessions.tsv" in line and "fps" in line and "required" in line
    assert len(out.strip().splitlines()) <= 5, out
    assert "properties" not in out


def test_duplicate_session_ids_are_refused(campaign: Path):
    sheet = campaign / "config" / "sessions.tsv"
    lines = sheet.read_text().splitlines()
    sheet.write_text("\n".join([*lines, lines[1]]) + "\n")
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    out = r.stdout + r.stderr
    assert "duplicate" in out and "session01" in out


def edit_cell(sheet: Path, session: str, column: str, value: str) -> None:
    lines = sheet.read_text().splitlines()
    i = lines[0].split("\t").index(column)
    rows = [r.split("\t") for r in lines[1:]]
    for r in rows:
        if r[0] == session:
            r[i] = value
    sheet.write_text("\n".join([lines[0], *("\t".join(r) for r in rows)]) + "\n")


#: One bad cell per extra session: (column, value, why the log gives).
BAD_CELLS = {
    "session02": ("fps", "fast", "is not a number"),
    "session03": ("fps", "0", "must be greater than 0"),
    "session04": ("fps", "-5", "must be greater than 0"),
    "session05": ("frames", "1-5", "does not match"),
}


def test_bad_cell_fails_only_that_session(campaign: Path):
    """A bad cell of one row is that session's problem: the DAG builds, the other
    sessions are planned as usual, and each bad session's one job fails, naming the
    sheet, the session, the column and the value (the full run is in test_workflow_run).
    Four bad sessions (copies of session02, one bad cell each) share one campaign."""
    sheet = campaign / "config" / "sessions.tsv"
    head, *rows = sheet.read_text().splitlines()
    template = next(r for r in rows if r.split("\t")[0] == "session02")
    extra = [template.replace("session02", s, 1) for s in BAD_CELLS if s != "session02"]
    sheet.write_text("\n".join([head, *rows, *extra]) + "\n")
    for session, (column, value, _) in BAD_CELLS.items():
        edit_cell(sheet, session, column, value)
    r = snakemake(campaign, "-n")
    assert r.returncode == 0, r.stdout + r.stderr
    counts = {x.split()[0]: x.split()[1] for x in r.stdout.splitlines() if len(x.split()) == 2}
    assert counts["session_sheet"] == str(len(BAD_CELLS)) and counts["ingest"] == "5"
    targets = [f"results/{s}/sheet_row.ok" for s in BAD_CELLS]
    r = snakemake(campaign, "--keep-going", *targets)
    assert r.returncode != 0
    for session, (column, value, why) in BAD_CELLS.items():
        log = (campaign / f"logs/session_sheet/{session}.log").read_text()
        assert "config/sessions.tsv" in log and session in log and "session01" not in log
        assert f"column '{column}': '{value}' {why}" in log, log


def test_bad_session_id_refuses_the_sheet_in_one_line(campaign: Path):
    sheet = campaign / "config" / "sessions.tsv"
    edit_cell(sheet, "session02", "session", "session 02")
    head, *rows = sheet.read_text().splitlines()
    sheet.write_text("\n".join([head, "# a comment line", *rows]) + "\n")
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    line = next(x for x in (r.stdout + r.stderr).splitlines() if "not valid" in x)
    assert "config/sessions.tsv: line 4" in line and "'session 02'" in line  # the file's line


def test_config_typo_fails_the_whole_dag_in_one_line(campaign: Path):
    """The config is campaign-wide: a typo stops every session before any job runs."""
    cfg = campaign / "config" / "config.yaml"
    cfg.write_text(cfg.read_text().replace("  enabled: true ", "  enabeld: true ", 1))
    assert "enabeld" in cfg.read_text()
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    out = r.stdout + r.stderr
    assert "config refine: Additional properties are not allowed ('enabeld' was unexpected)" in out
    assert len(out.strip().splitlines()) <= 5, out


@pytest.mark.parametrize(
    ("old", "new", "line"),
    [
        (  # a key of a nested section of a stage's block
            "    threshold_low: 0.08",
            "    thresold_low: 0.08",
            "config masks.classical.thresold_low: unknown key (did you mean threshold_low?)",
        ),
        (
            "  iters_first: 150 ",
            "  iters_frist: 150 ",
            "config fit.iters_frist: unknown key (did you mean iters_first?)",
        ),
        (  # a number YAML reads as text
            "  track_window_s: 0.003 ",
            "  track_window_s: 3e-3 ",
            "config fit.track_window_s: '3e-3' is text, a number is expected: write 0.003 "
            "(YAML reads 3e-3 as text)",
        ),
    ],
)
def test_stage_key_typo_fails_the_whole_dag_in_one_line(campaign: Path, old, new, line):
    """The stages' blocks are open in the schema (their keys are the stages' DEFAULTS):
    a key no stage knows stops every session before any job runs, not when that stage's
    first job starts."""
    cfg = campaign / "config" / "config.yaml"
    text = cfg.read_text()
    assert text.count(old) == 1
    cfg.write_text(text.replace(old, new))
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    out = r.stdout + r.stderr
    assert line in out.splitlines(), out
    assert len(out.strip().splitlines()) <= 5, out
