"""SurfPhase: a campaign of capture sessions → calibrated, metric 3D bubble interfaces.

Run from the project root (or with ``--directory`` pointing at a campaign folder that
holds ``config/config.yaml``):

    snakemake --cores 2                # everything for every session
    snakemake --cores 2 -n             # list the jobs
    snakemake --cores 2 --keep-going   # other sessions go on when one fails
"""


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/mask.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/views.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"


rule all:
    """Every stage that exists, for every rig and session of the campaign."""
    default_target: True
    input:
        expand(f"{RESULTS}/calib/{{rig}}/cameras.json", rig=RIGS),
        [final_fit(s, "bubbles.csv") for s in SESSIONS],
        f"{RESULTS}/campaign/metrics.csv",
        f"{RESULTS}/campaign/index.html",
