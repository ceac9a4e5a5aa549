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


def write_mp4(path: Path, frames: int = 6, size: int = 32) -> None:
    """A small H.264 video (a bright square moving up)."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    with imageio.get_writer(path, fps=10, codec="libx264", macro_block_size=16) as w:
        for k in range(frames):
            img = np.full((size, size), 40, np.uint8)
            img[size - 8 - 3 * k : size - 3 * k, 12:20] = 220
            w.append_data(img)


def write_mesh(path: Path, speed: float) -> None:
    """A tetrahedron (metres) whose vertices all move at ``speed`` m/s upwards."""
    from surfphase.mesh.ply import speed_colors, write_mesh_ply

    v = np.array([[0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0], [0, 0, 1e-3]], float) + [0, 5e-3, 0]
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    vel = np.tile([0.0, speed, 0.0], (4, 1))
    write_mesh_ply(path, v, f, vel, speed_colors(np.full(4, speed), 0.4))


def make_campaign(work: Path) -> None:
    """Sheets for sessions s1 (with truth) and s2 (without), and their stage outputs."""
    cfg = work / "config"
    cfg.mkdir()
    text = (ROOT / "config" / "config.yaml").read_text().replace("results: results", "results: res")
    text = text.replace("mesh_frames: 4", "mesh_frames: 2")
    assert "mesh_frames: 2" in text
    # Stage outputs are made by hand up to stage 1; tests that want refinement on say so.
    text = text.replace("  enabled: true       # false", "  enabled: false      # false")
    assert "  enabled: false" in text
    (cfg / "config.yaml").write_text(text)
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
        for i in range(3):
            write_mesh(d / "mesh" / f"{i:06d}.ply", 0.1 * (i + 1))
        for v in ("orbit01", "orbit02"):
            write_mp4(d / "views" / f"{v}.mp4")
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
    cmd += ["mesh_snapshots", "report_videos"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    for s, paired in (("s1", 2), ("s2", 0)):
        rep = tmp_path / "res" / s / "report"
        assert (rep / "velocity.png").stat().st_size > 1000
        assert (rep / "metrics.html").is_file()
        assert len(list((rep / "masks").glob("*.png"))) == 4
        log = (tmp_path / "logs" / "plots" / f"{s}.log").read_text()
        assert f"2 bubbles ({paired} paired with the truth)" in log
        # 3 meshes, mesh_frames 2 in the config: the first and the last
        assert sorted(p.name for p in (rep / "meshes").glob("*.png")) == [
            "000000.png",
            "000002.png",
        ]
        assert sorted(p.name for p in (rep / "videos").glob("*.mp4")) == [
            "orbit01_raw.mp4",
            "orbit02_raw.mp4",
        ]
        assert (rep / "videos.html").read_text().count("data:video/mp4;base64,") == 2
    page = (tmp_path / target).read_text()
    # per session: velocity plot, 2 mesh snapshots, 4 overlays; 2 videos
    assert page.count("data:image/png;base64,") == 2 * (1 + 2 + 4)
    assert page.count("data:video/mp4;base64,") == 2 * 2

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
    assert "Meshes of session s1" in report and "Novel views of session s2" in report


def test_report_rules_dry_run(tmp_path: Path):
    """With refinement on, the report shows raw and refined videos of every orbit view;
    with videos and mesh snapshots switched off, neither rule is in the DAG."""
    make_campaign(tmp_path)
    over = tmp_path / "over.yaml"
    target = "res/s1/report/videos.html"
    cmd = [sys.executable, "-m", "snakemake", "-n", "-p", "-s", str(snakefile(tmp_path))]
    cmd += ["-d", str(tmp_path), "--cores", "1"]
    cmd += ["--configfile", str(tmp_path / "config" / "config.yaml"), str(over)]
    over.write_text("refine:\n  enabled: true\n")
    r = subprocess.run([*cmd, "--", target], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    job = r.stdout[r.stdout.index("rule report_videos:") :].split("\n\n")[0]
    for k in range(1, 12):
        assert f"res/s1/refine/orbit{k:02d}.mp4" in job
    assert "--views res/s1/views --refine res/s1/refine" in r.stdout
    over.write_text("report:\n  mesh_frames: 0\n  videos: false\n")
    r = subprocess.run(
        [*cmd, "--", "res/campaign/index.html"], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "rule campaign_page:" in r.stdout
    assert "rule mesh_snapshots:" not in r.stdout and "rule report_videos:" not in r.stdout
