"""The workflow end to end on a tiny synthetic campaign: every stage's results, with and
without refinement, and the campaign outputs of a partly failed run (bad input and
resuming: test_workflow_faults)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from workflow_helpers import (
    SESSIONS,
    edit_sheet,
    make_workdir,
    sheet_value,
    snakemake,
)


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
        # Positions, velocities and the meshes' sizes in one table; their summary.
        sized = pd.read_csv(work / f"results/{s}/evaluate/bubbles.csv")
        assert len(sized) == len(bubbles) and {"volume_m3", "d_eq_m", "closed"} <= set(sized)
        assert metrics["sizes"]["bubble_frames"] == int(
            ((sized.bubble >= 1) & sized.volume_m3.notna()).sum()
        )
        assert (work / f"results/{s}/report/velocity.png").exists()
        for rule in ("ingest", "mask", "fit", "mesh", "evaluate", "plots"):
            assert (work / f"logs/{rule}/{s}.log").exists()
            assert (work / f"benchmarks/{rule}/{s}.tsv").exists()
    table = pd.read_csv(work / "results/campaign/metrics.csv")
    assert len(table) == len(SESSIONS) and "sizes.d_eq_mm_mean" in table.columns
    assert "session01" in (work / "results/campaign/index.html").read_text()


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
