"""The SLURM profile names only rules of the workflow, and gives each its resources.

Snakemake silently ignores a ``set-resources``/``set-threads`` key that names no rule,
so a renamed rule would fall back to the default 4 GB / 60 min without a GPU. The rules
are Snakemake's own list (``--list-rules``) in every configuration that changes the
rule set: refinement on and off, mesh windows on and off, ablations on.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from surfphase.commands.run import slurm_profile

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "workflow" / "profiles" / "slurm"
VARIANTS = {
    "refine on, one mesh job": "refine: {enabled: true}\nmesh: {window: 0}\n",
    "refine off, mesh windows": "refine: {enabled: false}\nmesh: {window: 2}\n",
    "ablations": "evaluate: {ablations: [no_sdf]}\n",
}


def list_rules(work: Path, variant: str) -> set[str]:
    extra = work / "variant.yaml"
    extra.write_text(variant)
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work)]
    r = subprocess.run(
        [*cmd, "--list-rules", "--configfile", str(extra)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return {m.group(1) for ln in r.stdout.splitlines() if (m := re.match(r"^(\w+)\b", ln))}


def local_rules() -> set[str]:
    """Rules that run on the submitting host (``localrule: True``): no SLURM resources."""
    names = set()
    for f in (ROOT / "workflow" / "rules").glob("*.smk"):
        blocks = re.split(r"^\s*(?:rule|checkpoint) (\w+):", f.read_text(), flags=re.M)
        for name, body in zip(blocks[1::2], blocks[2::2], strict=True):
            if re.search(r"^\s*localrule:\s*True", body, flags=re.M):
                names.add(name)
    return names


@pytest.fixture(scope="module")
def all_rules(tmp_path_factory) -> set[str]:
    work = tmp_path_factory.mktemp("rules")
    shutil.copytree(ROOT / "config", work / "config")
    rules: set[str] = set()
    for variant in VARIANTS.values():
        rules |= list_rules(work, variant)
    return rules


def test_profile_keys_are_rules_and_every_job_rule_has_resources(all_rules):
    prof = yaml.safe_load((PROFILE / "config.yaml").read_text())
    assert {"fit", "fit_stage2", "mesh_window", "campaign_page"} <= all_rules  # sanity
    for section in ("set-resources", "set-threads"):
        unknown = set(prof[section]) - all_rules
        assert not unknown, f"{section} names no rule of the workflow: {sorted(unknown)}"
    missing = all_rules - set(prof["set-resources"]) - local_rules() - {"all"}
    assert not missing, f"rules left to the default resources: {sorted(missing)}"


def test_final_fit_gets_the_fits_resources():
    res = yaml.safe_load((PROFILE / "config.yaml").read_text())["set-resources"]
    assert res["fit_stage2"] == res["fit"]
    assert res["fit_ablation"] == res["fit"]
    assert res["fit"]["gpu"] == 1


@pytest.mark.parametrize("device", ["cpu", "auto", "cuda"])
def test_campaign_profile_requests_gpus_unless_device_cpu(tmp_path: Path, device: str):
    camp = tmp_path / "camp"
    cfg = {"partition": "cpu", "gpu_partition": "gpu", "account": "lab"}
    out = slurm_profile(camp, PROFILE, cfg, device)
    prof = yaml.safe_load((out / "config.yaml").read_text())
    base = yaml.safe_load((PROFILE / "config.yaml").read_text())["set-resources"]
    gpu_rules = {r for r, v in base.items() if v.get("gpu")}
    assert {"fit", "fit_stage2", "refine", "train_prior"} <= gpu_rules
    res = prof["set-resources"]
    assert prof["default-resources"]["slurm_partition"] == "cpu"
    assert prof["default-resources"]["slurm_account"] == "lab"
    for rule in gpu_rules:
        if device == "cpu":
            assert "gpu" not in res[rule] and "slurm_partition" not in res[rule], rule
        else:
            assert res[rule]["gpu"] == 1 and res[rule]["slurm_partition"] == "gpu", rule
        # memory and time are the project's either way
        assert res[rule]["mem_mb"] == base[rule]["mem_mb"]
    assert not any("gpu" in v for r, v in res.items() if r not in gpu_rules)


def test_run_cluster_slurm_reads_device_from_the_campaign(tmp_path: Path, capsys):
    from surfphase.cli import main

    camp = tmp_path / "camp"
    (camp / "config").mkdir(parents=True)
    (camp / "config" / "config.yaml").write_text("device: cpu\nslurm:\n  partition: short\n")
    assert main(["run", "--campaign", str(camp), "--cluster", "slurm", "--print-command"]) == 0
    written = camp / ".surfphase" / "profiles" / "slurm" / "config.yaml"
    assert str(written.parent) in capsys.readouterr().out
    res = yaml.safe_load(written.read_text())["set-resources"]
    assert res["fit"]["mem_mb"] and not any("gpu" in v for v in res.values())
