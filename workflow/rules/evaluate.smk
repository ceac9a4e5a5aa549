# Evaluation of every session (held-out views, velocities against the truth or the 2D
# reference, Chamfer), the ablation fits it compares, and the campaign table.


include: "evaluate_common.smk"


rule fit_ablation:
    """An ablation's stage-1 fit: the fit settings with one part switched off."""
    input:
        ingest=f"{RESULTS}/{{session}}/ingest",
        masks=f"{RESULTS}/{{session}}/masks",
    output:
        surfels=ablation_fit("{session}", "{ablation}"),
        bubbles=ablation_fit("{session}", "{ablation}", "bubbles.csv"),
        summary=ablation_fit("{session}", "{ablation}", "summary.json"),
    params:
        surfphase=SURFPHASE,
        settings=lambda wc: json.dumps(
            {**config["fit"], **ABLATION_SETTINGS[wc.ablation]}
        ),
        device=config["device"],
        checkpoint=f"{RESULTS}/{{session}}/ablations/{{ablation}}/fit.ckpt",
        code=code_version("fit", "render", "commands/fit"),
    threads: config["threads"]
    resources:
        gpu=lambda wc: 1 if config["device"] == "cuda" else 0,
    log:
        "logs/fit_ablation/{session}.{ablation}.log",
    benchmark:
        "benchmarks/fit_ablation/{session}.{ablation}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} fit --ingest {input.ingest:q} --masks {input.masks:q}"
        " --out $(dirname {output.surfels:q}) --checkpoint {params.checkpoint:q}"
        " --device {params.device} --threads {threads}"
        " --params-json {params.settings:q} > {log:q} 2>&1"


rule evaluate:
    """Held-out views (full frame and the bubbles' region), bubble velocities (method,
    two-view baseline, stage 1, ablations) against the truth."""
    input:
        unpack(evaluate_inputs),
        unpack(evaluate_comparison_inputs),
    output:
        metrics=f"{RESULTS}/{{session}}/evaluate/metrics.json",
        baseline=f"{RESULTS}/{{session}}/evaluate/baseline_bubbles.csv",
        velocities=f"{RESULTS}/{{session}}/evaluate/velocity_table.csv",
        bubbles=f"{RESULTS}/{{session}}/evaluate/bubbles.csv",
    params:
        surfphase=SURFPHASE,
        gt=lambda wc, input: f"--gt {shlex.quote(input.gt)}" if "gt" in input.keys() else "",
        compare=evaluate_comparison_args,
        region_scale=REGION_SCALE,
        device=config["device"],
        code=code_version("eval", "render", "fit", "commands/evaluate"),
    log:
        "logs/evaluate/{session}.log",
    benchmark:
        "benchmarks/evaluate/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} evaluate --session {wildcards.session} --ingest {input.ingest:q}"
        " --masks {input.masks:q} --fit $(dirname {input.fit:q}) {params.gt}"
        " --meshes {input.meshes:q} {params.compare}"
        " --region-scale {params.region_scale}"
        " --device {params.device} --out $(dirname {output.metrics:q}) > {log:q} 2>&1"


rule mesh_compare:
    """Meshes of stage 1 or an ablation (single job), for their Chamfer distance."""
    input:
        fit=lambda wc: compare_fit(wc.session, wc.name),
        ingest=f"{RESULTS}/{{session}}/ingest",
        masks=f"{RESULTS}/{{session}}/masks",
    output:
        directory(compare_mesh("{session}", "{name}")),
    wildcard_constraints:
        name="|".join(["stage1", *ABLATION_SETTINGS]),
    params:
        surfphase=SURFPHASE,
        settings=MESH_SETTINGS,
        device=config["device"],
        code=code_version("mesh", "render", "fit", "commands/mesh"),
    threads: config["threads"]
    log:
        "logs/mesh_compare/{session}.{name}.log",
    benchmark:
        "benchmarks/mesh_compare/{session}.{name}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} mesh --fit $(dirname {input.fit:q}) --ingest {input.ingest:q}"
        " --masks {input.masks:q}"
        " --out {output:q} --device {params.device} --threads {threads}"
        " --params-json {params.settings:q} > {log:q} 2>&1"


rule campaign_table:
    """One table of every session's metrics (pandas)."""
    input:
        expand(f"{RESULTS}/{{session}}/evaluate/metrics.json", session=SESSIONS),
    output:
        f"{RESULTS}/campaign/metrics.csv",
    params:
        surfphase=SURFPHASE,
        code=code_version("eval", "commands/evaluate"),
    log:
        "logs/campaign_table/all.log",
    benchmark:
        "benchmarks/campaign_table/all.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} campaign-table --metrics {input:q} --out {output:q} > {log:q} 2>&1"
