"""Settings and helpers of the evaluate rules (evaluate.smk): the ablations (config
``evaluate: ablations``), the fits scored beside the final one, the bubble region.
"""

# Ablations: the stage-1 fit rerun with one part of the method switched off (config
# `evaluate: ablations`), scored by the evaluate rule beside the method; compare them with
# the method's stage-1 scores (`stage1` in metrics.json when refinement is on).
ABLATION_SETTINGS = {
    "no_sdf": {"use_sdf": False},  # opacities optimised directly, no SDF
    "no_guidance": {"guidance": False},  # plain per-frame refit, no bubble guidance
}
ABLATIONS = list((config.get("evaluate") or {}).get("ablations") or [])
_unknown_ablations = sorted(set(ABLATIONS) - set(ABLATION_SETTINGS))
if _unknown_ablations:
    raise WorkflowError(
        f"config evaluate.ablations: unknown {_unknown_ablations} "
        f"(known: {sorted(ABLATION_SETTINGS)})"
    )
REGION_SCALE = float(config["evaluate"]["region_scale"])  # the schema's default
# Meshes of stage 1 and the ablations too, for their Chamfer (sessions with ground truth):
# only with the fused surface, since the hull surface (mesh: surface: hull) is made from
# the masks alone and would be the same mesh for every fit.
from surfphase.mesh.params import DEFAULTS as _MESH_DEFAULTS

COMPARE_MESHES = bool(config["evaluate"]["compare_meshes"]) and (
    {**_MESH_DEFAULTS, **(config.get("mesh") or {})}["surface"] == "fused"
)


wildcard_constraints:
    ablation="|".join(ABLATION_SETTINGS),


def ablation_fit(session, ablation, name="surfels.npz"):
    """A file of an ablation's fit of a session."""
    return f"{RESULTS}/{session}/ablations/{ablation}/fit/{name}"


def compare_fit(session, name):
    """The surfels of a fit scored beside the final one: ``stage1`` or an ablation."""
    if name == "stage1":
        return f"{RESULTS}/{session}/fit/surfels.npz"
    return ablation_fit(session, name)


def compare_mesh(session, name):
    """The meshes of that fit (rule ``mesh_compare``)."""
    return f"{RESULTS}/{session}/compare/{name}/mesh"


def evaluate_comparison_inputs(wc):
    """The fits scored beside the final one: stage 1 (when refinement makes the final fit
    stage 2) and every configured ablation; with ground truth and ``evaluate:
    compare_meshes``, their meshes too."""
    extra = {}
    names = (["stage1"] if REFINE else []) + ABLATIONS
    if REFINE:
        extra["fit_stage1"] = compare_fit(wc.session, "stage1")
    for a in ABLATIONS:
        extra[f"ablation_{a}"] = ablation_fit(wc.session, a)
    if COMPARE_MESHES and "gt" in evaluate_inputs(wc):
        for name in names:
            extra[f"mesh_{name}"] = compare_mesh(wc.session, name)
    return extra


def evaluate_comparison_args(wc, input):
    """``--fit-stage1 DIR``, ``--ablation NAME=DIR`` and ``--compare-meshes NAME=DIR`` for
    the inputs above."""
    args = []
    if "fit_stage1" in input.keys():
        args.append(f"--fit-stage1 {shlex.quote(os.path.dirname(input.fit_stage1))}")
    for a in ABLATIONS:
        folder = os.path.dirname(input[f"ablation_{a}"])
        args.append(f"--ablation {shlex.quote(f'{a}={folder}')}")
    for key in input.keys():
        if key.startswith("mesh_"):
            args.append(f"--compare-meshes {shlex.quote(f'{key[5:]}={input[key]}')}")
    return " ".join(args)
