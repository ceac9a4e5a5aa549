"""A campaign's Snakemake lock: held by a live run, by a run on another host, or left
stale by a killed one; and the record ``surfphase run`` keeps while it runs."""

from __future__ import annotations

import json
import os
import shlex
import socket
import subprocess
import sys
import time
from pathlib import Path

from surfphase.io import atomic_write_text
from surfphase.runner.locate import snakemake_base, tail_lines

RUN_FILE = Path(".surfphase") / "run.json"  # in the campaign, while `surfphase run` runs


def lock_files(camp: Path) -> list[Path]:
    """Snakemake's lock files of the campaign (``.snakemake/locks``)."""
    d = camp / ".snakemake" / "locks"
    return sorted(d.iterdir()) if d.is_dir() else []


def snakemake_processes(camp: Path) -> list[int]:
    """PIDs of Snakemake processes on this host working in ``camp``.

    Snakemake changes into its ``--directory``, so a run of this campaign is a process
    whose command line runs snakemake and whose working folder is the campaign.
    """
    import psutil

    want = os.path.realpath(camp)
    pids = []
    for p in psutil.process_iter(["pid", "cwd", "cmdline"]):
        if p.info["pid"] == os.getpid():
            continue
        cmd = p.info.get("cmdline") or []
        cwd = p.info.get("cwd")
        if not cwd or not any("snakemake" in Path(c).name or "snakemake/" in c for c in cmd[:3]):
            continue
        if os.path.realpath(cwd) == want:
            pids.append(p.info["pid"])
    return sorted(pids)


def read_run_file(camp: Path) -> dict:
    """What the last `surfphase run` of ``camp`` recorded while it ran ({} if nothing)."""
    try:
        info = json.loads((camp / RUN_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def previous_run_killed(camp: Path) -> dict:
    """The record of a `surfphase run` of ``camp`` that ended without cleaning up (killed,
    or the machine went down); {} when there is none or that run is still alive."""
    import psutil

    info = read_run_file(camp)
    if not info:
        return {}
    if info.get("host") != socket.gethostname():
        return {}  # cannot tell from here
    try:
        proc = psutil.Process(int(info.get("pid", -1)))
        if abs(proc.create_time() - float(info.get("created", 0))) < 1.0:
            return {}  # still running
    except (psutil.Error, ValueError, TypeError):
        pass
    return info


def lock_state(camp: Path) -> dict:
    """``{"locked": bool, "live": [pids], "host": other host or ""}`` of the campaign.

    Locked with no live Snakemake here means a killed run left a stale lock, unless the
    run record says a run on another host holds it.
    """
    locked = bool(lock_files(camp))
    live = snakemake_processes(camp) if locked else []
    info = read_run_file(camp)
    other = info.get("host", "") if info.get("host") not in (None, socket.gethostname()) else ""
    return {"locked": locked, "live": live, "host": other if locked and not live else ""}


def lock_note(camp: Path) -> list[str]:
    """Status lines about the campaign's lock: a live run, or a stale lock and the fix."""
    st = lock_state(camp)
    if not st["locked"]:
        return []
    if st["live"]:
        pids = ", ".join(map(str, st["live"]))
        return [
            f"note: Snakemake is running in this campaign (pid {pids}); 'failed' may still be running"
        ]
    if st["host"]:
        return [
            f"note: the campaign is locked by a run on host {st['host']}; if that run is no "
            f"longer alive, release the lock with `snakemake --unlock --directory {shlex.quote(str(camp))}`"
        ]
    return [
        "note: stale lock: the last run was killed (no Snakemake process works in this "
        f"campaign, yet {camp / '.snakemake' / 'locks'} holds its lock). To recover: "
        "`surfphase run` resumes it (it releases the lock and redoes the incomplete jobs); "
        f"with plain Snakemake: `snakemake --unlock --directory {shlex.quote(str(camp))}`, "
        "then run with --rerun-incomplete."
    ]


def release_stale_lock(snakefile: Path, camp: Path, out=None) -> bool:
    """Before a run: say so when the previous run was killed, and release its stale lock.

    Returns False (and says why) when the campaign is locked by a live run.
    """
    out = out or sys.stdout
    killed = previous_run_killed(camp)
    st = lock_state(camp)
    if st["live"]:
        pids = ", ".join(map(str, st["live"]))
        out.write(
            f"Snakemake is already running in this campaign (pid {pids}); wait for it to "
            f"end, or stop it first (kill {pids}).\n"
        )
        return False
    if st["host"]:
        out.write(
            f"The campaign is locked by a run on host {st['host']}. If that run is no longer "
            f"alive: snakemake --unlock --directory {shlex.quote(str(camp))}\n"
        )
        return False
    if killed:
        out.write(
            f"The previous run (pid {killed.get('pid')}, started {killed.get('started', '?')}) "
            "was killed before it finished.\n"
        )
    if st["locked"]:
        out.write(
            "Releasing its stale lock (no Snakemake process works in this campaign); "
            "incomplete outputs are redone.\n"
            if killed
            else "The last run was killed: releasing its stale lock (no Snakemake process "
            "works in this campaign); incomplete outputs are redone.\n"
        )
        res = subprocess.run(
            snakemake_base(snakefile, camp) + ["--unlock"], capture_output=True, text=True
        )
        if res.returncode != 0:
            out.write(f"snakemake --unlock failed:\n{tail_lines(res.stderr, 10)}\n")
            return False
    out.flush()
    return True


def record_run(camp: Path) -> Path:
    """Write ``.surfphase/run.json`` (this process, host, start), removed when the run ends."""
    import psutil

    info = {
        "pid": os.getpid(),
        "created": psutil.Process().create_time(),
        "host": socket.gethostname(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    atomic_write_text(camp / RUN_FILE, json.dumps(info) + "\n")
    return camp / RUN_FILE
