"""`--sdm conda`: the jobs call the conda environment's python, not the one running
Snakemake (which would make the environment a no-op).

No conda is installed here, so a stand-in ``conda`` on PATH answers Snakemake's version
and configuration checks; a dry run creates no environment and prints each job's
command, which is what is checked. The environment file itself is checked for what it
must hold: the pinned torch and this project.
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
FAKE_CONDA = """#!/bin/sh
case "$1" in
  --version) echo "conda 24.7.1";;
  info) echo '{"conda_prefix": "%(p)s", "root_prefix": "%(p)s", "platform": "linux-64",
    "conda_version": "24.7.1", "envs_dirs": ["%(p)s/envs"], "pkgs_dirs": ["%(p)s/pkgs"]}';;
  config) echo '{"get": {"channel_priority": "strict"}}';;
  *) echo '{}';;
esac
"""


def _dry_run(tmp_path: Path, *extra: str) -> str:
    conda = tmp_path / "bin" / "conda"
    conda.parent.mkdir()
    conda.write_text(FAKE_CONDA % {"p": tmp_path})
    conda.chmod(conda.stat().st_mode | stat.S_IEXEC)
    env = {**os.environ, "PATH": f"{conda.parent}{os.pathsep}{os.environ['PATH']}"}
    work = tmp_path / "work"  # the demo's config, in a working folder of this test's own
    shutil.copytree(ROOT / "config", work / "config")
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work),
           "-n", "-p", "--cores", "1", "results/session01/ingest", *extra]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    return res.stdout + res.stderr


def test_conda_jobs_call_the_environments_python(tmp_path):
    out = _dry_run(tmp_path, "--sdm", "conda")
    assert "envs/surfphase.yaml will be created" in out
    shells = [ln for ln in out.splitlines() if "-m surfphase ingest" in ln]
    assert sys.executable not in "\n".join(shells)
    assert "python -m surfphase ingest" in shells[0]


def test_without_conda_jobs_call_this_python(tmp_path):
    out = _dry_run(tmp_path)
    assert f"{sys.executable} -m surfphase ingest" in out


def test_environment_file_installs_the_project_with_the_pinned_torch():
    env = yaml.safe_load((ROOT / "envs" / "surfphase.yaml").read_text())
    pip = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict))
    assert "torch==2.13.0" in pip
    # pip runs beside the file: "-e ../" is the project root (its pyproject.toml).
    target = next(p for p in pip if p.startswith("-e "))[3:].strip()
    assert (ROOT / "envs" / target / "pyproject.toml").resolve() == ROOT / "pyproject.toml"
    py = next(d for d in env["dependencies"] if isinstance(d, str) and d.startswith("python"))
    assert py.split("=")[1] >= "3.11"
