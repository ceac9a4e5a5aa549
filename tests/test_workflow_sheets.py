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
    assert "config/sessions.tsv" in out and "fps" in out


def test_duplicate_session_ids_are_refused(campaign: Path):
    sheet = campaign / "config" / "sessions.tsv"
    lines = sheet.read_text().splitlines()
    sheet.write_text("\n".join([*lines, lines[1]]) + "\n")
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    out = r.stdout + r.stderr
    assert "duplicate" in out and "session01" in out


def test_non_numeric_fps_is_refused(campaign: Path):
    sheet = campaign / "config" / "sessions.tsv"
    sheet.write_text(sheet.read_text().replace("\t1500\t", "\tfast\t", 1))
    r = snakemake(campaign, "-n")
    assert r.returncode != 0
    out = r.stdout + r.stderr
    assert "fps" in out and "config/sessions.tsv" in out
