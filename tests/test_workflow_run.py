"""The workflow end to end on a tiny synthetic campaign: results, bad input, resuming."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from surfphase.synth.campaign import write_campaign

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


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A tiny synthetic campaign with two sessions on one rig (generated once)."""
    out = tmp_path_factory.mktemp("tiny") / "campaign"
    write_campaign(out, preset="tiny", seed=3, sessions=2)
    return out


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


@pytest.fixture(scope="module")
def full_run(tiny: Path, tmp_path_factory) -> Path:
    """The whole workflow on the tiny campaign (run once; tests copy it to change it)."""
    work = make_workdir(tmp_path_factory.mktemp("full"), tiny)
    r = snakemake(work)
    assert r.returncode == 0, r.stdout + r.stderr
    return work


def test_full_run_produces_every_stage(full_run: Path):
    work = full_run
    cams = json.loads((work / "results/calib/rig01/cameras.json").read_text())["cameras"]
    assert set(cams) >= {"cam0", "cam1"}
    for s in SESSIONS:
        meta = json.loads((work / f"results/{s}/ingest/meta.json").read_text())
        stack = np.load(work / f"results/{s}/ingest/cam0.npy", mmap_mode="r")
        assert stack.shape[0] == len(meta["frame_indices"]) == 6
        labels = np.load(work / f"results/{s}/masks/cam0_labels.npy", mmap_mode="r")
        assert labels.shape == stack.shape
        bubbles = pd.read_csv(work / f"results/{s}/fit/bubbles.csv")
        assert set(bubbles["frame"]) == set(range(6))
        meshes = sorted((work / f"results/{s}/mesh").glob("*.ply"))
        assert len(meshes) == 6
        metrics = json.loads((work / f"results/{s}/evaluate/metrics.json").read_text())
        assert metrics["velocity"]["method"]["matched"] > 0
        assert metrics["chamfer_mm"]
        assert (work / f"results/{s}/report/velocity.png").exists()
        for rule in ("ingest", "mask", "fit", "mesh", "evaluate", "plots"):
            assert (work / f"logs/{rule}/{s}.log").exists()
            assert (work / f"benchmarks/{rule}/{s}.tsv").exists()
    table = pd.read_csv(work / "results/campaign/metrics.csv")
    assert len(table) == len(SESSIONS)
    assert "session01" in (work / "results/campaign/index.html").read_text()


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


def test_full_run_with_refinement(full_run: Path, tmp_path: Path):
    """Refinement on: novel views → prior → per-view SDEdit → stage-2 fit → evaluation.

    A small version of the demo's DAG (2 orbit views, a prior trained for 2 steps); the
    method's figures come from ``make demo`` and the benchmarks, not from this test. It
    goes on from the full run's stage 1 (copied with its Snakemake records: the stage-1
    settings are the same, so calibration, ingest, masks and stage 1 are not redone).
    """
    work = tmp_path / "work"
    shutil.copytree(full_run, work, symlinks=True)
    tiny = Path(sheet_value(work / "config" / "sessions.tsv", "session01", "cam0")).parents[1]
    cfg = work / "config" / "config.yaml"
    cfg.write_text(
        cfg.read_text()
        + "fit2:\n  iters_first: 4\n  iters_next: 2\n  views_per_step: 1\n"
        + f"prior:\n  clips: {tiny / 'clips'}\n"
        + "  embedded: {steps: 2, batch: 2, channels: [8, 16], sample_steps: 2, crop: 16,"
        + " frames: 4, overlap: 1}\n"
        + "refine:\n  enabled: true\n  n_views: 2\n  far_views: [2]\n"
        + "report:\n  mesh_frames: 1\n"
    )
    s = SESSIONS[0]
    r = snakemake(work, f"results/{s}/evaluate/metrics.json", f"results/{s}/report/videos")
    assert r.returncode == 0, r.stdout + r.stderr
    views = json.loads((work / f"results/{s}/views/cameras.json").read_text())
    assert set(views["cameras"]) == {"orbit01", "orbit02"}
    for v in ("orbit01", "orbit02"):
        raw = np.load(work / f"results/{s}/views/{v}.npy")
        refined = np.load(work / f"results/{s}/refine/{v}.npy")
        assert refined.shape == raw.shape and refined.dtype == raw.dtype == np.uint16
        assert not np.array_equal(refined, raw)  # strength > 0 changes the video
    stage2 = json.loads((work / f"results/{s}/fit2/stage2.json").read_text())
    assert stage2  # the stage-2 fit recorded its views and weights
    bubbles = pd.read_csv(work / f"results/{s}/fit2/bubbles.csv")
    assert set(bubbles["frame"]) == set(range(6))
    metrics = json.loads((work / f"results/{s}/evaluate/metrics.json").read_text())
    # The final fit is stage 2; stage 1 is scored beside it ("no refinement").
    assert metrics["velocity"]["method"]["matched"] > 0
    assert metrics["stage1"]["velocity"]["matched"] > 0
    assert (work / "results/prior/prior.json").exists()
    assert (work / f"logs/fit_stage2/{s}.log").exists()
    assert "rule fit:" not in r.stdout + r.stderr  # stage 1 was not redone


def test_failed_session_leaves_a_campaign_table_and_page_of_the_others(
    full_run: Path, tmp_path: Path, capsys
):
    """session02's fps is bad: session01 is finished (the full run's results, copied with
    their Snakemake records); `surfphase run` then writes the campaign table and page of
    session01, listing session02 with its error, and Snakemake still plans both outputs
    for the next run."""
    from surfphase.cli import main

    work = tmp_path / "work"
    shutil.copytree(full_run, work, symlinks=True)  # copy2: modification times kept
    shutil.rmtree(work / "results" / "session02")
    shutil.rmtree(work / "results" / "campaign")
    for log in work.glob("logs/*/session02.log"):
        log.unlink()
    edit_sheet(work / "config" / "sessions.tsv", "session02", "fps", "fast")
    assert main(["run", "--campaign", str(work), "--cores", "2"]) == 1
    out = capsys.readouterr().out
    assert "Campaign table and page of the 1 finished sessions (failed: session02)" in out
    table = pd.read_csv(work / "results/campaign/metrics.csv")
    assert list(table["session"]) == ["session01", "session02"]
    assert list(table["status"]) == ["finished", "failed"]
    err = table.set_index("session").loc["session02", "error"]
    assert err.startswith("session_sheet failed (log logs/session_sheet/session02.log)")
    assert "column 'fps': 'fast' is not a number" in err
    # session02 stopped at its sheet check, before its ingest.
    log = (work / "logs/session_sheet/session02.log").read_text()
    assert "config/sessions.tsv: session session02 (line 3): column 'fps': 'fast'" in log, log
    assert not (work / "logs/ingest/session02.log").exists()
    assert not (work / "results/session02/ingest").exists()
    metrics = json.loads((work / "results/session01/evaluate/metrics.json").read_text())
    row = table.set_index("session").loc["session01"]
    assert row["velocity.method.relative_error"] == pytest.approx(
        metrics["velocity"]["method"]["relative_error"]
    )
    page = (work / "results/campaign/index.html").read_text()
    assert "partial: 1 of 2 sessions finished" in page
    assert "is not a number" in page and 'id="session01"' in page
    # Not taken for Snakemake's own outputs: older than their inputs, so planned again.
    for f in ("metrics.csv", "index.html"):
        assert (work / "results/campaign" / f).stat().st_mtime == 0
    r = snakemake(work, "-n")
    assert r.returncode == 0, r.stdout + r.stderr
    jobs = {
        x.split()[0]: int(x.split()[1])
        for x in r.stdout.splitlines()
        if len(x.split()) == 2 and x.split()[1].isdigit()
    }
    assert jobs["campaign_table"] == jobs["campaign_page"] == jobs["session_sheet"] == 1
    assert jobs["ingest"] == jobs["plots"] == 1  # session02's; session01 is done


def test_status_tells_a_stale_lock_from_a_live_run(tiny: Path, tmp_path: Path, capsys):
    """`surfphase run` killed with SIGKILL (with its Snakemake): while it runs, status
    says so; afterwards it says the lock is stale and how to recover, and the next
    `surfphase run` says the previous run was killed, releases the lock and resumes."""
    from surfphase.cli import main
    from surfphase.commands.run import lock_note

    work = make_workdir(tmp_path, tiny)
    target = INGEST_TARGETS[:1]
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
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
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
