"""Frame windows: a long session's meshes made by several jobs, gathered into the same
files one job writes; the workflow knows the number of windows when it builds the DAG."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_mesh_resume import FIRST_FRAME, PARAMS, assert_same_meshes, write_fit

from surfphase.cli import main
from surfphase.mesh.stage import gather_mesh, run_mesh, run_mesh_window
from surfphase.mesh.windows import (
    fitted_frame_count,
    sheet_frame_count,
    window_count,
    window_positions,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.mark.parametrize(
    "spec, count",
    [("0:3000", 3000), ("10:2010:2", 1000), (":7", 7), ("5:8:", 3), ("1:10:4", 3)],
)
def test_sheet_frame_count_is_the_slice_length(spec, count):
    # Reference: Python's own slicing of a long enough list of frames.
    start, stop, *step = spec.split(":")
    sl = slice(int(start or 0), int(stop), int(step[0]) if step and step[0] else None)
    assert len(list(range(10_000))[sl]) == count
    assert sheet_frame_count(spec) == count


def test_sheet_frame_count_unknown_or_bad():
    for spec in (None, "", "5:", ":"):
        assert sheet_frame_count(spec) is None  # the video decides
    for spec in ("5:5", "3", "a:b", "0:10:0"):
        with pytest.raises(ValueError, match="frame range"):
            sheet_frame_count(spec)
    assert fitted_frame_count(1000, None) == 1000
    assert fitted_frame_count(1000, 250) == 250
    assert fitted_frame_count(100, 250) == 100


@pytest.mark.parametrize("n, size", [(1, 1), (7, 3), (9, 3), (10, 100), (2500, 100)])
def test_windows_cover_every_frame_once(n, size):
    picks = list(range(3, 3 + n))
    k = window_count(n, size)
    windows = [window_positions(picks, i, size) for i in range(k)]
    assert [t for w in windows for t in w] == picks
    assert all(1 <= len(w) <= size for w in windows)
    assert window_positions(picks, k, size) == []
    with pytest.raises(ValueError):
        window_count(n, 0)


def test_gathered_windows_equal_a_single_job(tmp_path):
    fit, ingest = write_fit(tmp_path, frames=7)
    single = tmp_path / "single"
    run_mesh(fit, ingest, single, PARAMS, device="cpu")
    # Windows of 3 frames by the command line: [0, 1, 2], [3, 4, 5], [6]. The fastest
    # frame is in the last one, so colours are right only if gathered session-wide.
    windows = []
    for k in range(window_count(7, 3)):
        w = tmp_path / "windows" / str(k)
        args = ["mesh", "--fit", str(fit), "--ingest", str(ingest), "--out", str(w)]
        args += ["--window", str(k), "--window-size", "3", "--device", "cpu"]
        assert main([*args, "--params-json", json.dumps(PARAMS)]) == 0
        info = json.loads((w / "window.json").read_text())
        assert info["frames"] == [FIRST_FRAME + t for t in window_positions(range(7), k, 3)]
        assert not (tmp_path / "windows" / f"{k}.partial").exists()
        windows.append(w)
    out = tmp_path / "gathered"
    assert main(["mesh-gather", "--windows", *map(str, reversed(windows)), "--out", str(out)]) == 0
    assert_same_meshes(single, out)


def test_gather_refuses_incomplete_or_foreign_windows(tmp_path):
    fit, ingest = write_fit(tmp_path / "a", frames=3)
    w = [tmp_path / "w" / str(k) for k in range(3)]
    for k in (0, 2):
        run_mesh_window(fit, ingest, w[k], k, 1, PARAMS, device="cpu")
    with pytest.raises(ValueError, match=r"cover 2 of 3 fitted frames \(missing positions \[1\]"):
        gather_mesh([w[0], w[2]], tmp_path / "out")
    with pytest.raises(ValueError, match="also in window"):
        gather_mesh([w[0], w[0], w[2]], tmp_path / "out")
    run_mesh_window(fit, ingest, w[1], 1, 1, {**PARAMS, "voxels": 20}, device="cpu")
    with pytest.raises(ValueError, match="differs from .*windows of different runs"):
        gather_mesh(w, tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="window.json"):
        gather_mesh([tmp_path / "a"], tmp_path / "out")
    assert not (tmp_path / "out").exists()


def write_campaign_sheets(work: Path, rows: list[tuple[str, str]], config: str) -> None:
    """Sheets of sessions ``(id, frames)`` whose videos need not exist (dry runs, or runs
    restricted to rules whose inputs are present)."""
    (work / "config").mkdir(parents=True)
    lines = ["session\trig\tfps\tframes\tcam0\tcam1"]
    lines += [f"{s}\trig01\t1500\t{f}\tvideos/{s}_0.cine\tvideos/{s}_1.cine" for s, f in rows]
    (work / "config" / "sessions.tsv").write_text("\n".join(lines) + "\n")
    (work / "config" / "rigs.tsv").write_text(
        "rig\tboard\tcam0\tcam1\nrig01\tboard.yaml\tcalib/cam0\tcalib/cam1\n"
    )
    (work / "config" / "config.yaml").write_text(
        "sessions: config/sessions.tsv\nrigs: config/rigs.tsv\nresults: results\n"
        "device: cpu\nthreads: 1\ningest:\n  scale: 0.25\n" + config
    )


def snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work)]
    return subprocess.run(
        [*cmd, "--cores", "2", *args], capture_output=True, text=True, timeout=600
    )


def job_counts(stdout: str) -> dict[str, int]:
    """The first job-stats table of a Snakemake dry run (``-n --quiet rules``)."""
    counts: dict[str, int] = {}
    for line in stdout.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit():
            if parts[0] in counts:
                break
            counts[parts[0]] = int(parts[1])
    return counts


def test_long_sheet_dry_run_lists_the_window_jobs(tmp_path):
    rows = [("long1", "0:3000"), ("long2", "10:2010:2"), ("open3", "")]
    # long1: 3000 frames, the fit keeps 2500 -> 25 windows; long2: 1000 -> 10 windows;
    # open3: the video decides -> a checkpoint reads the ingest's frame count first.
    write_campaign_sheets(tmp_path, rows, "fit:\n  frames: 2500\nmesh:\n  window: 100\n")
    r = snakemake(tmp_path, "-n", "--quiet", "rules")
    assert r.returncode == 0, r.stdout + r.stderr
    jobs = job_counts(r.stdout)
    assert jobs["mesh_window"] == 35, r.stdout
    assert jobs["mesh_frame_count"] == 1
    assert jobs["mesh"] == 3
    assert jobs["fit"] == 3  # the fit stays one job per session


def test_workflow_windows_equal_a_single_job(tmp_path):
    # One session whose frame count comes from the ingest (checkpoint), 4 frames in
    # windows of 3; the fit and ingest are given, so only the mesh rules run.
    work = tmp_path / "work"
    settings = "".join(f"  {k}: {v}\n" for k, v in PARAMS.items())
    write_campaign_sheets(work, [("s1", "")], f"mesh:\n{settings}  window: 3\n")
    fit, ingest = write_fit(work / "results" / "s1", frames=4, session="s1")
    # The mesh rules carve by the session's masks (here every pixel is the nucleation
    # region); the single job gets the same masks.
    from surfphase.cameras import load_cameras

    (work / "results/s1/masks").mkdir()
    for name, cam in load_cameras(Path(ingest) / "cameras.json").items():
        np.save(
            work / f"results/s1/masks/{name}_labels.npy",
            np.zeros((4, cam.height, cam.width), np.int32),
        )
    rules = ["--allowed-rules", "mesh", "mesh_window", "mesh_frame_count"]
    r = snakemake(work, "results/s1/mesh", *rules)
    assert r.returncode == 0, r.stdout + r.stderr
    for k in (0, 1):
        log = (work / f"logs/mesh_window/s1/{k}.log").read_text()
        assert f"window {k} ({3 - 2 * k} frames)" in log, log
        assert not (work / f"results/s1/mesh_windows/{k}").exists()  # temporary
    single = tmp_path / "single"
    run_mesh(fit, ingest, single, PARAMS, device="cpu", masks_dir=work / "results/s1/masks")
    out = tmp_path / "gathered"
    shutil.copytree(work / "results/s1/mesh", out, ignore=shutil.ignore_patterns(".snakemake*"))
    assert_same_meshes(single, out)


def test_status_and_progress_know_the_window_jobs(tmp_path):
    from surfphase.commands.run import OutputState, Progress, output_state

    # A window folder is temporary: removed once gathered, it counts as done.
    log = tmp_path / "logs/mesh_window/s1/0.log"
    log.parent.mkdir(parents=True)
    log.write_text("mesh s1: window 0 (3 frames) -> results/s1/mesh_windows/0\n")
    o = OutputState(
        path="results/s1/mesh_windows/0",
        rule="mesh_window",
        status="removed temp file",
        plan="no update",
        logs=["logs/mesh_window/s1/0.log"],
    )
    assert output_state(o, tmp_path) == "done"
    # The checkpoint job that counts the frames shows in `surfphase run`'s progress.
    out = io.StringIO()
    prog = Progress(tmp_path, out=out, live=False)
    info = {"jobid": 8, "rule": "mesh_frame_count", "wildcards": {"session": "s1"}}
    prog.feed({"event": "job_info", "time": 0.0, **info, "log": ["logs/mesh_frame_count/s1.log"]})
    prog.feed({"event": "job_finished", "time": 1.0, "jobid": 8})
    text = out.getvalue()
    assert "start  mesh_frame_count session=s1" in text
    assert "done   mesh_frame_count session=s1" in text
