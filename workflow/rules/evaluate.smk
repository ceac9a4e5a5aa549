rule evaluate:
    """Held-out views, bubble velocities (method and two-view baseline) against the truth."""
    input:
        unpack(evaluate_inputs),
    output:
        metrics=f"{RESULTS}/{{session}}/evaluate/metrics.json",
        baseline=f"{RESULTS}/{{session}}/evaluate/baseline_bubbles.csv",
        velocities=f"{RESULTS}/{{session}}/evaluate/velocity_table.csv",
    params:
        surfphase=SURFPHASE,
        gt=lambda wc, input: f"--gt {shlex.quote(input.gt)}" if "gt" in input.keys() else "",
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
        " --meshes {input.meshes:q}"
        " --device {params.device} --out $(dirname {output.metrics:q}) > {log:q} 2>&1"


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
