rule fit:
    """Stage-1 fit: SDF surfels per frame, bubble-guided tracking, metric velocities."""
    input:
        ingest=f"{RESULTS}/{{session}}/ingest",
        masks=f"{RESULTS}/{{session}}/masks",
    output:
        surfels=f"{RESULTS}/{{session}}/fit/surfels.npz",
        bubbles=f"{RESULTS}/{{session}}/fit/bubbles.csv",
        summary=f"{RESULTS}/{{session}}/fit/summary.json",
    params:
        surfphase=SURFPHASE,
        settings=lambda wc: json.dumps(config["fit"]),
        device=config["device"],
        checkpoint=f"{RESULTS}/{{session}}/fit.ckpt",
        code=code_version("fit", "render", "commands/fit"),
    threads: config["threads"]
    resources:
        gpu=lambda wc: 1 if config["device"] == "cuda" else 0,
    log:
        "logs/fit/{session}.log",
    benchmark:
        "benchmarks/fit/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} fit --ingest {input.ingest:q} --masks {input.masks:q}"
        " --out $(dirname {output.surfels:q}) --checkpoint {params.checkpoint:q}"
        " --device {params.device} --threads {threads}"
        " --params-json {params.settings:q} > {log:q} 2>&1"


rule fit_stage2:
    """Stage-2 fit: stage 1 restarted from its frame-0 surfels, with the refined orbit
    views as extra supervision (inputs 1.0, near views 0.5, far views 0.25)."""
    input:
        ingest=f"{RESULTS}/{{session}}/ingest",
        masks=f"{RESULTS}/{{session}}/masks",
        stage1=f"{RESULTS}/{{session}}/fit/surfels.npz",
        views=f"{RESULTS}/{{session}}/views",
        refined=lambda wc: refined_views(wc.session),
    output:
        surfels=f"{RESULTS}/{{session}}/fit2/surfels.npz",
        bubbles=f"{RESULTS}/{{session}}/fit2/bubbles.csv",
        summary=f"{RESULTS}/{{session}}/fit2/summary.json",
    params:
        surfphase=SURFPHASE,
        fit=lambda wc: json.dumps(config["fit"]),
        settings=lambda wc: json.dumps(fit2_settings()),
        device=config["device"],
        refine_dir=f"{RESULTS}/{{session}}/refine",
        checkpoint=f"{RESULTS}/{{session}}/fit2.ckpt",
        code=code_version("fit", "render", "commands/fit"),
    threads: config["threads"]
    resources:
        gpu=lambda wc: 1 if config["device"] == "cuda" else 0,
    log:
        "logs/fit_stage2/{session}.log",
    benchmark:
        "benchmarks/fit_stage2/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} fit2 --ingest {input.ingest:q} --masks {input.masks:q}"
        " --stage1 $(dirname {input.stage1:q}) --views {input.views:q}"
        " --refine {params.refine_dir:q} --out $(dirname {output.surfels:q})"
        " --checkpoint {params.checkpoint:q} --device {params.device} --threads {threads}"
        " --fit-json {params.fit:q} --params-json {params.settings:q} > {log:q} 2>&1"
