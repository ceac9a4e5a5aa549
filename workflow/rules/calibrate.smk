rule calibrate:
    """ChArUco calibration of one rig: intrinsics, distortion, extrinsics in the lab frame.

    Each camera column of rigs.tsv is a folder of images or a calibration recording; the
    optional ``timestamps`` column pairs the recordings' frames by capture time.
    """
    input:
        board=lambda wc: existing([resolve(rigs, rigs.loc[wc.rig, "board"])]),
        images=lambda wc: existing(rig_cameras(wc.rig).values()),
        timestamps=lambda wc: existing(
            [resolve(rigs, rigs.loc[wc.rig].get("timestamps", ""))]
        ),
    output:
        cameras=f"{RESULTS}/calib/{{rig}}/cameras.json",
        report=f"{RESULTS}/calib/{{rig}}/report.json",
        corners=f"{RESULTS}/calib/{{rig}}/corners.png",
    params:
        surfphase=SURFPHASE,
        board=lambda wc: resolve(rigs, rigs.loc[wc.rig, "board"]),
        cams=lambda wc: cam_args(rig_cameras(wc.rig)),
        timestamps=lambda wc: " ".join(
            f"--timestamps {shlex.quote(p)}"
            for p in [resolve(rigs, rigs.loc[wc.rig].get("timestamps", ""))]
            if p
        ),
        min_images=config["calibrate"]["min_images"],
        code=code_version("calib", "commands/calibrate"),
    log:
        "logs/calibrate/{rig}.log",
    benchmark:
        "benchmarks/calibrate/{rig}.tsv"
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "{params.surfphase} calibrate --rig {wildcards.rig} --board {params.board:q}"
        " {params.cams} {params.timestamps} --min-images {params.min_images}"
        " --out $(dirname {output.cameras:q}) > {log:q} 2>&1"
