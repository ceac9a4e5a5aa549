"""Read and validate the campaign: config, sessions sheet, rigs sheet.

Relative paths inside a sheet are resolved against that sheet's own folder, so a
campaign folder (sheets + videos) can be moved as a whole.

Problems that concern one session only (an unknown rig, a missing video) are not
raised here: that session's first job fails with a message naming the session and the
file, and ``--keep-going`` lets the other sessions finish. Problems with a whole sheet
(unreadable, a missing column, duplicate ids) stop the workflow before any job runs.
"""

import hashlib
import json
import os
import shlex
import sys
from pathlib import Path

import pandas as pd
import surfphase
from snakemake.exceptions import WorkflowError
from snakemake.settings.types import DeploymentMethod
from snakemake.utils import min_version, validate

min_version("8.0")

validate(config, schema="../schemas/config.schema.yaml")

RESULTS = config["results"].rstrip("/")
# Jobs call the Python that runs Snakemake; with `--sdm conda` each job runs inside
# envs/surfphase.yaml's environment instead, so they call that environment's python.
IN_CONDA = DeploymentMethod.CONDA in workflow.deployment_settings.deployment_method
SURFPHASE = config.get("surfphase_command") or (
    "python -m surfphase" if IN_CONDA else f"{shlex.quote(sys.executable)} -m surfphase"
)
PACKAGE_DIR = Path(surfphase.__file__).parent  # the package the jobs run


def read_sheet(path, key, schema, numeric=()):
    """Read a TSV sheet, check its columns with a JSON schema, index it by ``key``.

    Cells are read as text; the columns in ``numeric`` are converted to numbers first.
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
    for col in numeric:
        if col in df.columns:
            try:
                df[col] = pd.to_numeric(df[col])
            except ValueError as e:
                raise WorkflowError(f"{path}: column '{col}' must be numeric ({e})") from e
    try:
        validate(df, schema=schema, set_default=True)
    except WorkflowError as e:
        raise WorkflowError(f"{path}: invalid sheet\n{e}") from e
    dup = df[key][df[key].duplicated()].tolist()
    if dup:
        raise WorkflowError(f"{path}: duplicate {key} ids: {', '.join(dup)}")
    df = df.set_index(key, drop=False)
    df.attrs["path"] = str(path)
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
    cols = [c for c in df.columns if c.startswith("cam") and c[3:].isdigit()]
    return sorted(cols, key=lambda c: int(c[3:]))


sessions = read_sheet(
    config["sessions"], "session", "../schemas/sessions.schema.yaml", numeric=["fps"]
)
rigs = read_sheet(config["rigs"], "rig", "../schemas/rigs.schema.yaml")

SESSIONS = sessions["session"].tolist()
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
    """The rig's calibration, when the session's rig is a row of rigs.tsv."""
    if not rig_is_known(wc.session):
        return []
    return f"{RESULTS}/calib/{session_rig(wc.session)}/cameras.json"


# Refinement on: novel views → prior → refined views → stage-2 fit, whose surfels are the
# final result. Off (the "no refinement" ablation): the stage-1 fit is final.
REFINE = bool(config.get("refine", {}).get("enabled", False))
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
    far = (config.get("refine") or {}).get("far_views")
    if far is not None:
        settings.setdefault("far_views", far)
    return settings
