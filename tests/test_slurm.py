"""The demo campaign through SLURM equals a local run.

Needs a running SLURM cluster (CI starts a one-node one with ``scripts/slurm/start.sh``
before the tests); skipped otherwise. The tiny synthetic campaign goes through the
stages that feed the fit (calibrate, ingest) twice: on this machine with the local
profile, and with ``surfphase run --cluster slurm`` (the project's SLURM profile, the
campaign's account/partition). The jobs must appear in SLURM's job-completion record
(``/var/log/slurm/jobcomp.log``, written by slurmctld) with the campaign as working
folder, and every result file must equal the local one.
"""

from __future__ import annotations

import functools
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from surfphase.cli import main

JOBCOMP = Path("/var/log/slurm/jobcomp.log")
STAGES = ["calibrate", "ingest"]


@functools.cache
def slurm_ready() -> str:
    """Why SLURM cannot be used here ('' when it can)."""
    if not shutil.which("sinfo") or not shutil.which("sbatch"):
        return "SLURM is not installed (CI runs scripts/slurm/start.sh first)"
    try:
        res = subprocess.run(
            ["sinfo", "-h", "-o", "%t"], capture_output=True, text=True, timeout=20
        )
    except subprocess.TimeoutExpired:
        return "sinfo timed out: slurmctld not running"
    states = res.stdout.split()
    if res.returncode != 0 or not any(s.startswith(("idle", "mix")) for s in states):
        return f"no idle SLURM node (sinfo: {res.stdout.strip() or res.stderr.strip()})"
    if not JOBCOMP.parent.is_dir():
        return f"{JOBCOMP}: no job-completion record (start SLURM with scripts/slurm/start.sh)"
    return ""


# CI sets SURFPHASE_REQUIRE_SLURM=1 after starting SLURM: there, a cluster that is not
# ready fails the test instead of skipping it.
REQUIRED = os.environ.get("SURFPHASE_REQUIRE_SLURM") == "1"
pytestmark = pytest.mark.skipif(
    not REQUIRED and bool(slurm_ready()), reason=slurm_ready() or "SLURM ready"
)


def make_campaign(root: Path, data: Path, extra: str = "") -> Path:
    (root / "config").mkdir(parents=True)
    (root / "config" / "config.yaml").write_text(
        f"sessions: {data / 'sessions.tsv'}\nrigs: {data / 'rigs.tsv'}\nresults: results\n"
        "threads: 1\ningest:\n  scale: 0.25\n" + extra
    )
    return root


def normalised(path: Path, camp: Path):
    """A result file's content, with the campaign's own folder name taken out."""
    if path.suffix == ".npy":
        return np.load(path)
    if path.suffix == ".npz":
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    raw = path.read_bytes()
    if path.suffix in (".json", ".csv", ".txt", ".tsv", ".yaml"):
        text = raw.decode().replace(str(camp), "<campaign>")
        return json.loads(text) if path.suffix == ".json" else text
    return raw


def assert_same(a, b, name):
    if isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=name)
    elif isinstance(a, dict) and a and all(isinstance(v, np.ndarray) for v in a.values()):
        assert a.keys() == b.keys(), name
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{name}:{k}")
    else:
        assert a == b, name


def test_campaign_through_slurm_equals_local(tmp_path, monkeypatch):
    # Known sources of run-to-run float differences, held equal in both runs: OpenCV's
    # thread pool (calibration results vary in the last digits with >1 thread) and the
    # threads Snakemake gives a job (it sets OMP_NUM_THREADS from them). SLURM jobs get
    # this environment too (sbatch --export=ALL).
    if slurm_ready():
        pytest.fail(f"SURFPHASE_REQUIRE_SLURM=1 but {slurm_ready()}")
    monkeypatch.setenv("OPENCV_FOR_THREADS_NUM", "1")
    one_thread = "--max-threads 1"
    data = tmp_path / "data"
    assert main(["synth", "--preset", "tiny", "--out", str(data)]) == 0
    local = make_campaign(tmp_path / "local", data)
    cluster = make_campaign(
        tmp_path / "cluster", data, "slurm:\n  partition: debug\n  gpu_partition: debug\n"
    )
    run_local = ["run", "--campaign", str(local), "--cores", "2", "--snakemake-args", one_thread]
    assert main([*run_local, *STAGES]) == 0

    before = JOBCOMP.read_text() if JOBCOMP.exists() else ""
    smk = (
        "--slurm-status-command squeue --slurm-init-seconds-before-status-checks 2 "
        f"--slurm-keep-successful-logs {one_thread}"
    )
    args = ["run", "--campaign", str(cluster), "--cluster", "slurm", "--jobs", "4"]
    assert main([*args, "--snakemake-args", smk, *STAGES]) == 0

    # SLURM ran the jobs: slurmctld's completion record names the campaign folder, and
    # Snakemake kept one SLURM log per job under the rule's name.
    mine = [
        ln for ln in JOBCOMP.read_text()[len(before) :].splitlines() if f"WorkDir={cluster} " in ln
    ]
    slurm_dir = cluster / ".snakemake" / "slurm_logs"  # rule_<rule>/<wildcards>/<jobid>.log
    slurm_logs = sorted(slurm_dir.rglob("*.log"))
    rules = sorted({p.relative_to(slurm_dir).parts[0] for p in slurm_logs})
    assert rules == ["rule_calibrate", "rule_ingest"], slurm_logs
    assert len(mine) == len(slurm_logs) >= 2
    assert all("JobState=COMPLETED" in ln and "Partition=debug" in ln for ln in mine), mine
    ids = {re.search(r"JobId=(\d+)", ln).group(1) for ln in mine}
    assert ids == {p.stem for p in slurm_logs}

    # Same results as the local run, file by file.
    files = sorted(p.relative_to(local) for p in (local / "results").rglob("*") if p.is_file())
    assert files, "the local run wrote nothing"
    assert files == sorted(
        p.relative_to(cluster) for p in (cluster / "results").rglob("*") if p.is_file()
    )
    for rel in files:
        assert_same(normalised(local / rel, local), normalised(cluster / rel, cluster), str(rel))
