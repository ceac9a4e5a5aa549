"""Settings and helpers of the mesh rules (mesh.smk): frame windows of long sessions.

``mesh: window: N`` (N > 0) splits a session's fitted frames into windows of N frames.
The number of windows comes from the sessions sheet's ``frames`` column when it gives a
stop (start:stop[:step]); otherwise from the ingest's frame count, read after ingest by
the checkpoint ``mesh_frame_count``.
"""

from surfphase.mesh.windows import fitted_frame_count, sheet_frame_count, window_count

MESH_WINDOW = int(config["mesh"].get("window") or 0)
# `window` decides how jobs are cut, not what a mesh is: the stage never sees it.
MESH_SETTINGS = json.dumps({k: v for k, v in config["mesh"].items() if k != "window"})


def mesh_sheet_frames(session):
    """Frames the fit of ``session`` will hold, if the sessions sheet tells; else None."""
    try:
        n = sheet_frame_count(sessions.loc[session].get("frames", ""))
    except ValueError:
        return None  # a bad range: the session's ingest job fails and says why
    if n is None:
        return None
    return fitted_frame_count(n, (config.get("fit") or {}).get("frames"))


def mesh_window_dirs(wc):
    """The window folders of a session (one per ``mesh: window`` frames)."""
    picks = config["mesh"].get("frames")
    n = len(picks) if picks is not None else mesh_sheet_frames(wc.session)
    if n is None:
        meta = checkpoints.mesh_frame_count.get(session=wc.session).output[0]
        with open(meta) as fh:
            n_ingested = len(json.load(fh)["frame_indices"])
        n = fitted_frame_count(n_ingested, (config.get("fit") or {}).get("frames"))
    return [
        f"{RESULTS}/{wc.session}/mesh_windows/{k}" for k in range(window_count(n, MESH_WINDOW))
    ]
