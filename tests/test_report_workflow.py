"""The report rules on a small campaign: per-session figures, the campaign page and
Snakemake's HTML report, from stage outputs written here (the earlier stages' rules are
left out with ``--allowed-rules``, so nothing but the report runs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
FPS = 1000.0


def snakefile(work: Path) -> Path:
    """The project's Snakefile, with the report rules included if it lacks them."""
    main = ROOT / "Snakefile"
    if "workflow/rules/report.smk" in main.read_text():
        return main
    wrapper = work / "Snakefile.report"
    wrapper.write_text(
        f'include: "{main}"\ninclude: "{ROOT / "workflow" / "rules" / "report.smk"}"\n'
    )
    return wrapper


def bubbles(frames: range, bubble_ids: list[int], vy: float) -> pd.DataFrame:
    """Bubbles rising at ``vy`` m/s, 3 mm apart in x."""
    rows = []
    for b in bubble_ids:
        for f in frames:
            t = f / FPS
            rows.append(dict(frame=f, time_s=t, bubble=b, x=3e-3 * b, y=vy * t, z=0.0))
            rows[-1].update(vx=0.0, vy=vy, vz=0.0)
    return pd.DataFrame(rows)


def make_campaign(work: Path) -> None:
    """Sheets for sessions s1 (with truth) and s2 (without), and their stage outputs."""
    cfg = work / "config"
    cfg.mkdir()
    (cfg / "config.yaml").write_text(
        (ROOT / "config" / "config.yaml").read_text().replace("results: results", "results: res")
    )
    (cfg / "rigs.tsv").write_text("rig\tboard\tcam0\tcam1\nr1\tboard.yaml\tcal/cam0\tcal/cam1\n")
    (cfg / "sessions.tsv").write_text(
        "session\trig\tfps\tframes\tcam0\tcam1\tgt\n"
        f"s1\tr1\t{FPS:g}\t\tv/s1/cam0\tv/s1/cam1\tgt1\n"
        f"s2\tr1\t{FPS:g}\t\tv/s2/cam0\tv/s2/cam1\t\n"
    )
    (cfg / "gt1").mkdir()
    bubbles(range(12), [7, 8], 0.3).to_csv(cfg / "gt1" / "bubbles.csv", index=False)
    rows = []
    for s in ("s1", "s2"):
        d = work / "res" / s
        for sub in ("fit", "evaluate", "masks/overlays"):
            (d / sub).mkdir(parents=True)
        bubbles(range(10), [7, 8], 0.28).to_csv(d / "fit" / "bubbles.csv", index=False)
        bubbles(range(10), [7], 0.25).to_csv(d / "evaluate" / "baseline_bubbles.csv", index=False)
        m = {"session": s, "fps": FPS, "velocity": {"method": {"relative_error": 0.07}}}
        (d / "evaluate" / "metrics.json").write_text(json.dumps(m))
        for i in range(6):
            png = d / "masks" / "overlays" / f"frame_{i:05d}.png"
            png.write_bytes(b"\x89PNG\r\n\x1a\n" + np.full(64, i, np.uint8).tobytes())
        rows.append({"session": s, "velocity.method.relative_error": 0.07})
    (work / "res" / "campaign").mkdir()
    pd.DataFrame(rows).to_csv(work / "res" / "campaign" / "metrics.csv", index=False)


def test_report_rules_and_snakemake_report(tmp_path: Path):
    make_campaign(tmp_path)
    target = "res/campaign/index.html"
    # the target first: --allowed-rules takes every word after it
    cmd = [sys.executable, "-m", "snakemake", target, "-s", str(snakefile(tmp_path))]
    cmd += ["-d", str(tmp_path), "--cores", "2", "--allowed-rules", "plots", "campaign_page"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    for s, paired in (("s1", 2), ("s2", 0)):
        rep = tmp_path / "res" / s / "report"
        assert (rep / "velocity.png").stat().st_size > 1000
        assert (rep / "metrics.html").is_file()
        assert len(list((rep / "masks").glob("*.png"))) == 4
        log = (tmp_path / "logs" / "plots" / f"{s}.log").read_text()
        assert f"2 bubbles ({paired} paired with the truth)" in log
    page = (tmp_path / target).read_text()
    assert page.count("data:image/png;base64,") == 2 * (1 + 4)

    r = subprocess.run(
        [*cmd[:3], "--report", "res/report.html", *cmd[3:]],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    report = (tmp_path / "res" / "report.html").read_text()
    assert "Bubble velocities of session s1" in report  # caption, wildcards filled in
    assert "Bubble velocities of session s2" in report
