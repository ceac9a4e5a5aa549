"""The workflow's Snakefile, the campaign folder and its config, the Snakemake command of
a campaign and the campaign's SLURM profile."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import yaml

from surfphase.io import atomic_write_text

PROFILES = ("local", "slurm")


def project_root() -> Path:
    """The folder holding the Snakefile and workflow/ (the source tree of this package)."""
    return Path(__file__).resolve().parents[2]


def find_snakefile(given: str | None = None) -> Path:
    """The workflow's Snakefile: ``given``, ``$SURFPHASE_SNAKEFILE`` or the project's."""
    path = Path(given or os.environ.get("SURFPHASE_SNAKEFILE") or project_root() / "Snakefile")
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: Snakefile not found (install surfphase from its source tree, "
            "or give --snakefile / set SURFPHASE_SNAKEFILE)"
        )
    return path.resolve()


def campaign_dir(path: str | Path) -> Path:
    """A campaign folder: one that holds ``config/config.yaml``."""
    camp = Path(path).resolve()
    if not (camp / "config" / "config.yaml").is_file():
        raise FileNotFoundError(
            f"{camp / 'config' / 'config.yaml'}: not found; a campaign folder holds "
            "config/config.yaml (create one with `surfphase new-campaign`)"
        )
    return camp


def read_config(camp: Path) -> dict:
    path = camp / "config" / "config.yaml"
    try:
        cfg = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(cfg, dict):
        raise ValueError(f"{path}: must be a YAML mapping")
    return cfg


def snakemake_base(snakefile: Path, camp: Path) -> list[str]:
    """The Snakemake command for ``camp`` (the Python running surfphase runs Snakemake)."""
    return [sys.executable, "-m", "snakemake", "-s", str(snakefile), "--directory", str(camp)]


def slurm_profile(
    camp: Path, base_profile: Path, slurm_cfg: dict | None, device: str = "auto"
) -> Path:
    """Write the campaign's SLURM profile: the project's plus account and partitions.

    ``slurm_cfg`` is the ``slurm:`` mapping of the campaign config (``account``,
    ``partition``, ``gpu_partition``; all optional). GPU rules are those with a ``gpu``
    resource in the project's profile; with ``device`` ``"cpu"`` (the campaign config's
    ``device``) they request no GPU and run on ``partition``. Returns the folder of the
    written profile, ``CAMPAIGN/.surfphase/profiles/slurm``.
    """
    prof = yaml.safe_load((base_profile / "config.yaml").read_text()) or {}
    slurm_cfg = slurm_cfg or {}
    unknown = set(slurm_cfg) - {"account", "partition", "gpu_partition"}
    if unknown:
        raise ValueError(
            f"{camp / 'config' / 'config.yaml'}: unknown slurm keys {sorted(unknown)} "
            "(account, partition, gpu_partition)"
        )
    defaults = dict(prof.get("default-resources") or {})
    if slurm_cfg.get("account"):
        defaults["slurm_account"] = str(slurm_cfg["account"])
    if slurm_cfg.get("partition"):
        defaults["slurm_partition"] = str(slurm_cfg["partition"])
    prof["default-resources"] = defaults
    gpu_part = slurm_cfg.get("gpu_partition")
    for res in (prof.get("set-resources") or {}).values():
        if device == "cpu":
            res.pop("gpu", None)  # the jobs run with --device cpu: a GPU would sit idle
        elif gpu_part and res.get("gpu"):
            res["slurm_partition"] = str(gpu_part)
    out = camp / ".surfphase" / "profiles" / "slurm"
    header = (
        f"# Written by `surfphase run --cluster slurm` from {base_profile / 'config.yaml'}\n"
        "# and the slurm: section of config/config.yaml. Edit those, not this file.\n"
    )
    atomic_write_text(out / "config.yaml", header + yaml.safe_dump(prof, sort_keys=False))
    return out


def tail_lines(text: str, n: int) -> str:
    return "\n".join(text.strip().splitlines()[-n:])
