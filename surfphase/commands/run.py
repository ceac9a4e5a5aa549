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
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from surfphase.io import atomic_write_text

# Stages in the order of DESIGN.md; rules not listed are shown after them.
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
                    lines.append(f"failed: {s} {u}: {log}" + (f"  | {last}" if last else ""))
    if (camp / ".snakemake" / "locks").is_dir() and any((camp / ".snakemake" / "locks").iterdir()):
        lines.append("note: Snakemake is running in this campaign; 'failed' may still be running")
    return "\n".join(lines)


def _last_line(path: Path, max_bytes: int = 4096) -> str:
    """The last non-empty line of a (log) file, or ''."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            text = f.read().decode(errors="replace")
    except OSError:
        return ""
    lines = [ln.strip() for ln in re.split(r"[\r\n]", text) if ln.strip()]
    return lines[-1][:120] if lines else ""


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
    chosen = [
        o.path
        for o in rows
        if (not stages or o.rule in stages)
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
        self.out.write("\r\033[K" + line[: cols - 1])
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
    if rc != 0 and not prog.failed:
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
    rc = stream(cmd, camp, verbose=args.verbose or args.dry_run)
    return 1 if rc else 0


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
