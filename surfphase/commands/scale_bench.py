"""``surfphase bench scale``: DAG build and dry-run time of a large campaign, disk use.

A campaign of N sessions is written as sheets whose rows all point at the videos of one
synthetic session (so nothing heavy is generated); Snakemake then builds the DAG and
dry-runs it. With ``--results`` the disk use and file count per session of a finished
run are reported too.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def register(subparsers) -> None:
    """No stage command: this module only adds a benchmark."""


def write_scaled_campaign(
    source: Path, work: Path, n_sessions: int, frames: str = "", mesh_window: int = 0
) -> None:
    """Sheets for ``n_sessions`` copies of ``source``'s first session, under ``work/config``.

    ``source`` is a campaign folder written by ``surfphase synth`` (sessions.tsv, rigs.tsv).
    ``frames`` (``start:stop[:step]``) fills every row's frames column (long sessions in a
    dry run); ``mesh_window`` sets ``mesh: window`` (frames per mesh job).
    """
    lines = (source / "sessions.tsv").read_text().splitlines()
    cols = lines[0].split("\t")
    row = lines[1].split("\t")
    path_cols = {i for i, c in enumerate(cols) if c.startswith("cam") or c == "gt"}
    row = [str((source / v).resolve()) if i in path_cols and v else v for i, v in enumerate(row)]
    if frames:
        row[cols.index("frames")] = frames
    out = [lines[0]]
    for k in range(n_sessions):
        out.append("\t".join([f"s{k:04d}", *row[1:]]))
    (work / "config").mkdir(parents=True, exist_ok=True)
    (work / "config" / "sessions.tsv").write_text("\n".join(out) + "\n")
    rig_lines = (source / "rigs.tsv").read_text().splitlines()
    rcols = rig_lines[0].split("\t")
    rrow = [
        str((source / v).resolve()) if (c.startswith("cam") or c == "board") and v else v
        for c, v in zip(rcols, rig_lines[1].split("\t"), strict=True)
    ]
    (work / "config" / "rigs.tsv").write_text(rig_lines[0] + "\n" + "\t".join(rrow) + "\n")
    (work / "config" / "config.yaml").write_text(
        "sessions: config/sessions.tsv\nrigs: config/rigs.tsv\nresults: results\n"
        + (f"mesh:\n  window: {int(mesh_window)}\n" if mesh_window else "")
    )


def disk_use(results: Path) -> dict:
    """Bytes and files per session folder under ``results`` (checkpoints included)."""
    out = {}
    for d in sorted(p for p in results.iterdir() if p.is_dir()):
        files = [f for f in d.rglob("*") if f.is_file()]
        out[d.name] = {
            "megabytes": round(sum(f.stat().st_size for f in files) / 1e6, 2),
            "files": len(files),
        }
    return out


def _bench(args: argparse.Namespace) -> int:
    from surfphase.synth.campaign import write_campaign

    report: dict = {"sessions": args.sessions}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        source = Path(args.campaign) if args.campaign else tmp / "tiny"
        if not args.campaign:
            write_campaign(source, preset="tiny", seed=0)
        work = tmp / "work"
        write_scaled_campaign(source, work, args.sessions, args.frames, args.mesh_window)
        cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile")]
        cmd += ["-d", str(work), "--cores", "2", "-n", "--quiet", "rules"]
        t0 = time.perf_counter()
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        r = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        report["dry_run_s"] = round(time.perf_counter() - t0, 2)
        # CPU time too: on a shared machine the wall time mostly measures the others' load.
        cpu = c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime
        report["dry_run_cpu_s"] = round(cpu, 2)
        if r.returncode != 0:
            print(r.stdout + r.stderr, file=sys.stderr)
            return 1
        report["jobs"] = {
            line.split()[0]: int(line.split()[1])
            for line in r.stdout.splitlines()
            if len(line.split()) == 2 and line.split()[1].isdigit()
        }
    if args.results:
        report["disk_use"] = disk_use(Path(args.results))
    print(json.dumps(report, indent=1))
    return 0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "scale", help="DAG build + dry-run time of an N-session campaign; disk use per session"
    )
    p.add_argument("--sessions", type=int, default=50)
    p.add_argument("--campaign", help="a synthetic campaign folder (default: a tiny one)")
    p.add_argument("--results", help="a results/ folder to report disk use per session")
    p.add_argument("--frames", default="", help="frames column of every session, start:stop")
    p.add_argument("--mesh-window", type=int, default=0, help="mesh: window (frames per job)")
    p.set_defaults(func=_bench)
