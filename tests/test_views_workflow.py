"""The workflow plans one prior, one render per session and one refine job per session × view."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import yaml
from test_workflow_sheets import snakemake

ROOT = Path(__file__).resolve().parents[1]

SETTINGS = {
    "prior": {"backend": "embedded", "clips": "clips", "embedded": {"steps": 5}},
    # Not the defaults (0.2, 0.35, 4-8, 0): a workflow that ignored them would fail.
    "refine": {"enabled": False, "strength_near": 0.15, "strength_far": 0.45,
               "far_views": [3, 4, 5, 9], "seed": 7},
}  # fmt: skip


def job_counts(text: str) -> dict[str, int]:
    """``rule: count`` rows of Snakemake's job table."""
    out = {}
    for line in text.splitlines():
        m = re.fullmatch(r"\s*([a-z_0-9]+)\s+(\d+)\s*", line)
        if m and m.group(1) != "total":
            out[m.group(1)] = int(m.group(2))
    return out


def test_dry_run_has_one_refine_job_per_session_and_view(tmp_path):
    shutil.copytree(ROOT / "config", tmp_path / "config")
    cfg = tmp_path / "config" / "config.yaml"
    cfg.write_text(yaml.safe_dump({**yaml.safe_load(cfg.read_text()), **SETTINGS}))
    (tmp_path / "clips").mkdir()
    targets = [f"results/{s}/refine/orbit{k:02d}.npy" for s in ("session01", "session02")
               for k in range(1, 12)]  # fmt: skip
    r = snakemake(tmp_path, "-n", "-p", *targets)
    assert r.returncode == 0, r.stdout + r.stderr
    out = r.stdout + r.stderr
    counts = job_counts(out)
    assert counts["refine"] == 22 and counts["render_views"] == 2 and counts["train_prior"] == 1
    # strengths from the config by view number: far views 4–8, near the others
    for k in range(1, 12):
        s = "0.45" if k in (3, 4, 5, 9) else "0.15"
        assert re.search(rf"--view orbit{k:02d} --strength {s} --seed 7", out), k
    assert "render-views --fit results/session01/fit/surfels.npz" in out
    assert re.search(r"train-prior --clips clips --out results/prior --backend embedded", out)
