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
REGION_SCALE = float((config.get("evaluate") or {}).get("region_scale", 1.5))


wildcard_constraints:
    ablation="|".join(ABLATION_SETTINGS),


def ablation_fit(session, ablation, name="surfels.npz"):
    """A file of an ablation's fit of a session."""
    return f"{RESULTS}/{session}/ablations/{ablation}/fit/{name}"


def evaluate_comparison_inputs(wc):
    """The fits scored beside the final one: stage 1 (when refinement makes the final fit
    stage 2) and every configured ablation."""
    extra = {}
    if REFINE:
        extra["fit_stage1"] = f"{RESULTS}/{wc.session}/fit/surfels.npz"
    for a in ABLATIONS:
        extra[f"ablation_{a}"] = ablation_fit(wc.session, a)
    return extra


def evaluate_comparison_args(wc, input):
    """``--fit-stage1 DIR`` and ``--ablation NAME=DIR`` for the inputs above."""
    args = []
    if "fit_stage1" in input.keys():
        args.append(f"--fit-stage1 {shlex.quote(os.path.dirname(input.fit_stage1))}")
    for a in ABLATIONS:
        folder = os.path.dirname(input[f"ablation_{a}"])
        args.append(f"--ablation {shlex.quote(f'{a}={folder}')}")
    return " ".join(args)
