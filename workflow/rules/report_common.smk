"""Settings and helpers of the report rules (report.smk): mesh snapshots and novel-view
videos per session (config ``report``).
"""


# The schema fills in every key's default (workflow/schemas/config.schema.yaml).
REPORT = config["report"]
MESH_FRAMES = int(REPORT["mesh_frames"])


def novel_view_names():
    """The orbit views (``orbit01`` …) of the novel-view rules."""
    return ORBIT_VIEWS


def has_novel_views():
    """Whether the report shows novel-view videos (raw, and refined with refinement on):
    config ``report: videos`` and a workflow that renders them (rule render_views). With
    refinement off this still renders the raw views of the stage-1 fit for the report."""
    return bool(REPORT["videos"]) and rules.has("render_views")


def report_video_inputs(wc):
    inputs = {}
    if has_novel_views():
        inputs["views"] = f"{RESULTS}/{wc.session}/views"
        if REFINE:
            inputs["refined"] = [
                f"{RESULTS}/{wc.session}/refine/{v}.mp4" for v in novel_view_names()
            ]
    return inputs


def session_report_extras(wc):
    """Mesh snapshots and novel-view videos of every session, when there are any."""
    extras = {}
    if MESH_FRAMES > 0:
        extras["meshes"] = expand(f"{RESULTS}/{{session}}/report/meshes", session=SESSIONS)
    if has_novel_views():
        extras["videos"] = expand(f"{RESULTS}/{{session}}/report/videos.html", session=SESSIONS)
    if REFINE:  # the prior is trained only when the refinement is on
        extras["prior"] = f"{RESULTS}/prior"
    return extras
