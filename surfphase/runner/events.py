"""Snakemake's job events as JSON lines: a logger plugin, and the reader of its file.

Snakemake 9 passes every log record through its logger-plugin interface
(``snakemake-interface-logger-plugins``), each with an ``event`` (``LogEvent``) and the
event's fields as attributes: a job's rule, wildcards, outputs, logs and id when it is
scheduled (``job_info``), its id when it finishes (``job_finished``) or fails
(``job_error``), the done/total counts (``progress``) and the job counts of the run
(``run_info``). :class:`LogHandler` writes those, one JSON object per line, to the file
given by ``--logger-surfphase-events FILE``; ``surfphase run`` reads them for its
progress lines instead of Snakemake's human-readable text.

Snakemake finds a logger plugin as a top-level package named
``snakemake_logger_plugin_<name>`` (``pkgutil.iter_modules``; no entry points), so the
package ``snakemake_logger_plugin_surfphase`` next to ``surfphase`` re-exports the two
classes of this module, and ``surfphase run`` puts the folder holding it on the
``PYTHONPATH`` of the Snakemake it starts (an editable install is not seen by
``pkgutil``). Run by hand: ``snakemake --logger surfphase --logger-surfphase-events
FILE ...``.

Each line: ``{"event": ..., "time": seconds since the epoch, ...}`` with

- ``job_info``: ``jobid``, ``rule``, ``wildcards`` (mapping), ``output`` and ``log``
  (lists of paths, relative to the working folder);
- ``job_finished``: ``jobid``;
- ``job_error``: ``jobid``, ``rule``, ``log``;
- ``progress``: ``done``, ``total``;
- ``run_info``: ``total`` (jobs of the run) and ``stats`` (jobs per rule);
- ``submitted``: ``jobid``, ``external_jobid`` (a cluster executor's job id);
- ``nothing_to_do``: every requested output is up to date.

Two of these have no event in Snakemake: ``nothing_to_do`` is Snakemake's own message
constant (``snakemake.common.NOTHING_TO_BE_DONE_MSG``), and ``submitted`` is the SLURM
executor plugin's submission message (``Job J has been submitted with SLURM jobid N``),
the one place where this module reads a message's text.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass, field
from logging import LogRecord
from pathlib import Path
from typing import Any

from snakemake_interface_logger_plugins.base import LogHandlerBase
from snakemake_interface_logger_plugins.common import LogEvent
from snakemake_interface_logger_plugins.settings import LogHandlerSettingsBase

PLUGIN = "surfphase"  # snakemake --logger surfphase
EVENTS_FILE = Path(".surfphase") / "events.jsonl"  # in a campaign: its last run's events
EVENTS_OPTION = "--logger-surfphase-events"
_SUBMITTED = re.compile(r"^Job (\d+) has been submitted with \S+ jobid (\S+)")


def _paths(value: Any) -> list[str]:
    return [str(v) for v in (value or []) if str(v)]


def event_of(record: LogRecord) -> dict[str, Any] | None:
    """The JSON-ready event of one Snakemake log record, or None for other records."""
    event = getattr(record, "event", None)
    t = {"time": record.created}
    if event == LogEvent.JOB_INFO:
        wildcards = {str(k): str(v) for k, v in (getattr(record, "wildcards", None) or {}).items()}
        return {
            "event": "job_info",
            **t,
            "jobid": int(record.jobid),
            "rule": str(record.rule_name),
            "wildcards": wildcards,
            "output": _paths(getattr(record, "output", None)),
            "log": _paths(getattr(record, "log", None)),
        }
    if event == LogEvent.JOB_FINISHED:
        return {"event": "job_finished", **t, "jobid": int(record.job_id)}
    if event == LogEvent.JOB_ERROR:
        return {
            "event": "job_error",
            **t,
            "jobid": int(record.jobid),
            "rule": str(record.rule_name),
            "log": _paths(getattr(record, "log", None)),
        }
    if event == LogEvent.PROGRESS:
        return {"event": "progress", **t, "done": int(record.done), "total": int(record.total)}
    if event == LogEvent.RUN_INFO:
        stats = {str(k): int(v) for k, v in (getattr(record, "stats", None) or {}).items()}
        return {"event": "run_info", **t, "total": stats.get("total", 0), "stats": stats}
    if event is None:
        from snakemake.common import NOTHING_TO_BE_DONE_MSG

        msg = record.getMessage() if record.msg is not None else ""
        if msg == NOTHING_TO_BE_DONE_MSG:
            return {"event": "nothing_to_do", **t}
        if m := _SUBMITTED.match(msg):
            return {"event": "submitted", **t, "jobid": int(m.group(1)), "external_jobid": m[2]}
    return None


@dataclass
class LogHandlerSettings(LogHandlerSettingsBase):
    """``--logger-surfphase-events FILE``: where the events go (appended)."""

    events: str | None = field(
        default=None,
        metadata={
            "help": "JSON-lines file the job events are appended to",
            "type": str,  # the annotation is a string here (postponed annotations)
            "required": True,
        },
    )


class LogHandler(LogHandlerBase):
    """Appends each job event to the events file, one JSON line, flushed at once."""

    def __post_init__(self) -> None:
        path = Path(str(self.settings.events))  # type: ignore[union-attr]
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(path, "a", encoding="utf-8")  # noqa: SIM115 (closed in close())

    def emit(self, record: LogRecord) -> None:
        try:
            event = event_of(record)
            if event is not None:
                self._file.write(json.dumps(event) + "\n")
                self._file.flush()
        except Exception:  # a logging handler must not raise into Snakemake
            self.handleError(record)

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
        super().close()

    @property
    def writes_to_stream(self) -> bool:
        return False

    @property
    def writes_to_file(self) -> bool:
        return False  # an events file, not a log: not listed as Snakemake's log

    @property
    def has_filter(self) -> bool:
        return True  # every record reaches emit(), which keeps the job events

    @property
    def has_formatter(self) -> bool:
        return True

    @property
    def needs_rulegraph(self) -> bool:
        return False


class EventFile:
    """Reads an events file as it grows: :meth:`new` returns the events appended since the
    last call (a line still being written waits for the next call)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.offset = 0

    def new(self) -> list[dict[str, Any]]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read()
        except OSError:
            return []
        end = data.rfind(b"\n") + 1
        self.offset += end
        events = []
        for line in data[:end].splitlines():
            try:
                events.append(json.loads(line))
            except ValueError:
                continue  # not ours: skip it rather than stop the run's display
        return events


def running_jobs(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The ``job_info`` events of the jobs that neither finished nor failed since."""
    running: dict[int, dict[str, Any]] = {}
    for ev in events:
        if ev.get("event") == "job_info":
            running[int(ev["jobid"])] = ev
        elif ev.get("event") in ("job_finished", "job_error"):
            running.pop(int(ev["jobid"]), None)
    return list(running.values())


def logger_args(events: Path) -> list[str]:
    """The Snakemake options that write the job events to ``events``."""
    return ["--logger", PLUGIN, EVENTS_OPTION, str(events)]


def now() -> float:
    """Seconds since the epoch (the clock of the events' ``time``)."""
    return time.time()
