"""The evaluate rules in a dry run: ablation fits per session × ablation, the meshes of
the compared fits, and the evaluate job's arguments for them (the fits and meshes
themselves are the fit and mesh stages', tested there)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from test_report_workflow import make_campaign, snakefile  # noqa: E402


def _dry_run(work: Path, over: str, target: str) -> subprocess.CompletedProcess:
    (work / "over.yaml").write_text(over)
    cmd = [sys.executable, "-m", "snakemake", "-n", "-p", "-s", str(snakefile(work))]
    cmd += ["-d", str(work), "--cores", "1"]
    cmd += ["--allowed-rules", "fit_ablation", "mesh_compare", "evaluate"]
    cmd += ["--configfile", str(work / "config" / "config.yaml"), str(work / "over.yaml")]
    return subprocess.run([*cmd, "--", target], capture_output=True, text=True, timeout=300)


def test_ablations_dry_run(tmp_path: Path):
    make_campaign(tmp_path)
    for s in ("s1", "s2"):
        for d in ("ingest", "masks", "mesh"):
            (tmp_path / "res" / s / d).mkdir(exist_ok=True)
        (tmp_path / "res" / s / "fit" / "surfels.npz").write_bytes(b"")
    targets = "res/s1/evaluate/metrics.json"
    over = "mesh:\n  surface: fused\n"  # the fits' own geometry: one mesh per fit
    over += "evaluate:\n  ablations: [no_sdf, no_guidance]\n  region_scale: 2.0\n"
    r = _dry_run(tmp_path, over, targets)
    assert r.returncode == 0, r.stdout + r.stderr
    jobs = [b for b in r.stdout.split("\n\n") if "rule fit_ablation:" in b]
    assert len(jobs) == 2
    for a, flag in (("no_sdf", '"use_sdf": false'), ("no_guidance", '"guidance": false')):
        job = next(j for j in jobs if f"res/s1/ablations/{a}/fit/surfels.npz" in j)
        assert flag in job and f"--checkpoint res/s1/ablations/{a}/fit.ckpt" in job
    ev = next(b for b in r.stdout.split("\n\n") if "rule evaluate:" in b)
    assert "--ablation no_sdf=res/s1/ablations/no_sdf/fit" in ev
    assert "--ablation no_guidance=res/s1/ablations/no_guidance/fit" in ev
    assert "--region-scale 2.0" in ev and "--fit-stage1" not in ev
    # with ground truth, each compared fit is meshed and its Chamfer scored
    meshes = [b for b in r.stdout.split("\n\n") if "rule mesh_compare:" in b]
    assert len(meshes) == 2
    for a in ("no_sdf", "no_guidance"):
        assert f"--compare-meshes {a}=res/s1/compare/{a}/mesh" in ev
        job = next(j for j in meshes if f"res/s1/compare/{a}/mesh" in j)
        assert f"--fit $(dirname res/s1/ablations/{a}/fit/surfels.npz)" in job
    r = _dry_run(tmp_path, over + "  compare_meshes: false\n", targets)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "rule mesh_compare:" not in r.stdout and "--compare-meshes" not in r.stdout
    # the hull surface (the default) is made from the masks alone: no mesh per fit
    r = _dry_run(tmp_path, over.replace("surface: fused", "surface: hull"), targets)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "rule mesh_compare:" not in r.stdout and "--compare-meshes" not in r.stdout
    # refinement on: the final fit is stage 2, stage 1 is scored beside it
    (tmp_path / "res" / "s1" / "fit2").mkdir()
    (tmp_path / "res" / "s1" / "fit2" / "surfels.npz").write_bytes(b"")
    r = _dry_run(tmp_path, "refine:\n  enabled: true\nmesh:\n  surface: fused\n", targets)
    assert r.returncode == 0, r.stdout + r.stderr
    ev = next(b for b in r.stdout.split("\n\n") if "rule evaluate:" in b)
    assert "--fit $(dirname res/s1/fit2/surfels.npz)" in ev
    assert "--fit-stage1 res/s1/fit" in ev and "--ablation" not in ev
    assert "--compare-meshes stage1=res/s1/compare/stage1/mesh" in ev
    # an unknown ablation is refused by the config schema, naming it
    r = _dry_run(tmp_path, "evaluate:\n  ablations: [no_magic]\n", targets)
    assert r.returncode != 0 and "no_magic" in r.stdout + r.stderr
