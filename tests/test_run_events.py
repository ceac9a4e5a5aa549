"""`surfphase run`'s job events: SurfPhase's logger plugin in a real Snakemake run
(found by Snakemake's own plugin search), the reader of its file, and the stage order
against the workflow's rules."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from surfphase.runner.events import EventFile, logger_args
from surfphase.runner.progress import new_log, plugin_path, snakemake_env, snakemake_logs
from surfphase.runner.status import STAGE_ORDER

ROOT = Path(__file__).resolve().parents[1]

TOY = """\
rule all:
    input: expand("out/{session}.txt", session=["a", "b"])

rule make:
    output: "out/{session}.txt"
    log: "logs/{session}.log"
    shell: "test {wildcards.session} != b && echo ok > {output} 2> {log} || (echo bad > {log}; exit 1)"
"""


def test_plugin_writes_the_job_events_of_a_real_run(tmp_path: Path):
    (tmp_path / "Snakefile").write_text(TOY)
    events = tmp_path / "events.jsonl"
    cmd = [sys.executable, "-m", "snakemake", "--cores", "1", "--keep-going"]
    before = snakemake_logs(tmp_path)
    res = subprocess.run(
        cmd + logger_args(events), cwd=tmp_path, env=snakemake_env(), capture_output=True
    )
    assert res.returncode == 1  # session b fails
    # Snakemake's own log of this run, as its last lines name it.
    log = new_log(tmp_path, before)
    assert log and f"Complete log(s): {log}" in res.stderr.decode()
    assert (tmp_path / "out/a.txt").is_file() and not (tmp_path / "out/b.txt").exists()
    evs = [json.loads(ln) for ln in events.read_text().splitlines()]
    info = {e["wildcards"].get("session"): e for e in evs if e["event"] == "job_info"}
    assert set(info) == {"a", "b"}  # `all` never runs: its input failed
    for s in ("a", "b"):
        assert info[s]["rule"] == "make" and info[s]["output"] == [f"out/{s}.txt"]
        assert info[s]["log"] == [f"logs/{s}.log"]
    finished = [e["jobid"] for e in evs if e["event"] == "job_finished"]
    errors = [e for e in evs if e["event"] == "job_error"]
    assert finished == [info["a"]["jobid"]]
    assert [(e["jobid"], e["rule"], e["log"]) for e in errors] == [
        (info["b"]["jobid"], "make", ["logs/b.log"])
    ]
    run_info = next(e for e in evs if e["event"] == "run_info")
    assert run_info["stats"] == {"make": 2, "all": 1, "total": 3}
    assert [(e["done"], e["total"]) for e in evs if e["event"] == "progress"] == [(1, 3)]
    times = [e["time"] for e in evs]
    assert times == sorted(times)
    # Nothing left to make for session a: Snakemake says so, and so does the file.
    again = tmp_path / "again.jsonl"
    subprocess.run(
        cmd + ["out/a.txt"] + logger_args(again), cwd=tmp_path, env=snakemake_env(), check=True
    )
    assert [json.loads(ln)["event"] for ln in again.read_text().splitlines()] == ["nothing_to_do"]


def test_snakemake_finds_the_plugin_by_its_name(monkeypatch):
    """With the environment `surfphase run` gives Snakemake, and no PYTHONPATH of its own
    (an editable install is invisible to Snakemake's search of sys.path)."""
    monkeypatch.delenv("PYTHONPATH", raising=False)
    assert plugin_path() == ROOT  # the top-level package beside surfphase/
    code = (
        "from snakemake_interface_logger_plugins.registry import LoggerPluginRegistry as R; "
        "print(R().get_plugin('surfphase').log_handler.__module__)"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd="/", env=snakemake_env(), capture_output=True, text=True
    )
    assert res.stdout.strip() == "surfphase.runner.events", res.stderr


def test_event_file_returns_whole_lines_as_they_come(tmp_path: Path):
    path = tmp_path / "events.jsonl"
    reader = EventFile(path)
    assert reader.new() == []  # not written yet
    path.write_text('{"event": "progress", "done": 1, "total": 2}\n{"event": "job_fi')
    assert reader.new() == [{"event": "progress", "done": 1, "total": 2}]
    with open(path, "a") as f:
        f.write('nished", "jobid": 4}\n')
    assert reader.new() == [{"event": "job_finished", "jobid": 4}]
    assert reader.new() == []


def test_stage_order_names_the_workflows_rules(tmp_path: Path):
    """Every stage of the status table's order is a rule of `snakemake --list-rules`
    (with `mesh: window` > 0 for the window rules), and every rule a job can run for
    a session or the campaign is ordered (`all` is no stage; the checkpoint that counts
    a session's frames for the windows is shown after the others)."""
    window = tmp_path / "window.yaml"  # the window rules exist only with windows
    window.write_text("mesh:\n  window: 2\n")
    res = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", "Snakefile", "--list-rules"]
        + ["--configfile", "config/config.yaml", str(window)],
        cwd=ROOT,
        env=snakemake_env(),
        capture_output=True,
        text=True,
        check=True,
    )
    rules = set(re.findall(r"^([a-z_0-9]+) ", res.stdout, flags=re.M))
    assert "mesh_window" in rules and "fit" in rules
    assert set(STAGE_ORDER) <= rules, set(STAGE_ORDER) - rules
    assert rules - set(STAGE_ORDER) == {"all", "mesh_frame_count"}


def test_status_shows_the_jobs_a_live_run_has_started(tmp_path: Path):
    """A stage whose job started and has not ended is running, not failed or pending;
    one that ended keeps the state Snakemake's summary gives it."""
    from surfphase.runner.events import running_jobs
    from surfphase.runner.status import format_status, mark_running

    events = [
        {"event": "job_info", "jobid": 1, "rule": "ingest", "output": ["res/s1/ingest"]},
        {
            "event": "job_info",
            "jobid": 2,
            "rule": "fit",
            "output": ["res/s1/fit/a", "res/s1/fit/b"],
        },
        {"event": "job_info", "jobid": 3, "rule": "ingest", "output": ["res/s2/ingest"]},
        {"event": "job_finished", "jobid": 1},
        {"event": "job_error", "jobid": 3, "rule": "ingest", "log": ["logs/ingest/s2.log"]},
    ]
    assert [e["jobid"] for e in running_jobs(events)] == [2]

    def cell(state):
        return {"state": state, "outputs": 1, "logs": ["logs/x.log"] if state == "failed" else []}

    table = {
        "s1": {"ingest": cell("done"), "fit": cell("pending")},
        "s2": {"ingest": cell("failed"), "fit": cell("pending")},
    }
    mark_running(table, running_jobs(events), "res")
    assert {u: {s: c["state"] for s, c in cells.items()} for u, cells in table.items()} == {
        "s1": {"ingest": "done", "fit": "running"},
        "s2": {"ingest": "failed", "fit": "pending"},
    }
    text = format_status(table, tmp_path)
    assert text.splitlines()[1].split() == ["s1", "done", "running"]
    assert "stages: 1 done, 1 failed, 0 outdated, 1 pending, 1 running" in text


def test_a_cluster_submission_is_an_event():
    """The SLURM executor's submission message (its text, as
    snakemake_executor_plugin_slurm logs it) is the one message read for an event."""
    import logging

    from surfphase.runner.events import event_of

    msg = "Job 3 has been submitted with SLURM jobid 17 (log: /c/.snakemake/slurm_logs/x.log)."
    rec = logging.LogRecord("snakemake", logging.INFO, __file__, 1, msg, None, None)
    ev = event_of(rec)
    assert ev == {"event": "submitted", "time": rec.created, "jobid": 3, "external_jobid": "17"}
    other = logging.LogRecord("snakemake", logging.INFO, __file__, 1, "Select jobs", None, None)
    assert event_of(other) is None
