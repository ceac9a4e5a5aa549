rule ingest:
    """Read each camera's video, apply the frame range, undistort, crop/scale, stack."""
    input:
        cameras=ingest_cameras,
        videos=lambda wc: existing(session_cameras(wc.session).values()),
    output:
        directory(f"{RESULTS}/{{session}}/ingest"),
    params:
        surfphase=SURFPHASE,
        cams=lambda wc: cam_args(session_cameras(wc.session)),
        cameras=lambda wc: f"{RESULTS}/calib/{session_rig(wc.session)}/cameras.json",
        rig=lambda wc: session_rig(wc.session),
        rigs_sheet=config["rigs"],
        fps=lambda wc: sessions.loc[wc.session, "fps"],
        frames=lambda wc: (
            f"--frames {sessions.loc[wc.session, 'frames']}"
            if sessions.loc[wc.session].get("frames")
            else ""
        ),
        scale=config["ingest"]["scale"],
        fit_size=config["ingest"]["fit_size"],
        crop=(
            "--crop " + ",".join(str(v) for v in config["ingest"]["crop"])
            if config["ingest"].get("crop")
            else ""
        ),
        native="--native-masks" if config["ingest"]["native_masks"] else "",
        code=code_version("ingest", "video", "labformats", "commands/ingest"),
    log:
        "logs/ingest/{session}.log",
    benchmark:
        "benchmarks/ingest/{session}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} ingest --session {wildcards.session} --rig {params.rig:q}"
        " --rigs-sheet {params.rigs_sheet:q} --cameras {params.cameras:q} {params.cams}"
        " --fps {params.fps} {params.frames} --scale {params.scale}"
         " --fit-size {params.fit_size} {params.crop} {params.native}"
        " --out {output:q} > {log:q} 2>&1"
