"""Settings and helpers of the novel-view, prior and refinement rules (views.smk).

Config blocks ``prior`` (clips, backend, per-backend parameters, Wan weights folder) and
``refine`` (orbit views, SDEdit strengths per view, seed), whose defaults are
``surfphase.views_params.REFINE_DEFAULTS``.
"""
import glob as _glob

PRIOR = config["prior"]  # the schema fills in its defaults
REFINE_SETTINGS = {**REFINE_DEFAULTS, **(config.get("refine") or {})}
N_VIEWS = int(REFINE_SETTINGS["n_views"])
ORBIT_VIEWS = [f"orbit{k:02d}" for k in range(1, N_VIEWS + 1)]


wildcard_constraints:
    view="orbit[0-9]+",


def refined_views(session, suffix=".npy"):
    """The refined videos of a session, one per orbit view (``.npy`` or ``.mp4``)."""
    return [f"{RESULTS}/{session}/refine/{v}{suffix}" for v in ORBIT_VIEWS]


def views_settings():
    """``surfphase render-views`` parameters from the ``refine`` block."""
    return {
        "n_views": N_VIEWS,
        "step_deg": float(REFINE_SETTINGS["step_deg"]),
        "reference": REFINE_SETTINGS["reference_camera"],
    }


def view_strength(view):
    """SDEdit strength of an orbit view: ``strength_far`` for the ``far_views`` numbers
    (those far from both input cameras), else ``strength_near``."""
    far = [int(k) for k in REFINE_SETTINGS["far_views"]]
    key = "strength_far" if int(view[len("orbit") :]) in far else "strength_near"
    return float(REFINE_SETTINGS[key])


def prior_clips():
    """The clips setting (folder or glob), as given in the config; refinement needs it."""
    clips = PRIOR.get("clips")
    if not clips:
        raise WorkflowError(
            "refine: enabled: true needs prior: clips (a folder of monocular clips); "
            "set it, or set refine: enabled: false to make stage 1 the final fit"
        )
    return str(clips)


def prior_clip_inputs(wc):
    """Clip files/folders that exist (a missing folder is reported by the job, naming it)."""
    spec = prior_clips()
    if any(ch in spec for ch in "*?["):
        return sorted(_glob.glob(spec))
    return existing([spec])


def prior_settings():
    """Backend parameters: the backend's block, plus the local weights folder for Wan."""
    backend = PRIOR["backend"]
    settings = dict(PRIOR.get(backend) or {})
    if backend == "wan":
        settings["weights"] = PRIOR.get("wan_weights")
    settings.setdefault("seed", int(config["seed"]))
    return settings

