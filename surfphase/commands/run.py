"""``surfphase run`` and ``surfphase status``: the campaign workflow for users.

``surfphase run`` calls Snakemake on the project's Snakefile with a campaign folder
(one that holds ``config/config.yaml``) and one of the project's profiles
(``workflow/profiles/local`` or, with ``--cluster slurm``, ``workflow/profiles/slurm``
plus the account and partitions from the campaign's ``slurm:`` config). Its output is a
line per job (started, done, failed, with the job's log), and, on a terminal, a line
that shows the running jobs, their elapsed time and the last line of their logs.

``surfphase status`` asks Snakemake (``--detailed-summary``: every output file of the
campaign's DAG, its rule and whether it is up to date) and tells per session and stage
whether it is done, failed (outputs missing, log present), outdated (code, params or
inputs changed) or pending. It never re-implements the DAG.

After a kill: ``status`` tells a stale lock (no Snakemake process works in the
campaign) from a live run, and ``run`` says the previous run was killed, releases the
stale lock and resumes. After a run in which sessions failed, ``run`` writes the
campaign table and page of the sessions that finished, listing the failed ones with
their error, dated so that Snakemake rewrites them on the next run.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import re
import select
import shlex
import signal
import socket
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from surfphase.io import atomic_write_text

# Stages in the order of docs/method.md §1; rules not listed are shown after them.
STAGE_ORDER = [
    "session_sheet",
    "calibrate",
    "ingest",
    "mask",
    "fit",
    "render_views",
    "train_prior",
    "refine",
    "fit_stage2",
    "fit_ablation",
    "mesh_window",
    "mesh",
    "mesh_compare",
    "evaluate",
    "plots",
    "mesh_snapshots",
    "report_videos",
    "campaign_table",
    "campaign_page",
]
PROFILES = ("local", "slurm")


# --- locating the workflow and the campaign ---------------------------------------------


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


# --- what Snakemake knows: the detailed summary -----------------------------------------


@dataclass
class OutputState:
    """One output file of the campaign's DAG, as Snakemake's detailed summary sees it."""

    path: str
    rule: str
    status: str  # Snakemake's: ok, missing, incomplete, ...
    plan: str  # Snakemake's: no update, update pending
    logs: list[str] = field(default_factory=list)


def detailed_summary(
    snakefile: Path, camp: Path, extra: list[str] | None = None
) -> list[OutputState]:
    """Every output of the DAG with its rule and state (``snakemake --detailed-summary``)."""
    cmd = snakemake_base(snakefile, camp) + ["--detailed-summary", "--cores", "1"] + (extra or [])
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise ValueError(
            f"campaign {camp}: Snakemake could not read the workflow:\n{_tail(res.stderr, 15)}"
        )
    text = res.stdout[res.stdout.find("output_file\t") :]
    rows = []
    for row in csv.DictReader(io.StringIO(text), delimiter="\t"):
        if not row.get("output_file"):
            continue
        logs = [s for s in (row.get("log-file(s)") or "").split(",") if s and s != "-"]
        rows.append(
            OutputState(
                path=row["output_file"],
                rule=row.get("rule") or "?",
                status=(row.get("status") or "").strip(),
                plan=(row.get("plan") or "").strip(),
                logs=[s.strip() for s in logs],
            )
        )
    return rows


def _tail(text: str, n: int) -> str:
    return "\n".join(text.strip().splitlines()[-n:])


def unit_of(path: str, results: str) -> str:
    """Which part of the campaign an output belongs to: a session, ``calib/<rig>`` or
    ``campaign`` (outputs under ``results/<session>/...`` and ``results/calib/<rig>/...``)."""
    parts = Path(os.path.normpath(path)).parts
    res = Path(os.path.normpath(results)).parts
    if parts[: len(res)] != res or len(parts) <= len(res) + 1:
        return "campaign"
    head = parts[len(res)]
    if head == "calib" and len(parts) > len(res) + 2:
        return f"calib/{parts[len(res) + 1]}"
    return head


def output_state(o: OutputState, camp: Path) -> str:
    """done / failed / outdated / pending for one output."""
    if o.status == "incomplete":
        return "failed"
    # A temporary output (e.g. a mesh window) removed after its consumer ran was made.
    if o.status in ("ok", "removed temp file") or (camp / o.path).exists():
        return "outdated" if o.plan == "update pending" else "done"
    if any((camp / log).is_file() for log in o.logs):
        return "failed"
    return "pending"


def campaign_status(
    snakefile: Path, camp: Path, sessions: list[str] | None = None
) -> dict[str, dict[str, dict]]:
    """``{unit: {stage: {"state": ..., "outputs": n, "logs": [...]}}}`` of a campaign.

    A unit is a session, ``calib/<rig>`` or ``campaign``; a stage is a rule. A stage is
    failed if any output failed, else pending if any is pending, else outdated if any is
    outdated, else done.
    """
    results = str(read_config(camp).get("results", "results"))
    table: dict[str, dict[str, dict]] = {}
    rank = {"failed": 3, "pending": 2, "outdated": 1, "done": 0}
    for o in detailed_summary(snakefile, camp):
        unit = unit_of(o.path, results)
        if sessions and unit not in sessions:
            continue
        state = output_state(o, camp)
        cell = table.setdefault(unit, {}).setdefault(
            o.rule, {"state": "done", "outputs": 0, "logs": []}
        )
        cell["outputs"] += 1
        if rank[state] > rank[cell["state"]]:
            cell["state"] = state
        if state == "failed":
            cell["logs"] += [log for log in o.logs if log not in cell["logs"]]
    return table


def stage_columns(table: dict[str, dict[str, dict]]) -> list[str]:
    seen = {s for cells in table.values() for s in cells}
    return [s for s in STAGE_ORDER if s in seen] + sorted(seen - set(STAGE_ORDER))


def format_status(table: dict[str, dict[str, dict]], camp: Path) -> str:
    stages = stage_columns(table)
    units = sorted(table, key=lambda u: (u == "campaign", not u.startswith("calib/"), u))
    width = max([len("session")] + [len(u) for u in units]) + 2
    colw = [max(len(s), 8) + 2 for s in stages]
    lines = [
        "session".ljust(width) + "".join(s.ljust(w) for s, w in zip(stages, colw, strict=True))
    ]
    for u in units:
        cells = [table[u].get(s, {}).get("state", "-") for s in stages]
        lines.append(u.ljust(width) + "".join(c.ljust(w) for c, w in zip(cells, colw, strict=True)))
    counts: dict[str, int] = {}
    for cells in table.values():
        for c in cells.values():
            counts[c["state"]] = counts.get(c["state"], 0) + 1
    lines.append("")
    lines.append(
        "stages: "
        + ", ".join(f"{counts.get(k, 0)} {k}" for k in ("done", "failed", "outdated", "pending"))
    )
    for u in units:
        for s in stages:
            cell = table[u].get(s)
            if cell and cell["state"] == "failed":
                for log in cell["logs"] or ["(no log)"]:
                    last = _last_line(camp / log) if cell["logs"] else ""
                    lines += failure_lines(f"failed: {s} {u}: {log}", last)
    lines += lock_note(camp)
    return "\n".join(lines)


def failure_lines(head: str, last: str, width: int = 100) -> list[str]:
    """``head  | last`` on one line when it fits in ``width``, else ``last`` wrapped
    under ``head`` (never cut: a log's last line often ends with the file at fault)."""
    if not last:
        return [head]
    if len(head) + 4 + len(last) <= width:
        return [f"{head}  | {last}"]
    wrapped = textwrap.wrap(last, width - 6, break_long_words=False, break_on_hyphens=False) or [
        last
    ]
    return [head, *(f"    | {ln}" for ln in wrapped)]


def middle_cut(text: str, width: int) -> str:
    """``text`` cut to ``width`` characters in the middle, keeping its start and end."""
    if len(text) <= width:
        return text
    keep = max(width - 1, 2)
    head = keep // 3
    return text[:head] + "…" + text[len(text) - (keep - head) :]


def _last_line(path: Path, max_bytes: int = 4096) -> str:
    """The last non-empty line of a (log) file, or '' (at most 1000 characters: longer
    ones are cut in the middle, keeping the end)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            text = f.read().decode(errors="replace")
    except OSError:
        return ""
    lines = [ln.strip() for ln in re.split(r"[\r\n]", text) if ln.strip()]
    return middle_cut(lines[-1], 1000) if lines else ""


# --- locks: a live run or a killed one --------------------------------------------------

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
            out.write(f"snakemake --unlock failed:\n{_tail(res.stderr, 10)}\n")
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


# --- targets ----------------------------------------------------------------------------


def resolve_targets(
    snakefile: Path,
    camp: Path,
    targets: list[str],
    sessions: list[str],
    rows: list[OutputState] | None = None,
) -> list[str]:
    """Snakemake targets for stages (rule names) and/or sessions.

    No sessions: stage names become their output files for every session; other
    targets (files) pass unchanged. With sessions: the outputs of those sessions (of the
    given stages, or of every stage). The file lists come from Snakemake's summary
    (``rows``, asked for when not given).
    """
    if not sessions and not targets:
        return []
    rows = detailed_summary(snakefile, camp) if rows is None else rows
    results = str(read_config(camp).get("results", "results"))
    rules = {o.rule for o in rows}
    units = {unit_of(o.path, results) for o in rows}
    for s in sessions:
        if s not in units:
            known = sorted(u for u in units if not u.startswith("calib/") and u != "campaign")
            raise ValueError(
                f"campaign {camp}: unknown session '{s}' (sessions: {', '.join(known)})"
            )
    stages = [t for t in targets if t in rules]
    files = [t for t in targets if t not in rules]
    for f in files:
        if "/" not in f and "." not in f:
            raise ValueError(
                f"campaign {camp}: '{f}' is neither a stage ({', '.join(sorted(rules))}) nor a file"
            )
    # Only files given: those files, not every output of the campaign.
    chosen = [
        o.path
        for o in rows
        if (stages or sessions)
        and (not stages or o.rule in stages)
        and (not sessions or unit_of(o.path, results) in sessions)
    ]
    if (stages or sessions) and not chosen:
        raise ValueError(
            f"campaign {camp}: nothing to do for stages {stages} of sessions {sessions}"
        )
    return chosen + files


# --- running Snakemake with a progress display --------------------------------------------


@dataclass
class _Job:
    rule: str
    wildcards: str = ""
    log: str = ""
    started: float = field(default_factory=time.monotonic)


class Progress:
    """Turns Snakemake's log into one line per job event (and a live line on a TTY)."""

    def __init__(self, camp: Path, out=None, live: bool | None = None):
        self.camp = camp
        self.out = out = out or sys.stdout
        self.live = out.isatty() if live is None else live
        self.jobs: dict[str, _Job] = {}
        self.pending: _Job | None = None
        self.pending_id: str | None = None
        self.in_error = False
        self.failing: _Job | None = None
        self.done = 0
        self.total = 0
        self.failed: list[_Job] = []
        self.last_status = 0.0
        self.log_file = ""

    def _print(self, text: str) -> None:
        if self.live:
            self.out.write("\r\033[K")
        self.out.write(text + "\n")
        self.out.flush()

    def _head(self) -> str:
        pct = f"{100 * self.done // self.total:3d}%" if self.total else "   "
        return f"[{self.done:>3}/{self.total or '?':<3} {pct}]"

    def feed(self, line: str) -> None:
        """Take one line of Snakemake's output."""
        s = line.rstrip("\n")
        st = s.strip()
        if self.failing and not s[:1].isspace():
            self.close()
        if m := re.match(r"^(?:local)?(?:rule|checkpoint) (\S+):$", s):
            self.pending, self.pending_id, self.in_error = _Job(m.group(1)), None, False
        elif m := re.match(r"^Error in rule (\S+):$", s):
            self.pending, self.pending_id, self.in_error = _Job(m.group(1)), None, True
        elif self.pending and (m := re.match(r"^log: (.+?)(?: \(check log.*\))?$", st)):
            self.pending.log = m.group(1)
        elif self.failing and (m := re.match(r"^log: (.+?)(?: \(check log.*\))?$", st)):
            self.failing.log = self.failing.log or m.group(1)
        elif self.pending and (m := re.match(r"^wildcards: (.+)$", st)):
            self.pending.wildcards = m.group(1)
        elif self.pending and (m := re.match(r"^jobid: (\d+)$", st)):
            if self.in_error:  # reported when the error block ends (its log line follows)
                self.failing = self.jobs.pop(m.group(1), self.pending)
                self.pending = None
            else:
                self.pending_id = m.group(1)
        elif self.pending and self.pending_id and st.startswith("resources:"):
            job, self.pending = self.pending, None
            job.started = time.monotonic()
            self.jobs[self.pending_id] = job
            if job.rule != "all":
                self._print(f"{self._head()} start  {job.rule} {job.wildcards}")
        elif m := re.match(r"^Finished jobid: (\d+) \(Rule: (\S+)\)", s):
            job = self.jobs.pop(m.group(1), _Job(m.group(2)))
            self.done += 1
            if job.rule != "all":
                secs = time.monotonic() - job.started
                self._print(f"{self._head()} done   {job.rule} {job.wildcards} ({secs:.0f}s)")
        elif m := re.match(r"^(\d+) of (\d+) steps", s):
            self.done, self.total = int(m.group(1)), int(m.group(2))
        elif m := re.match(r"^total\s+(\d+)$", st):
            self.total = int(m.group(1))
        elif m := re.search(r"has been submitted with SLURM jobid (\d+)", s):
            self._print(f"{self._head()} queued as SLURM job {m.group(1)}")
        elif m := re.match(r"^Complete log\(s\): (.+)$", s):
            self.log_file = m.group(1)
        elif st.startswith("Nothing to be done"):
            self._print("Nothing to do: every requested output is up to date.")

    def close(self) -> None:
        """Report a failed job whose error block has ended (or the output has)."""
        if self.failing:
            job, self.failing = self.failing, None
            self.failed.append(job)
            self._print(f"{self._head()} FAILED {job.rule} {job.wildcards}  log: {job.log or '-'}")

    def tick(self) -> None:
        """Refresh the live line: running jobs, elapsed time, last line of their logs."""
        if not self.live or not self.jobs or time.monotonic() - self.last_status < 1:
            return
        self.last_status = time.monotonic()
        parts = []
        for job in list(self.jobs.values())[:3]:
            secs = int(time.monotonic() - job.started)
            last = _last_line(self.camp / job.log) if job.log else ""
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


def stream(cmd: list[str], camp: Path, verbose: bool, out=None) -> int:
    """Run Snakemake, showing its progress; returns its exit code."""
    out = out or sys.stdout
    if verbose:
        return subprocess.call(cmd)
    prog = Progress(camp, out=out)
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1
    )
    assert proc.stdout is not None
    tail: list[str] = []
    while True:
        ready, _, _ = select.select([proc.stdout], [], [], 1.0)
        if ready:
            line = proc.stdout.readline()
            if not line:
                break
            tail = (tail + [line.rstrip()])[-25:]
            prog.feed(line)
        prog.tick()
    rc = proc.wait()
    prog.close()
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
    return rc


def build_run_command(args: argparse.Namespace) -> tuple[list[str], Path]:
    """The Snakemake command line of ``surfphase run`` and the campaign folder."""
    camp = campaign_dir(args.campaign)
    snakefile = find_snakefile(args.snakefile)
    sessions = [s for item in (args.session or []) for s in item.split(",") if s]
    profiles = snakefile.parent / "workflow" / "profiles"
    if args.cluster == "slurm":
        cfg = read_config(camp)
        profile = slurm_profile(
            camp, profiles / "slurm", cfg.get("slurm"), str(cfg.get("device", "auto"))
        )
    else:
        profile = profiles / "local"
    if not (profile / "config.yaml").is_file():
        raise FileNotFoundError(f"{profile / 'config.yaml'}: profile not found")
    cmd = snakemake_base(snakefile, camp) + ["--profile", str(profile)]
    if args.cores:
        cmd += ["--cores", str(args.cores)]
    if args.jobs:
        cmd += ["--jobs", str(args.jobs)]
    if args.dry_run:
        cmd += ["--dry-run"]
    # Targets before the extra options: options such as --set-threads take several values.
    cmd += resolve_targets(snakefile, camp, list(args.targets), sessions)
    cmd += shlex.split(args.snakemake_args or "")
    return cmd, camp


def run_cmd(args: argparse.Namespace) -> int:
    cmd, camp = build_run_command(args)
    if args.print_command:
        print(shlex.join(cmd))
        return 0
    if args.dry_run:
        return 1 if stream(cmd, camp, verbose=True) else 0
    snakefile = find_snakefile(args.snakefile)
    if not release_stale_lock(snakefile, camp):
        return 1
    run_file = record_run(camp)
    try:
        rc = stream(cmd, camp, verbose=args.verbose)
    finally:
        run_file.unlink(missing_ok=True)
    whole = not args.targets and not args.session
    if rc > 0 and whole:
        try:
            partial_campaign(snakefile, camp)
        except Exception as e:  # the run's own failure is what matters: report, go on
            print(
                "The campaign table and page of the finished sessions were not written: "
                f"{type(e).__name__}: {e}"
            )
    return 1 if rc else 0


# --- the campaign's table and page when some sessions failed ------------------------------


def campaign_sessions(camp: Path) -> list[str]:
    """The session ids of the campaign's sessions sheet (config ``sessions``)."""
    import pandas as pd

    sheet = camp / str(read_config(camp).get("sessions", "config/sessions.tsv"))
    try:
        df = pd.read_csv(sheet, sep="\t", dtype=str, comment="#", keep_default_na=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{sheet}: cannot read the sessions sheet ({e})") from e
    df.columns = [c.strip() for c in df.columns]
    if "session" not in df.columns:
        raise ValueError(f"{sheet}: no 'session' column")
    return [v.strip() for v in df["session"] if v.strip()]


def session_outcomes(
    table: dict[str, dict[str, dict]], camp: Path, sessions: list[str]
) -> dict[str, str]:
    """``{session: ""}`` for each of ``sessions`` whose every stage is done, else
    ``{session: why}``: the first failed stage and the last line of its log, or the
    first stage not run and why (a failed calibration)."""
    calib_failed = [
        f"calibrate {u} failed: {_last_line(camp / c['logs'][0]) if c['logs'] else 'no log'}"
        for u, cells in sorted(table.items())
        if u.startswith("calib/")
        for c in cells.values()
        if c["state"] == "failed"
    ]
    out = {}
    for unit, cells in table.items():
        if unit not in sessions:
            continue  # the campaign's own outputs, a rig's calibration, the prior
        order = stage_columns({unit: cells})
        failed = [s for s in order if cells[s]["state"] == "failed"]
        waiting = [s for s in order if cells[s]["state"] != "done"]
        if failed:
            s = failed[0]
            log = cells[s]["logs"][0] if cells[s]["logs"] else ""
            last = _last_line(camp / log) if log else ""
            out[unit] = f"{s} failed" + (f" (log {log}): {last}" if log else "")
        elif waiting:
            out[unit] = f"{waiting[0]} not run ({cells[waiting[0]]['state']})" + (
                f"; {'; '.join(calib_failed)}" if calib_failed else ""
            )
        else:
            out[unit] = ""
    return out


def partial_campaign(snakefile: Path, camp: Path, out=None) -> bool:
    """After a run in which some sessions failed: write the campaign table and page
    (``RESULTS/campaign/metrics.csv``, ``index.html``) of the sessions that finished,
    with a row per failed session: its ``status`` and ``error``.

    Snakemake does not take them for its own: they get the modification time 0 (older
    than any input), so the next run rewrites both from every session. Returns whether
    they were written (not when nothing finished or the campaign outputs are up to date).
    """
    from surfphase.eval.stage import campaign_table
    from surfphase.report.plots import campaign_page

    out = out or sys.stdout
    table = campaign_status(snakefile, camp)
    stages = table.get("campaign", {})
    if "campaign_table" not in stages or all(c["state"] == "done" for c in stages.values()):
        return False
    results = camp / str(read_config(camp).get("results", "results"))
    outcomes = session_outcomes(table, camp, campaign_sessions(camp))
    done = sorted(s for s, why in outcomes.items() if not why)
    failed = sorted(s for s, why in outcomes.items() if why)
    if not done:
        out.write("No session finished: no campaign table or page.\n")
        return False
    rows = []
    for s in done:
        rows.append({**json.loads((results / s / "evaluate" / "metrics.json").read_text())})
        rows[-1]["session"], rows[-1]["status"], rows[-1]["error"] = s, "finished", ""
    rows += [{"session": s, "status": "failed", "error": outcomes[s]} for s in failed]
    metrics_csv = results / "campaign" / "metrics.csv"
    atomic_write_text(metrics_csv, campaign_table(rows).to_csv(index=False))
    media: dict[str, dict[str, list[Path]]] = {k: {} for k in ("figures", "overlays", "meshes")}
    media["videos"] = {}
    for s in done:
        rep = results / s / "report"
        media["figures"][s] = [rep / "velocity.png"] if (rep / "velocity.png").is_file() else []
        media["overlays"][s] = sorted((rep / "masks").glob("*.png"))
        media["meshes"][s] = sorted((rep / "meshes").glob("*.png"))
        media["videos"][s] = sorted((rep / "videos").glob("*.mp4"))
    prior = results / "prior" / "samples.png"
    page = results / "campaign" / "index.html"
    campaign_page(
        metrics_csv,
        page,
        media["figures"],
        media["overlays"],
        f"SurfPhase campaign (partial: {len(done)} of {len(outcomes)} sessions finished)",
        meshes=media["meshes"],
        videos=media["videos"],
        prior_samples=prior if prior.is_file() else None,
    )
    for f in (metrics_csv, page):
        os.utime(f, (0, 0))  # older than every input: Snakemake reruns them
    out.write(
        f"Campaign table and page of the {len(done)} finished sessions (failed: "
        f"{', '.join(failed)}): {metrics_csv.relative_to(camp)}, {page.relative_to(camp)}; "
        "the next run rewrites them.\n"
    )
    out.flush()
    return True


def status_cmd(args: argparse.Namespace) -> int:
    camp = campaign_dir(args.campaign)
    snakefile = find_snakefile(args.snakefile)
    sessions = [s for item in (args.session or []) for s in item.split(",") if s]
    table = campaign_status(snakefile, camp, sessions or None)
    if args.json:
        print(json.dumps(table, indent=1, sort_keys=True))
    else:
        print(format_status(table, camp))
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--campaign",
        default=".",
        metavar="DIR",
        help="campaign folder holding config/config.yaml (default: the current folder)",
    )
    p.add_argument("--snakefile", help="the workflow's Snakefile (default: the project's)")
    p.add_argument(
        "--session",
        action="append",
        metavar="ID",
        help="only this session (repeat, or comma-separate, for several)",
    )


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run the campaign workflow (Snakemake with the project's profile)",
        description=(
            "Run the workflow on a campaign. TARGETs are stages (calibrate, ingest, ...) "
            "or output files; none means every stage of every session. Failed sessions do "
            "not stop the others; a killed run resumes where it stopped."
        ),
    )
    p.add_argument("targets", nargs="*", metavar="TARGET", help="stages or output files")
    _common(p)
    p.add_argument("--cores", type=int, help="CPU cores to use (local; profile default 2)")
    p.add_argument("--jobs", type=int, help="jobs in flight at once (cluster; default 100)")
    p.add_argument(
        "--cluster",
        choices=PROFILES,
        default="local",
        help="where jobs run: this machine (local) or SLURM (slurm; account and partitions "
        "from the campaign config's slurm: section)",
    )
    p.add_argument("-n", "--dry-run", action="store_true", help="list the jobs, run nothing")
    p.add_argument("--verbose", action="store_true", help="show Snakemake's full output")
    p.add_argument(
        "--snakemake-args", metavar="ARGS", help="more Snakemake options, e.g. '--forcerun fit'"
    )
    p.add_argument(
        "--print-command", action="store_true", help="print the Snakemake command, run nothing"
    )
    p.set_defaults(func=run_cmd)

    s = subparsers.add_parser(
        "status",
        help="which sessions and stages are done, failed, outdated or pending",
        description="Per session and stage: done, failed (see its log), outdated "
        "(code, parameters or inputs changed: will rerun) or pending. Asks Snakemake.",
    )
    _common(s)
    s.add_argument("--json", action="store_true", help="print the table as JSON")
    s.set_defaults(func=status_cmd)
