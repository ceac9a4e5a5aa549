rule mesh:
    """One mesh per frame (TSDF fusion of rendered depth, marching cubes), with velocity."""
    input:
        fit=f"{RESULTS}/{{session}}/fit/surfels.npz",
        ingest=f"{RESULTS}/{{session}}/ingest",
    output:
        directory(f"{RESULTS}/{{session}}/mesh"),
    params:
        surfphase=SURFPHASE,
        settings=lambda wc: json.dumps(config["mesh"]),
        device=config["device"],
        code=code_version("mesh", "render", "fit", "commands/mesh"),
    threads: config["threads"]
    log:
        "logs/mesh/{session}.log",
    benchmark:
        "benchmarks/mesh/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} mesh --fit $(dirname {input.fit:q}) --ingest {input.ingest:q}"
        " --out {output:q} --device {params.device} --params-json {params.settings:q}"
        " > {log:q} 2>&1"
