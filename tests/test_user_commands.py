"""`surfphase new-campaign`, `surfphase run` and `surfphase status`.

new-campaign is checked on MRAW and CINE files written here, then the project's own
Snakefile reads the written campaign (`surfphase status`, a Snakemake DAG). run/status
are checked on a toy workflow (three sessions, one fails) so they do not wait for the
stages' own code; the expected states come from the toy's known behaviour.
"""

from __future__ import annotations

import io
import shutil
import struct
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from surfphase.cli import main
from surfphase.commands import run as runmod
from surfphase.commands.new_campaign import find_videos, new_campaign

ROOT = Path(__file__).resolve().parents[1]


def write_cine(path: Path, n: int, h: int, w: int, fps: int) -> None:
    """A minimal 8-bit CINE file (layout as in tests/test_labformats.py)."""
    stride = (w + 3) // 4 * 4
    setup = bytearray(12432)
    struct.pack_into("<H", setup, 142, len(setup) & 0xFFFF)
    struct.pack_into("<I", setup, 768, fps)
    struct.pack_into("<I", setup, 896, 8)
    off_offsets = 44 + 40 + len(setup)
    first = off_offsets + 8 * n
    head = struct.pack("<2sHHHiIiIIIIII", b"CI", 44, 0, 1, 0, n, 0, n, 44, 84, off_offsets, 0, 0)
    bmp = struct.pack("<IiiHHIIiiII", 40, w, h, 1, 8, 0, stride * h, 0, 0, 0, 0)
    with open(path, "wb") as f:
        f.write(head + bmp + bytes(setup))
        f.write(struct.pack(f"<{n}q", *[first + i * (8 + stride * h) for i in range(n)]))
        for i in range(n):
            f.write(struct.pack("<II", 8, stride * h) + bytes([i]) * (stride * h))


@pytest.fixture
def lab_videos(tmp_path):
    """Session run01 as Photron MRAW (5000 fps), run02 as Phantom CINE (2500 fps)."""
    pymraw = pytest.importorskip("pyMRAW")
    vid = tmp_path / "videos"
    vid.mkdir()
    data = np.arange(3 * 4 * 6, dtype=np.uint16).reshape(3, 4, 6)
    for cam in ("left", "right"):
        pymraw.save_mraw(
            data, str(vid / f"run01_{cam}.cih"), bit_depth=16, info_dict={"Record Rate(fps)": 5000}
        )
        (vid / "run02").mkdir(exist_ok=True)
        write_cine(vid / "run02" / f"{cam}.cine", 3, 4, 6, fps=2500)
        (vid / "calib" / cam).mkdir(parents=True)
        (vid / "calib" / cam / "pose000.png").write_bytes(b"")
    return vid


def test_find_videos_naming_rules(tmp_path, lab_videos):
    found = find_videos(lab_videos)
    assert sorted(found) == ["run01", "run02"]
    assert found["run01"]["left"].name == "run01_left.cih"  # the header, not the .mraw
    assert found["run02"]["right"].name == "right.cine"
    photron = tmp_path / "photron"
    photron.mkdir()
    for name in ("C001H001S0001.cihx", "C001H001S0001.mraw", "C002H001S0001.cihx"):
        (photron / name).write_bytes(b"")
    assert find_videos(photron) == {
        "S0001": {
            "C001H001": photron / "C001H001S0001.cihx",
            "C002H001": photron / "C002H001S0001.cihx",
        }
    }
    (photron / "lonely.avi").write_bytes(b"")
    with pytest.raises(ValueError, match="lonely.avi: cannot tell session and camera"):
        find_videos(photron)


def test_new_campaign_from_lab_files_runs_in_the_workflow(tmp_path, lab_videos, capsys):
    camp = tmp_path / "campaign"
    assert main(["new-campaign", "--videos", str(lab_videos), "--out", str(camp)]) == 0
    printed = capsys.readouterr().out
    assert f"surfphase run --campaign {camp}" in printed
    sheet = pd.read_csv(camp / "config" / "sessions.tsv", sep="\t", comment="#", dtype=str)
    assert sheet["session"].tolist() == ["run01", "run02"]
    assert sheet["fps"].tolist() == ["5000", "2500"]  # from the CIH and CINE headers
    assert (camp / "config" / sheet.loc[0, "cam0"]).resolve() == lab_videos / "run01_left.cih"
    assert (camp / "config" / sheet.loc[1, "cam1"]).resolve() == lab_videos / "run02" / "right.cine"
    assert "cam0 = left, cam1 = right" in (camp / "config" / "sessions.tsv").read_text()
    rigs = pd.read_csv(camp / "config" / "rigs.tsv", sep="\t", comment="#", dtype=str)
    assert (camp / "config" / rigs.loc[0, "cam1"]).resolve() == lab_videos / "calib" / "right"
    board = yaml.safe_load((camp / "config" / "board.yaml").read_text())
    assert board == {
        "squares_x": 5,
        "squares_y": 7,
        "square_length": 0.004,
        "marker_length": 0.003,
        "dictionary": "DICT_4X4_50",
    }
    # The project's workflow accepts the campaign: everything is still to do.
    assert main(["status", "--campaign", str(camp), "--json"]) == 0
    table = yaml.safe_load(capsys.readouterr().out)
    assert table["calib/rig01"]["calibrate"]["state"] == "pending"
    assert {table[s]["ingest"]["state"] for s in ("run01", "run02")} == {"pending"}
    with pytest.raises(ValueError, match="already holds a campaign"):
        new_campaign(lab_videos, camp)


def test_new_campaign_errors(tmp_path, lab_videos):
    (lab_videos / "run01_right.mraw").unlink()
    (lab_videos / "run01_right.cih").unlink()
    with pytest.raises(ValueError, match="session run01: no video for camera"):
        new_campaign(lab_videos, tmp_path / "a")
    imgs = tmp_path / "imgs"
    for cam in ("cam0", "cam1"):
        (imgs / "s1" / cam).mkdir(parents=True)
        (imgs / "s1" / cam / "000.png").write_bytes(b"")
    with pytest.raises(ValueError, match="session s1: no frame rate.*give --fps"):
        new_campaign(imgs, tmp_path / "b")
    info = new_campaign(imgs, tmp_path / "b", fps=1500)
    assert info["fps"] == {"s1": 1500.0}
    assert (tmp_path / "b" / "calib" / "cam1").is_dir()  # template folders to fill


# --- run / status on a toy workflow ---------------------------------------------------------

TOY = """\
configfile: "config/config.yaml"
SESSIONS = ["s1", "s2", "s3"]
rule all:
    input: expand("results/{s}/fit/done.txt", s=SESSIONS)
rule ingest:
    output: "results/{s}/ingest/frames.txt"
    log: "logs/ingest/{s}.log"
    shell: "echo reading > {log}; if [ {wildcards.s} = s2 ]; then echo 'bad video' >> {log}; exit 1; fi; echo {wildcards.s} > {output}"
rule fit:
    input: "results/{s}/ingest/frames.txt"
    output: "results/{s}/fit/done.txt"
    log: "logs/fit/{s}.log"
    shell: "cat {input} > {output} 2> {log}"
"""


@pytest.fixture
def toy(tmp_path):
    proj = tmp_path / "project"
    shutil.copytree(ROOT / "workflow" / "profiles", proj / "workflow" / "profiles")
    (proj / "Snakefile").write_text(TOY)
    camp = tmp_path / "camp"
    (camp / "config").mkdir(parents=True)
    (camp / "config" / "config.yaml").write_text(
        "results: results\nslurm:\n  account: lab42\n  partition: short\n  gpu_partition: gpu\n"
    )
    return proj / "Snakefile", camp


def test_run_then_status(toy, capsys):
    snakefile, camp = toy
    assert (
        main(
            [
                "run",
                "--campaign",
                str(camp),
                "--snakefile",
                str(snakefile),
                "ingest",
                "--session",
                "s1",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "done   ingest s=s1" in out and "fit" not in out.split("steps done")[0]
    assert (camp / "results/s1/ingest/frames.txt").is_file()
    assert not (camp / "results/s3").exists()

    assert (
        main(["run", "--campaign", str(camp), "--snakefile", str(snakefile), "--cores", "1"]) == 1
    )
    out = capsys.readouterr().out
    assert "FAILED ingest s=s2  log: logs/ingest/s2.log" in out
    assert "1 failed" in out

    # Changing a stage's code makes it outdated (one of Snakemake's rerun triggers).
    snakefile.write_text(TOY.replace("cat {input}", "cat {input} {input}"))
    assert main(["status", "--campaign", str(camp), "--snakefile", str(snakefile)]) == 0
    text = capsys.readouterr().out
    rows = {ln.split()[0]: ln.split()[1:] for ln in text.splitlines()[1:4]}
    assert text.splitlines()[0].split() == ["session", "ingest", "fit"]
    assert rows == {
        "s1": ["done", "outdated"],
        "s2": ["failed", "pending"],
        "s3": ["done", "outdated"],
    }
    assert "failed: ingest s2: logs/ingest/s2.log  | bad video" in text
    assert "stages: 2 done, 1 failed, 2 outdated, 1 pending" in text


def test_run_targets_and_slurm_profile(toy, capsys):
    snakefile, camp = toy
    rows = runmod.detailed_summary(snakefile, camp)
    with pytest.raises(ValueError, match="unknown session 's9'"):
        runmod.resolve_targets(snakefile, camp, [], ["s9"], rows)
    with pytest.raises(ValueError, match="'mesh' is neither a stage"):
        runmod.resolve_targets(snakefile, camp, ["mesh"], [], rows)
    assert runmod.resolve_targets(snakefile, camp, ["fit"], ["s3", "s1"], rows) == [
        "results/s1/fit/done.txt",
        "results/s3/fit/done.txt",
    ]
    args = ["run", "--campaign", str(camp), "--snakefile", str(snakefile), "--cluster", "slurm"]
    assert main([*args, "--jobs", "7", "--print-command"]) == 0
    cmd = capsys.readouterr().out.split()
    prof_dir = Path(cmd[cmd.index("--profile") + 1])
    assert prof_dir == camp / ".surfphase" / "profiles" / "slurm"
    assert cmd[cmd.index("--jobs") + 1] == "7"
    prof = yaml.safe_load((prof_dir / "config.yaml").read_text())
    assert prof["executor"] == "slurm"
    assert prof["default-resources"]["slurm_account"] == "lab42"
    assert prof["default-resources"]["slurm_partition"] == "short"
    assert prof["set-resources"]["fit"]["slurm_partition"] == "gpu"
    assert prof["set-resources"]["fit"]["gpu"] == 1
    assert "slurm_partition" not in prof["set-resources"]["ingest"]
    assert main(["run", "--campaign", str(camp / "nowhere")]) == 2


def test_progress_lines():
    """The progress display turns Snakemake's job events into one line per event."""
    events = [
        {"event": "run_info", "time": 0.0, "total": 2, "stats": {"ingest": 1, "fit": 1}},
        {
            "event": "job_info",
            "time": 1.0,
            "jobid": 3,
            "rule": "ingest",
            "wildcards": {"s": "s1"},
            "output": ["results/s1/ingest/frames.txt"],
            "log": ["logs/ingest/s1.log"],
        },
        {"event": "submitted", "time": 1.5, "jobid": 3, "external_jobid": "17"},
        {"event": "job_finished", "time": 4.0, "jobid": 3},
        {"event": "progress", "time": 4.0, "done": 1, "total": 2},
        {"event": "job_error", "time": 5.0, "jobid": 2, "rule": "fit", "log": ["logs/fit/s1.log"]},
    ]
    out = io.StringIO()
    prog = runmod.Progress(Path("/c"), out=out, live=False)
    for ev in events:
        prog.feed(ev)
    lines = out.getvalue().splitlines()
    assert lines[0].endswith("start  ingest s=s1")
    assert lines[1].endswith("queued as SLURM job 17")
    assert "done   ingest s=s1 (3s)" in lines[2]
    assert lines[3] == "[  1/2    50%] FAILED fit   log: logs/fit/s1.log"
    assert (prog.done, prog.total) == (1, 2)
    assert [(j.rule, j.log) for j in prog.failed] == [("fit", "logs/fit/s1.log")]


def test_live_line_shows_running_jobs_and_their_logs(tmp_path):
    """On a terminal, long jobs show their elapsed time and the last line of their log."""
    import time

    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "fit.log").write_text("frame 1/24\nframe 7/24 psnr 31.2\n")
    out = io.StringIO()
    prog = runmod.Progress(tmp_path, out=out, live=True)
    prog.feed(
        {
            "event": "job_info",
            "time": time.time(),
            "jobid": 5,
            "rule": "fit",
            "wildcards": {"session": "a"},
            "output": ["results/a/fit"],
            "log": ["logs/fit.log"],
        }
    )
    prog.tick()
    live = out.getvalue().rsplit("\r\033[K", 1)[-1]
    assert live.startswith("[  0/?      ] running: fit session=a 0m00s | frame 7/24 psnr 31.2")


def test_every_help_text_prints():
    """`--help` of every command and benchmark formats (argparse's % expansion included)."""
    import argparse
    import contextlib
    import io

    from surfphase.cli import build_parser

    def walk(parser: argparse.ArgumentParser):
        yield parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from walk(sub)

    parsers = list(walk(build_parser()))
    assert len(parsers) > 10
    for p in parsers:
        with contextlib.redirect_stdout(io.StringIO()) as out:
            p.print_help()
        assert p.prog in out.getvalue()
