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
