"""``surfphase run``'s progress: a line per job event (started, done, failed with its
log, queued on a cluster) and, on a terminal, a live line with the running jobs, their
elapsed time and the last line of their logs.

The events are Snakemake's own, written as JSON lines by SurfPhase's logger plugin
(:mod:`surfphase.runner.events`); Snakemake's text output is only shown (its last lines
when it stops before any job failed), never parsed.
"""

from __future__ import annotations

import importlib.util
import os
import select
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from surfphase.runner.events import EVENTS_FILE, EventFile, logger_args
from surfphase.runner.status import last_line, middle_cut

PLUGIN_PACKAGE = "snakemake_logger_plugin_surfphase"


@dataclass
class _Job:
    rule: str
    wildcards: str = ""
    log: str = ""
    started: float = field(default_factory=time.time)


def wildcards_text(wildcards: dict[str, Any]) -> str:
    """``session=s1, window=0``: a job's wildcards as Snakemake prints them."""
    return ", ".join(f"{k}={v}" for k, v in wildcards.items())


class Progress:
    """Turns Snakemake's job events into one line per event (and a live line on a TTY)."""

    def __init__(self, camp: Path, out=None, live: bool | None = None):
        self.camp = camp
        self.out = out = out or sys.stdout
        self.live = out.isatty() if live is None else live
        self.jobs: dict[int, _Job] = {}
        self.done = 0
        self.total = 0
        self.failed: list[_Job] = []
        self.last_status = 0.0
        self.log_file = ""
        self.ran = False  # Snakemake built a DAG with jobs to run (run_info)

    def _print(self, text: str) -> None:
        if self.live:
            self.out.write("\r\033[K")
        self.out.write(text + "\n")
        self.out.flush()

    def _head(self) -> str:
        pct = f"{100 * self.done // self.total:3d}%" if self.total else "   "
        return f"[{self.done:>3}/{self.total or '?':<3} {pct}]"

    def feed(self, ev: dict[str, Any]) -> None:
        """Take one event (a line of the events file, :mod:`surfphase.runner.events`)."""
        kind = ev.get("event")
        if kind == "job_info":
            job = _Job(
                rule=ev["rule"],
                wildcards=wildcards_text(ev.get("wildcards") or {}),
                log=(ev.get("log") or [""])[0],
                started=float(ev.get("time", time.time())),
            )
            self.jobs[int(ev["jobid"])] = job
            if job.rule != "all":
                self._print(f"{self._head()} start  {job.rule} {job.wildcards}")
        elif kind == "job_finished":
            job = self.jobs.pop(int(ev["jobid"]), None) or _Job("?")
            self.done += 1
            if job.rule != "all":
                secs = float(ev.get("time", time.time())) - job.started
                self._print(f"{self._head()} done   {job.rule} {job.wildcards} ({secs:.0f}s)")
        elif kind == "job_error":
            job = self.jobs.pop(int(ev["jobid"]), None) or _Job(ev.get("rule", "?"))
            job.log = job.log or (ev.get("log") or [""])[0]
            self.failed.append(job)
            self._print(f"{self._head()} FAILED {job.rule} {job.wildcards}  log: {job.log or '-'}")
        elif kind == "progress":
            self.done, self.total = int(ev["done"]), int(ev["total"])
        elif kind == "run_info":
            self.total, self.ran = int(ev["total"]), True
        elif kind == "submitted":
            self._print(f"{self._head()} queued as SLURM job {ev['external_jobid']}")
        elif kind == "nothing_to_do":
            self._print("Nothing to do: every requested output is up to date.")

    def tick(self) -> None:
        """Refresh the live line: running jobs, elapsed time, last line of their logs."""
        if not self.live or not self.jobs or time.monotonic() - self.last_status < 1:
            return
        self.last_status = time.monotonic()
        parts = []
        for job in list(self.jobs.values())[:3]:
            secs = max(int(time.time() - job.started), 0)
            last = last_line(self.camp / job.log) if job.log else ""
            parts.append(
                f"{job.rule} {job.wildcards} {secs // 60}m{secs % 60:02d}s"
                + (f" | {last}" if last else "")
            )
        cols = 120
        try:
            cols = os.get_terminal_size(self.out.fileno()).columns
        except (OSError, ValueError, AttributeError):
            pass
        line = f"{self._head()} running: " + "; ".join(parts)
        self.out.write("\r\033[K" + middle_cut(line, cols - 1))
        self.out.flush()


def plugin_path() -> Path | None:
    """The folder holding the ``snakemake_logger_plugin_surfphase`` package (to put on the
    PYTHONPATH of Snakemake: an editable install is invisible to its plugin search)."""
    beside = Path(__file__).resolve().parents[2]
    if (beside / PLUGIN_PACKAGE / "__init__.py").is_file():
        return beside
    spec = importlib.util.find_spec(PLUGIN_PACKAGE)
    if spec and spec.origin:
        return Path(spec.origin).resolve().parents[1]
    return None


def with_events(cmd: list[str], camp: Path, out=None) -> tuple[list[str], Path | None]:
    """``cmd`` with the options that write Snakemake's job events to the campaign's events
    file, emptied for this run; ``(cmd, None)`` with a warning when the plugin is missing."""
    if plugin_path() is None:
        (out or sys.stdout).write(
            f"warning: {PLUGIN_PACKAGE} is not installed (reinstall surfphase): no progress "
            "lines; Snakemake's own output follows.\n"
        )
        return cmd, None
    events = camp / EVENTS_FILE
    events.parent.mkdir(parents=True, exist_ok=True)
    events.write_text("")
    return cmd + logger_args(events), events


def snakemake_env() -> dict[str, str]:
    """This process's environment with the logger plugin's folder on the PYTHONPATH."""
    env = dict(os.environ)
    path = plugin_path()
    if path is not None:
        env["PYTHONPATH"] = os.pathsep.join(
            [str(path), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]]
        )
    return env


def snakemake_logs(camp: Path) -> set[Path]:
    """Snakemake's log files in the campaign (one per run that got to its jobs)."""
    return set((camp / ".snakemake" / "log").glob("*.snakemake.log"))


def new_log(camp: Path, before: set[Path]) -> str:
    """The log file Snakemake started since ``before`` (:func:`snakemake_logs`), or ''."""
    logs = snakemake_logs(camp) - before
    return str(max(logs, key=lambda p: p.stat().st_mtime)) if logs else ""


def _follow(proc: subprocess.Popen, prog: Progress, events: EventFile | None) -> list[str]:
    """Show the run's events until Snakemake exits; returns its last 25 output lines."""
    assert proc.stdout is not None
    tail: list[str] = []
    while True:
        ready, _, _ = select.select([proc.stdout], [], [], 1.0)
        if ready:
            line = proc.stdout.readline()
            if not line:
                break
            tail = (tail + [line.rstrip()])[-25:]
        for ev in events.new() if events else []:
            prog.feed(ev)
        prog.tick()
    proc.wait()
    for ev in events.new() if events else []:
        prog.feed(ev)
    return tail


def _summary(prog: Progress, camp: Path, rc: int, tail: list[str], out) -> None:
    if prog.live:
        out.write("\r\033[K")
    if rc < 0:
        try:
            name = signal.Signals(-rc).name
        except ValueError:
            name = f"signal {-rc}"
        out.write(
            f"Snakemake was killed ({name}). Run `surfphase run` again to resume: it "
            "releases the stale lock and redoes the incomplete jobs.\n"
        )
    elif rc != 0 and not prog.failed:
        out.write("Snakemake stopped:\n" + "\n".join(tail) + "\n")
    summary = f"{prog.done} of {prog.total or prog.done} steps done"
    if prog.failed:
        summary += f", {len(prog.failed)} failed: " + ", ".join(
            f"{j.rule} {j.wildcards} ({j.log or 'no log'})" for j in prog.failed
        )
    out.write(summary + "\n")
    if prog.log_file:
        out.write(f"Snakemake's log: {prog.log_file}\n")
    out.write(f"See `surfphase status --campaign {shlex.quote(str(camp))}`.\n")
    out.flush()


def stream(cmd: list[str], camp: Path, verbose: bool, out=None, events: Path | None = None) -> int:
    """Run Snakemake, showing its progress from the job events it writes to ``events``
    (see :func:`with_events`; None: none to show); returns its exit code."""
    out = out or sys.stdout
    if verbose:
        return subprocess.call(cmd, env=snakemake_env())
    prog = Progress(camp, out=out)
    before = snakemake_logs(camp)
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        bufsize=1,
        env=snakemake_env(),
    )
    tail = _follow(proc, prog, EventFile(events) if events else None)
    rc = proc.returncode
    if prog.ran:  # Snakemake names its log ("Complete log(s)") when it ran jobs
        prog.log_file = new_log(camp, before)
    _summary(prog, camp, rc, tail, out)
    return rc
