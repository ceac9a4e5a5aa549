"""The workflow on bad input and after a kill, on the tiny synthetic campaign: a bad
session stops only itself, a killed run resumes, a stale lock is told from a live run."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from workflow_helpers import (
    INGEST_TARGETS,
    ROOT,
    edit_sheet,
    make_workdir,
    sheet_value,
    snakemake,
)


def add_session_copies(sheet: Path, source: str, names: list[str]) -> None:
    """Append rows to ``sheet`` that copy ``source``'s row under new session ids."""
    head, *rows = sheet.read_text().splitlines()
    row = next(r for r in rows if r.split("\t")[0] == source)
    extra = ["\t".join([n, *row.split("\t")[1:]]) for n in names]
    sheet.write_text("\n".join([head, *rows, *extra]) + "\n")


def test_bad_sessions_stop_only_themselves(tiny: Path, tmp_path: Path):
    """Four sessions, each with its own fault, beside a healthy one, in one run: each
    bad session's log names the session and the file at fault; session01 finishes.

    session02: a missing video folder; session03: a rig the rigs sheet lacks;
    session04: cam1 two frames short; session05: its rig's calibration has too few
    images (the calibrate job fails, naming the rig and the folder)."""
    work = make_workdir(tmp_path, tiny)
    sheet = work / "config" / "sessions.tsv"
    add_session_copies(sheet, "session02", ["session03", "session04", "session05"])
    bad = str(tmp_path / "nowhere" / "cam1")
    edit_sheet(sheet, "session02", "cam1", bad)
    edit_sheet(sheet, "session03", "rig", "rig99")
    src = Path(sheet_value(sheet, "session04", "cam1"))
    short = tmp_path / "short_cam1"
    shutil.copytree(src, short)
    for f in sorted(short.iterdir())[-2:]:
        f.unlink()
    edit_sheet(sheet, "session04", "cam1", str(short))
    rigs = work / "config" / "rigs.tsv"
    lines = rigs.read_text().splitlines()
    cols = lines[0].split("\t")
    row = lines[1].split("\t")
    few = tmp_path / "few_cam1"
    few.mkdir()
    for f in sorted(Path(row[cols.index("cam1")]).iterdir())[:3]:
        shutil.copy(f, few / f.name)
    row2 = list(row)
    row2[0] = "rig02"
    row2[cols.index("cam1")] = str(few)
    rigs.write_text("\n".join([*lines, "\t".join(row2)]) + "\n")
    edit_sheet(sheet, "session05", "rig", "rig02")
    sessions = ["session01", "session02", "session03", "session04", "session05"]
    r = snakemake(work, "--keep-going", *[f"results/{s}/ingest" for s in sessions])
    assert r.returncode != 0
    for s, expect in [
        ("session02", [bad]),
        ("session03", ["rig99", "rigs.tsv"]),
        ("session04", [str(short)]),
    ]:
        log = (work / f"logs/ingest/{s}.log").read_text()
        assert s in log
        for e in expect:
            assert e in log, log
        assert not (work / f"results/{s}/ingest").exists()
    log = (work / "logs/calibrate/rig02.log").read_text()
    assert "rig02" in log and str(few) in log, log
    assert not (work / "results/session05/ingest").exists()
    # The healthy session finished.
    assert (work / "results/session01/ingest/meta.json").exists()


def test_killed_run_resumes_with_rerun_incomplete(tiny: Path, tmp_path: Path):
    work = make_workdir(tmp_path, tiny)
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work)]
    proc = subprocess.Popen(
        [*cmd, "--cores", "1", *INGEST_TARGETS],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    # Kill the whole process group as soon as the first ingest job has started.
    deadline = time.time() + 300
    while time.time() < deadline and not (work / "logs/ingest").exists():
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    # The documented resume: release the lock the killed run left, rerun what is incomplete.
    assert snakemake(work, "--unlock").returncode == 0
    r = snakemake(work, "--rerun-incomplete", *INGEST_TARGETS)
    assert r.returncode == 0, r.stdout + r.stderr
    ref = make_workdir(tmp_path / "ref", tiny)
    assert snakemake(ref, *INGEST_TARGETS).returncode == 0
    for s in ("session01", "session02"):
        a = np.load(work / f"results/{s}/ingest/cam0.npy")
        b = np.load(ref / f"results/{s}/ingest/cam0.npy")
        np.testing.assert_array_equal(a, b)


def test_status_tells_a_stale_lock_from_a_live_run(tiny: Path, tmp_path: Path, capsys):
    """`surfphase run` killed with SIGKILL (with its Snakemake): while it runs, status
    says so; afterwards it says the lock is stale and how to recover, and the next
    `surfphase run` says the previous run was killed, releases the lock and resumes."""
    from surfphase.cli import main
    from surfphase.commands.run import lock_note

    work = make_workdir(tmp_path, tiny)
    # Two sessions' ingest on one core: once the first has started, the second keeps the
    # run alive, so the kill finds it running even on a busy machine (with one target
    # the run could end, releasing its lock, between the check below and the kill).
    target = INGEST_TARGETS
    proc = subprocess.Popen(
        [sys.executable, "-m", "surfphase", "run", "--campaign", str(work), "--cores", "1"]
        + target,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.time() + 300
    while time.time() < deadline and not (work / "logs/ingest").exists():
        time.sleep(0.2)
    live = lock_note(work)
    running = proc.poll() is None
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert running, "the run ended before it could be killed"
    assert live and live[0].startswith("note: Snakemake is running in this campaign (pid ")
    assert main(["status", "--campaign", str(work)]) == 0
    text = capsys.readouterr().out
    assert "Snakemake is running" not in text
    assert "note: stale lock: the last run was killed" in text
    assert "`surfphase run` resumes it" in text and "snakemake --unlock --directory" in text
    assert main(["run", "--campaign", str(work), "--cores", "2", *target]) == 0
    out = capsys.readouterr().out
    assert "The previous run (pid " in out and "was killed before it finished" in out
    assert "Releasing its stale lock" in out
    assert (work / f"{target[0]}/meta.json").exists()
    assert not (work / ".surfphase/run.json").exists()
    assert lock_note(work) == []  # the resumed run ended and released its lock
