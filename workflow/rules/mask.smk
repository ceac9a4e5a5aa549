rule mask:
    """Bubble instance masks per camera, associated across views and time."""
    input:
        f"{RESULTS}/{{session}}/ingest",
    output:
        directory(f"{RESULTS}/{{session}}/masks"),
    params:
        surfphase=SURFPHASE,
        settings=lambda wc: json.dumps(config["masks"]),
        code=code_version("masks", "commands/mask"),
    log:
        "logs/mask/{session}.log",
    benchmark:
        "benchmarks/mask/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} mask --ingest {input:q} --out {output:q}"
        " --params-json {params.settings:q} > {log:q} 2>&1"
