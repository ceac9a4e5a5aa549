report: "../report/workflow.rst"


include: "report_common.smk"


rule plots:
    """Per session: velocity over time per bubble (method, baseline, truth), metrics, masks."""
    input:
        fit=lambda wc: final_fit(wc.session, "bubbles.csv"),
        metrics=f"{RESULTS}/{{session}}/evaluate/metrics.json",
        baseline=f"{RESULTS}/{{session}}/evaluate/baseline_bubbles.csv",
        masks=f"{RESULTS}/{{session}}/masks",
        # the truth's bubbles.csv, when the session has a ground-truth folder
        gt=lambda wc: existing(
            [
                resolve(sessions, g and f"{g}/bubbles.csv")
                for g in [sessions.loc[wc.session].get("gt", "")]
            ]
        ),
    output:
        velocity=report(
            f"{RESULTS}/{{session}}/report/velocity.png",
            caption="../report/velocity.rst",
            category="Sessions",
            subcategory="{session}",
        ),
        metrics=report(
            f"{RESULTS}/{{session}}/report/metrics.html",
            caption="../report/metrics.rst",
            category="Sessions",
            subcategory="{session}",
        ),
        masks=report(
            directory(f"{RESULTS}/{{session}}/report/masks"),
            patterns=["{name}.png"],
            caption="../report/masks.rst",
            category="Sessions",
            subcategory="{session}",
        ),
    params:
        surfphase=SURFPHASE,
        gt=lambda wc, input: " ".join(f"--gt {shlex.quote(p)}" for p in input.gt),
        code=code_version("report", "commands/report"),
    log:
        "logs/plots/{session}.log",
    benchmark:
        "benchmarks/plots/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} plots --session {wildcards.session} --fit $(dirname {input.fit:q})"
        " --evaluate $(dirname {input.metrics:q}) --masks {input.masks:q} {params.gt}"
        " --out $(dirname {output.velocity:q}) > {log:q} 2>&1"


rule mesh_snapshots:
    """Per session: a few meshes drawn from the front and the side, coloured by speed."""
    input:
        meshes=f"{RESULTS}/{{session}}/mesh",
    output:
        report(
            directory(f"{RESULTS}/{{session}}/report/meshes"),
            patterns=["{name}.png"],
            caption="../report/meshes.rst",
            category="Sessions",
            subcategory="{session}",
        ),
    params:
        surfphase=SURFPHASE,
        frames=MESH_FRAMES,
        code=code_version("report", "commands/report"),
    log:
        "logs/mesh_snapshots/{session}.log",
    benchmark:
        "benchmarks/mesh_snapshots/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} mesh-snapshots --session {wildcards.session}"
        " --meshes {input.meshes:q} --frames {params.frames} --out {output:q} > {log:q} 2>&1"


rule report_videos:
    """Per session: the novel-view videos, raw renders beside refined ones, on one page."""
    input:
        unpack(report_video_inputs),
    output:
        videos=directory(f"{RESULTS}/{{session}}/report/videos"),
        page=report(
            f"{RESULTS}/{{session}}/report/videos.html",
            caption="../report/videos.rst",
            category="Sessions",
            subcategory="{session}",
        ),
    params:
        surfphase=SURFPHASE,
        views=lambda wc, input: (
            f"--views {shlex.quote(input.views)}" if "views" in input.keys() else ""
        ),
        refine=lambda wc, input: (
            f"--refine {shlex.quote(os.path.dirname(input.refined[0]))}"
            if "refined" in input.keys()
            else ""
        ),
        code=code_version("report", "commands/report"),
    log:
        "logs/report_videos/{session}.log",
    benchmark:
        "benchmarks/report_videos/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} report-videos --session {wildcards.session} {params.views}"
        " {params.refine} --out $(dirname {output.page:q}) > {log:q} 2>&1"


rule campaign_page:
    """One self-contained HTML page: every session's metrics, fits compared, figures."""
    input:
        unpack(session_report_extras),
        metrics=f"{RESULTS}/campaign/metrics.csv",
        velocity=expand(f"{RESULTS}/{{session}}/report/velocity.png", session=SESSIONS),
        masks=expand(f"{RESULTS}/{{session}}/report/masks", session=SESSIONS),
    output:
        report(
            f"{RESULTS}/campaign/index.html",
            caption="../report/campaign.rst",
            category="Campaign",
        ),
    params:
        surfphase=SURFPHASE,
        reports=" ".join(shlex.quote(f"{s}={RESULTS}/{s}/report") for s in SESSIONS),
        prior=lambda wc, input: (
            f"--prior-samples {shlex.quote(os.path.join(input.prior, 'samples.png'))}"
            if "prior" in input.keys()
            else ""
        ),
        code=code_version("report", "commands/report"),
    log:
        "logs/campaign_page/all.log",
    benchmark:
        "benchmarks/campaign_page/all.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} campaign-page --metrics {input.metrics:q} --out {output:q}"
        " --session-report {params.reports} {params.prior} > {log:q} 2>&1"
