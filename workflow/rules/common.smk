"""Read and validate the campaign: config, sessions sheet, rigs sheet.

Relative paths inside a sheet are resolved against that sheet's own folder, so a
campaign folder (sheets + videos) can be moved as a whole.

Problems that concern one session only (an unknown rig, a missing video, a bad cell of
its row in the sessions sheet: a non-numeric fps, a malformed frame range) are not raised
here: that session's first job fails with a message naming the session, the file and
the column, and ``--keep-going`` lets the other sessions finish. Problems with a whole
sheet (unreadable, a missing column, a bad or duplicate id) and with the config (it is
campaign-wide) stop the workflow before any job runs, in one line per problem.
"""

import hashlib
import json
import math
import os
import shlex
import sys
from pathlib import Path

import jsonschema
import pandas as pd
import surfphase
import yaml
from snakemake.exceptions import WorkflowError
from snakemake.settings.types import DeploymentMethod
from snakemake.utils import min_version, validate
from surfphase.settings import key_hint, text_for_numbers, unknown_keys
from surfphase.sheets import camera_columns as sheet_camera_columns
from surfphase.views_params import REFINE_DEFAULTS

min_version("8.0")



def config_problems(cfg, schema_file):
    """One line per problem of the config (``section.key: why``), or '' when none."""
    schema = yaml.safe_load((Path(workflow.current_basedir) / schema_file).read_text())
    lines = []
    for err in sorted(
        jsonschema.Draft202012Validator(schema).iter_errors(cfg), key=lambda e: list(e.path)
    ):
        where = ".".join(str(k) for k in err.path) or "(top level)"
        lines.append(f"config {where}: {err.message}")
    return "\n".join(lines)


def stage_key_problems(cfg):
    """One line per key of a stage's block of the config that the stage does not know
    (``config fit.iters_frist: unknown key (did you mean iters_first?)``).

    The schema leaves these blocks open: their keys are the stages' ``DEFAULTS``, read
    here without importing torch or OpenCV (``surfphase.fit.params``,
    ``surfphase.masks.params``, ``surfphase.mesh.params``).
    """
    from surfphase.fit.params import DEFAULTS as FIT_DEFAULTS
    from surfphase.fit.params import STAGE2_DEFAULTS
    from surfphase.masks.params import DEFAULTS as MASKS_DEFAULTS
    from surfphase.mesh.params import DEFAULTS as MESH_DEFAULTS

    known = {  # section: (its keys, where they are documented)
        "masks": (MASKS_DEFAULTS, "surfphase.masks.stage.DEFAULTS"),
        "fit": (FIT_DEFAULTS, "surfphase.fit.stage.DEFAULTS"),
        # fit keys in fit2: override fit: for stage 2
        "fit2": ({**FIT_DEFAULTS, **STAGE2_DEFAULTS}, "surfphase.fit.stage2.DEFAULTS and fit"),
        # window: how mesh jobs are cut (mesh.smk); the stage never sees it
        "mesh": ({**MESH_DEFAULTS, "window": 0}, "surfphase.mesh.stage.DEFAULTS"),
    }
    lines = []
    for section, (defaults, see) in known.items():
        given = cfg.get(section)
        if not isinstance(given, dict):
            continue  # absent, or not a mapping: the schema says so
        for key in unknown_keys(defaults, given, section):
            lines.append(f"config {key}: unknown key ({key_hint(defaults, key, see)})")
        lines += [f"config {line}" for line in text_for_numbers(defaults, given, section)]
    return lines


# The config is campaign-wide: any problem stops the whole workflow, in one line each.
try:
    validate(config, schema="../schemas/config.schema.yaml")  # also sets the defaults
    schema_problems = ""
except WorkflowError as e:
    schema_problems = config_problems(config, "../schemas/config.schema.yaml") or str(e)
config_lines = [*filter(None, [schema_problems]), *stage_key_problems(config)]
if config_lines:
    raise WorkflowError("\n".join(config_lines))

RESULTS = config["results"].rstrip("/")
# Jobs call the Python that runs Snakemake; with `--sdm conda` each job runs inside
# envs/surfphase.yaml's environment instead, so they call that environment's python.
IN_CONDA = DeploymentMethod.CONDA in workflow.deployment_settings.deployment_method
SURFPHASE = config.get("surfphase_command") or (
    "python -m surfphase" if IN_CONDA else f"{shlex.quote(sys.executable)} -m surfphase"
)
PACKAGE_DIR = Path(surfphase.__file__).parent  # the package the jobs run


def _cell_problems(row, schema, numeric):
    """Problems of one sheet row (``{column: text}``) against the row's JSON schema.

    Returns ``(row, ["column 'c': why", ...])``: the row with its valid numeric cells
    converted; its other cells, valid or not, are left as text.
    """
    text, row, problems, bad = dict(row), dict(row), [], set()
    for col in numeric:
        if col not in row:
            continue
        try:
            value = pd.to_numeric(row[col])
            ok = math.isfinite(float(value))
        except (ValueError, TypeError):
            ok = False
        if ok:
            row[col] = value
        else:
            problems.append(f"column '{col}': {row[col]!r} is not a number")
            bad.add(col)
    checked = {k: float(v) if k in numeric else v for k, v in row.items() if k not in bad}
    validator = jsonschema.Draft202012Validator(schema)
    for err in sorted(validator.iter_errors(checked), key=lambda e: list(e.path)):
        if not err.path:
            continue  # a missing column: checked for the whole sheet
        col = err.path[0]
        what = schema.get("properties", {}).get(col, {}).get("description", "")
        why = {
            "exclusiveMinimum": f"must be greater than {err.validator_value}",
            "minimum": f"must be at least {err.validator_value}",
            "pattern": f"does not match {err.validator_value}",
        }.get(err.validator, err.message)
        problems.append(f"column '{col}': {text[col]!r} {why}" + (f" ({what})" if what else ""))
    return row, problems


def read_sheet(path, key, schema, numeric=(), row_problems="keep"):
    """Read a TSV sheet, check it with a JSON schema, index it by ``key``.

    Cells are read as text; the columns in ``numeric`` are converted to numbers. Each
    row is checked on its own. The whole sheet is refused (WorkflowError, one line per
    problem) when it is unreadable, lacks a required column, or has a bad or duplicate
    id. Other problems of a row are the row's own: with ``row_problems="keep"`` they are
    kept in ``df.attrs["row_problems"]`` (``{id: message}``) and that row's jobs fail
    (rule ``session_sheet``); with ``"fail"`` they refuse the sheet too.
    """
    path = Path(path)
    if not path.is_file():
        raise WorkflowError(f"{path}: sheet not found (set '{key}s' in the config)")
    try:
        df = pd.read_csv(path, sep="\t", dtype=str, comment="#", keep_default_na=False)
    except (pd.errors.ParserError, UnicodeDecodeError) as e:
        raise WorkflowError(f"{path}: not a readable TSV sheet ({e})") from e
    df.columns = [c.strip() for c in df.columns]
    for col in df.columns:
        df[col] = df[col].str.strip()
    schema_path = Path(workflow.current_basedir) / schema
    schema = yaml.safe_load(schema_path.read_text())
    missing = [c for c in schema.get("required", []) if c not in df.columns]
    if missing:
        raise WorkflowError(
            f"{path}: missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
            f"(required: {', '.join(schema['required'])}; the sheet has: "
            f"{', '.join(df.columns) or 'no columns'}; see {schema_path.name})"
        )
    for col, prop in schema.get("properties", {}).items():
        if col not in df.columns and "default" in prop:
            df[col] = str(prop["default"])
    key_schema = {"type": "object", "properties": {key: schema["properties"][key]}}
    # The file's line of each row (pandas skips comment and blank lines).
    text_lines = path.read_text(errors="replace").splitlines()
    lines = [i + 1 for i, ln in enumerate(text_lines) if ln.split("#", 1)[0].strip()][1:]
    if len(lines) != len(df):
        lines = [None] * len(df)
    problems, rows = {}, []
    for k, rec in enumerate(df.to_dict("records")):
        where = f"line {lines[k]}" if lines[k] else f"row {k + 1}"
        ident = rec[key]
        for err in jsonschema.Draft202012Validator(key_schema).iter_errors(rec):
            raise WorkflowError(
                f"{path}: {where}: {key} id {ident!r} is not valid ({err.message}; "
                f"{schema['properties'][key].get('description', '')})"
            )
        rec, why = _cell_problems(rec, schema, numeric)
        rows.append(rec)
        if why:
            problems[ident] = f"{path}: {key} {ident} ({where}): " + "; ".join(why)
    dup = df[key][df[key].duplicated()].tolist()
    if dup:
        raise WorkflowError(f"{path}: duplicate {key} ids: {', '.join(dup)}")
    if problems and row_problems == "fail":
        raise WorkflowError("\n".join(problems.values()))
    for col in numeric:
        if col not in df.columns:
            continue
        good = [r[key] not in problems for r in rows]
        if all(good):
            df[col] = pd.to_numeric(df[col])
        else:  # the valid cells converted together (one dtype), the others left as text
            values = iter(pd.to_numeric(df.loc[good, col]).to_numpy())
            cells = [next(values) if g else r[col] for g, r in zip(good, rows, strict=True)]
            df[col] = pd.Series(cells, index=df.index, dtype=object)
    df = df.set_index(key, drop=False)
    df.attrs["path"] = str(path)
    df.attrs["row_problems"] = problems
    return df


def resolve(sheet, value):
    """A path written in ``sheet``: absolute, or relative to the sheet's folder."""
    if not value:
        return ""
    p = Path(value)
    if not p.is_absolute():
        p = Path(sheet.attrs["path"]).parent / p
    return os.path.normpath(p)


def camera_columns(df):
    """Camera columns ``cam0, cam1, ...`` in numeric order."""
    return sheet_camera_columns(df.columns)


sessions = read_sheet(
    config["sessions"], "session", "../schemas/sessions.schema.yaml", numeric=["fps"]
)
rigs = read_sheet(config["rigs"], "rig", "../schemas/rigs.schema.yaml", row_problems="fail")

SESSIONS = sessions["session"].tolist()
# Sessions whose row of the sessions sheet is invalid: {session: why} (rule session_sheet).
SESSION_PROBLEMS = sessions.attrs["row_problems"]
RIGS = rigs["rig"].tolist()


wildcard_constraints:
    session="|".join(SESSIONS) or "NO_SESSION",
    rig="|".join(RIGS) or "NO_RIG",


def session_cameras(session):
    """``{camera: video path}`` of a session (cameras with an empty cell are absent)."""
    row = sessions.loc[session]
    return {c: resolve(sessions, row[c]) for c in camera_columns(sessions) if row[c]}


def rig_cameras(rig):
    """``{camera: calibration folder}`` of a rig."""
    row = rigs.loc[rig]
    return {c: resolve(rigs, row[c]) for c in camera_columns(rigs) if row[c]}


def session_rig(session):
    return sessions.loc[session, "rig"]


def rig_is_known(session):
    return session_rig(session) in rigs.index


def cam_args(mapping):
    """``--cam name=path`` arguments, shell-quoted."""
    return " ".join(f"--cam {shlex.quote(f'{k}={v}')}" for k, v in mapping.items())


def existing(paths):
    """The paths that exist (missing ones are reported by the job, naming the session)."""
    return [p for p in paths if p and os.path.exists(p)]


def code_version(*packages):
    """A hash of the package version and the sources of ``packages`` (e.g. ``"calib"``).

    Used in ``params:`` so that a change of a stage's code reruns that stage.
    """
    h = hashlib.sha256()
    files = [PACKAGE_DIR / "__init__.py", PACKAGE_DIR / "cameras.py", PACKAGE_DIR / "io.py"]
    for pkg in packages:
        p = PACKAGE_DIR / pkg
        files += sorted(p.rglob("*.py")) if p.is_dir() else [p.with_suffix(".py")]
    found = [f for f in files if f.is_file()]
    if len(found) < 4:
        raise WorkflowError(f"code_version{packages}: sources not found under {PACKAGE_DIR}")
    for f in found:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def ingest_cameras(wc):
    """The rig's calibration, when the session's rig is a row of rigs.tsv.

    A session whose row of the sessions sheet is invalid gets the output of rule
    ``session_sheet`` instead: that job fails with the problem, and the session's ingest
    (and every later stage) does not run, while the other sessions go on.
    """
    if wc.session in SESSION_PROBLEMS:
        return f"{RESULTS}/{wc.session}/sheet_row.ok"
    if not rig_is_known(wc.session):
        return []
    return f"{RESULTS}/calib/{session_rig(wc.session)}/cameras.json"


# Refinement on: novel views → prior → refined views → stage-2 fit, whose surfels are the
# final result. Off (the "no refinement" ablation): the stage-1 fit is final.
REFINE = bool({**REFINE_DEFAULTS, **(config.get("refine") or {})}["enabled"])
FINAL_FIT = "fit2" if REFINE else "fit"


def final_fit(session, name="surfels.npz"):
    """A file of the session's final fit (stage 2 with refinement, else stage 1)."""
    return f"{RESULTS}/{session}/{FINAL_FIT}/{name}"


def evaluate_inputs(wc):
    """Stage outputs the evaluation reads, plus the session's ground truth if it has one."""
    inputs = {
        "ingest": f"{RESULTS}/{wc.session}/ingest",
        "masks": f"{RESULTS}/{wc.session}/masks",
        "fit": final_fit(wc.session),
        "meshes": f"{RESULTS}/{wc.session}/mesh",
    }
    gt = resolve(sessions, sessions.loc[wc.session].get("gt", ""))
    if gt and os.path.isdir(gt):
        inputs["gt"] = gt
    return inputs


def fit2_settings():
    """Stage-2 settings (config ``fit2:``); the far views default to ``refine.far_views``."""
    settings = dict(config.get("fit2") or {})
    settings.setdefault("far_views", REFINE_SETTINGS["far_views"])
    return settings


# The rule that fails a session whose row of the sessions sheet is invalid.
include: "sheet.smk"
