# Novel views of the stage-1 fit, the video prior (trained once per campaign) and the
# SDEdit refinement of every view (one job per session × view, so a cluster runs the views
# in parallel). The stage-2 fit reads R/<session>/views and every refined_views(session).


include: "views_common.smk"


rule render_views:
    """The stage-1 fit rendered into the orbit views: lossless frames, alpha, MP4."""
    input:
        fit=f"{RESULTS}/{{session}}/fit/surfels.npz",
        ingest=f"{RESULTS}/{{session}}/ingest",
    output:
        directory(f"{RESULTS}/{{session}}/views"),
    params:
        surfphase=SURFPHASE,
        settings=lambda wc: json.dumps(views_settings()),
        device=config["device"],
        code=code_version("views", "views_params", "render", "fit/outputs", "commands/views"),
    threads: config["threads"]
    log:
        "logs/render_views/{session}.log",
    benchmark:
        "benchmarks/render_views/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} render-views --fit {input.fit:q} --ingest {input.ingest:q}"
        " --out {output:q} --device {params.device} --threads {threads}"
        " --params-json {params.settings:q} > {log:q} 2>&1"


rule train_prior:
    """The video prior, trained (embedded) or LoRA-fine-tuned (Wan) once per campaign."""
    input:
        prior_clip_inputs,
    output:
        directory(f"{RESULTS}/prior"),
    params:
        surfphase=SURFPHASE,
        clips=lambda wc: prior_clips(),
        backend=PRIOR["backend"],
        settings=lambda wc: json.dumps(prior_settings()),
        device=config["device"],
        code=code_version("prior", "commands/prior"),
    threads: config["threads"]
    resources:
        gpu=lambda wc: 1 if config["device"] == "cuda" else 0,
    log:
        "logs/train_prior/prior.log",
    benchmark:
        "benchmarks/train_prior/prior.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} train-prior --clips {params.clips:q} --out {output:q}"
        " --backend {params.backend} --device {params.device} --threads {threads}"
        " --params-json {params.settings:q} > {log:q} 2>&1"


rule refine:
    """One orbit view refined by SDEdit with the prior (strength from the view number)."""
    input:
        views=f"{RESULTS}/{{session}}/views",
        prior=f"{RESULTS}/prior",
    output:
        npy=f"{RESULTS}/{{session}}/refine/{{view}}.npy",
        mp4=f"{RESULTS}/{{session}}/refine/{{view}}.mp4",
    params:
        surfphase=SURFPHASE,
        strength=lambda wc: view_strength(wc.view),
        seed=int(REFINE_SETTINGS["seed"]),
        device=config["device"],
        code=code_version("prior", "views", "views_params", "commands/prior"),
    threads: config["threads"]
    resources:
        gpu=lambda wc: 1 if config["device"] == "cuda" else 0,
    log:
        "logs/refine/{session}/{view}.log",
    benchmark:
        "benchmarks/refine/{session}/{view}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} refine --prior {input.prior:q} --views {input.views:q}"
        " --view {wildcards.view} --strength {params.strength} --seed {params.seed}"
        " --out $(dirname {output.npy:q}) --device {params.device} --threads {threads}"
        " > {log:q} 2>&1"
