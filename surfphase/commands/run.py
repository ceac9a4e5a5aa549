"""``surfphase run`` and ``surfphase status``: the campaign workflow for users.

``surfphase run`` calls Snakemake on the project's Snakefile with a campaign folder
(one that holds ``config/config.yaml``) and one of the project's profiles
(``workflow/profiles/local`` or, with ``--cluster slurm``, ``workflow/profiles/slurm``
plus the account and partitions from the campaign's ``slurm:`` config). Its output is a
line per job (started, done, failed, with the job's log), and, on a terminal, a line
that shows the running jobs, their elapsed time and the last line of their logs, both
from the job events Snakemake's logger-plugin interface gives SurfPhase's plugin
(:mod:`surfphase.runner.events`), not from Snakemake's text.

``surfphase status`` asks Snakemake (``--detailed-summary``: every output file of the
campaign's DAG, its rule and whether it is up to date) and tells per session and stage
whether it is done, failed (outputs missing, log present), outdated (code, params or
inputs changed) or pending; while ``surfphase run`` runs, the stages of the jobs its
events say have started and not ended are running. It never re-implements the DAG.

After a kill: ``status`` tells a stale lock (no Snakemake process works in the
campaign) from a live run, and ``run`` says the previous run was killed, releases the
stale lock and resumes. After a run in which sessions failed, ``run`` writes the
campaign table and page of the sessions that finished, listing the failed ones with
their error, dated so that Snakemake rewrites them on the next run.

This module holds the command lines and the targets; the work is in
:mod:`surfphase.runner` (its names are re-exported here).
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

from surfphase.runner.locate import (
    PROFILES,
    campaign_dir,
    find_snakefile,
    project_root,
    read_config,
    slurm_profile,
    snakemake_base,
)
from surfphase.runner.locks import (
    RUN_FILE,
    lock_files,
    lock_note,
    lock_state,
    previous_run_killed,
    read_run_file,
    record_run,
    release_stale_lock,
    snakemake_processes,
)
from surfphase.runner.partial import campaign_sessions, partial_campaign, session_outcomes
from surfphase.runner.progress import Progress, stream, with_events
from surfphase.runner.status import (
    STAGE_ORDER,
    OutputState,
    campaign_status,
    detailed_summary,
    failure_lines,
    format_status,
    last_line,
    middle_cut,
    output_state,
    stage_columns,
    unit_of,
)

__all__ = [
    "PROFILES",
    "RUN_FILE",
    "STAGE_ORDER",
    "OutputState",
    "Progress",
    "build_run_command",
    "campaign_dir",
    "campaign_sessions",
    "campaign_status",
    "detailed_summary",
    "failure_lines",
    "find_snakefile",
    "format_status",
    "last_line",
    "lock_files",
    "lock_note",
    "lock_state",
    "middle_cut",
    "output_state",
    "partial_campaign",
    "previous_run_killed",
    "project_root",
    "read_config",
    "read_run_file",
    "record_run",
    "release_stale_lock",
    "resolve_targets",
    "run_cmd",
    "session_outcomes",
    "slurm_profile",
    "snakemake_base",
    "snakemake_processes",
    "stage_columns",
    "status_cmd",
    "stream",
    "unit_of",
]


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
    cmd, events = with_events(cmd, camp)
    try:
        rc = stream(cmd, camp, verbose=args.verbose or events is None, events=events)
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
        "(code, parameters or inputs changed: will rerun), pending, or running (a job "
        "`surfphase run` has started). Asks Snakemake.",
    )
    _common(s)
    s.add_argument("--json", action="store_true", help="print the table as JSON")
    s.set_defaults(func=status_cmd)
