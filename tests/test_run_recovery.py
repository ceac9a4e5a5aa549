"""`surfphase run` / `status` after a failure: a killed Snakemake, a killed run, long
failure lines (the workflow-level tests are in test_workflow_run.py)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from surfphase.commands import run as runmod


def test_stream_says_snakemake_was_killed(tmp_path: Path):
    cmd = [sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"]
    out = io.StringIO()
    assert runmod.stream(cmd, tmp_path, verbose=False, out=out) == -9
    text = out.getvalue()
    assert "Snakemake was killed (SIGKILL)" in text
    assert "Run `surfphase run` again to resume" in text


def test_long_failure_lines_keep_the_file_name(tmp_path: Path):
    """A log's last line of 300 characters ending with the file at fault is wrapped in
    full, never cut (it used to be cut at ~175 characters)."""
    bad = "/data/lab/2026-11-30/very/long/folder/name/of/the/recording/session02/cam1.tif"
    last = "ValueError: session02: camera cam1: " + "frame count disagrees " * 9 + "in " + bad
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "ingest.log").write_text("starting\n" + last + "\n")
    table = {
        "session02": {"ingest": {"state": "failed", "outputs": 1, "logs": ["logs/ingest.log"]}}
    }
    text = runmod.format_status(table, tmp_path)
    assert bad in text
    failure = text[text.index("failed: ingest session02") :]
    assert " ".join(ln.strip(" |") for ln in failure.splitlines()).endswith(last)
    assert max(len(ln) for ln in failure.splitlines()) <= 100
    assert any(ln.endswith(bad) for ln in failure.splitlines())  # the path is not broken
    # Short ones stay on one line.
    assert runmod.failure_lines("failed: x s1: log", "bad video") == [
        "failed: x s1: log  | bad video"
    ]


def test_middle_cut_keeps_both_ends():
    text = "start " + "m" * 2000 + " end/of/it.tif"
    cut = runmod.middle_cut(text, 100)
    assert len(cut) == 100 and cut.startswith("start ") and cut.endswith(" end/of/it.tif")
    assert runmod.middle_cut("short", 100) == "short"


def test_lock_of_a_live_process_is_not_stale(tmp_path: Path):
    """A process running snakemake with the campaign as working folder holds the lock."""
    camp = tmp_path / "camp"
    (camp / ".snakemake" / "locks").mkdir(parents=True)
    (camp / ".snakemake" / "locks" / "0.input.lock").write_text("x")
    fake = tmp_path / "snakemake"  # a stand-in named like Snakemake's entry point
    fake.write_text("import time\ntime.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, str(fake)], cwd=camp)
    try:
        deadline = time.time() + 30
        while time.time() < deadline and proc.pid not in runmod.snakemake_processes(camp):
            time.sleep(0.1)
        assert runmod.lock_state(camp) == {"locked": True, "live": [proc.pid], "host": ""}
        assert "is running in this campaign (pid" in runmod.lock_note(camp)[0]
        out = io.StringIO()
        assert not runmod.release_stale_lock(Path("Snakefile"), camp, out=out)
        assert f"already running in this campaign (pid {proc.pid})" in out.getvalue()
    finally:
        proc.kill()
        proc.wait()
    assert runmod.lock_state(camp)["live"] == []
    assert "stale lock" in runmod.lock_note(camp)[0]


def test_run_record_of_a_dead_process_means_killed(tmp_path: Path):
    camp = tmp_path / "camp"
    path = runmod.record_run(camp)
    info = json.loads(path.read_text())
    assert info["pid"] == os.getpid()
    assert runmod.previous_run_killed(camp) == {}  # this process is alive
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    path.write_text(json.dumps({**info, "pid": dead.pid}))
    assert runmod.previous_run_killed(camp)["pid"] == dead.pid
    path.write_text(json.dumps({**info, "pid": dead.pid, "host": "elsewhere"}))
    assert runmod.previous_run_killed(camp) == {}  # another host: cannot tell


def test_file_targets_are_only_those_files(tmp_path: Path):
    """`surfphase run results/s1/ingest` asks for that output, not the whole campaign."""
    camp = tmp_path / "camp"
    (camp / "config").mkdir(parents=True)
    (camp / "config" / "config.yaml").write_text("results: results\n")
    rows = [
        runmod.OutputState("results/s1/ingest", "ingest", "missing", "update pending"),
        runmod.OutputState("results/s1/fit/x.npz", "fit", "missing", "update pending"),
    ]
    target = ["results/s1/ingest"]
    assert runmod.resolve_targets(Path("Snakefile"), camp, target, [], rows) == target
    both = runmod.resolve_targets(Path("Snakefile"), camp, ["fit", *target], [], rows)
    assert both == ["results/s1/fit/x.npz", *target]
