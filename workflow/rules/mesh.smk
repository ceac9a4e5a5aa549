# Meshes per frame. Every finished frame is checkpointed next to the output
# (`mesh.partial/`, or `mesh_windows/<k>.partial/`), so a killed job resumes.
#
# `mesh: window: N` (N > 0) splits a session's fitted frames into windows of N frames,
# each meshed by its own job (`mesh_window`, output `mesh_windows/<k>/`, temporary);
# `mesh` then gathers them into the same `mesh/` folder one job writes. The number of
# windows comes from the sessions sheet's `frames` column when it gives a stop
# (start:stop[:step]); otherwise from the ingest's frame count, read after ingest by
# the checkpoint `mesh_frame_count` (helpers in mesh_common.smk).

include: "mesh_common.smk"


if MESH_WINDOW > 0:

    checkpoint mesh_frame_count:
        """The ingested frame count (a copy of the ingest's meta.json) for the windows."""
        input:
            f"{RESULTS}/{{session}}/ingest",
        output:
            f"{RESULTS}/{{session}}/mesh_windows/frames.json",
        localrule: True
        log:
            "logs/mesh_frame_count/{session}.log",
        benchmark:
            "benchmarks/mesh_frame_count/{session}.tsv"
        conda:
            "../../envs/surfphase.yaml"
        shell:
            "cp {input:q}/meta.json {output:q} > {log:q} 2>&1"

    rule mesh_window:
        """Meshes of one window of frames (raw arrays, gathered by `mesh`)."""
        input:
            fit=lambda wc: final_fit(wc.session),
            ingest=f"{RESULTS}/{{session}}/ingest",
            masks=f"{RESULTS}/{{session}}/masks",
        output:
            temp(directory(f"{RESULTS}/{{session}}/mesh_windows/{{window}}")),
        wildcard_constraints:
            window=r"\d+",
        params:
            surfphase=SURFPHASE,
            settings=MESH_SETTINGS,
            size=MESH_WINDOW,
            device=config["device"],
            code=code_version("mesh", "render", "fit", "commands/mesh"),
        threads: config["threads"]
        log:
            "logs/mesh_window/{session}/{window}.log",
        benchmark:
            "benchmarks/mesh_window/{session}/{window}.tsv"
        conda:
            "../../envs/surfphase.yaml"
        shell:
            "{params.surfphase} mesh --fit $(dirname {input.fit:q}) --ingest {input.ingest:q}"
            " --masks {input.masks:q}"
            " --out {output:q} --window {wildcards.window} --window-size {params.size}"
            " --device {params.device} --threads {threads}"
            " --params-json {params.settings:q} > {log:q} 2>&1"

    rule mesh:
        """One mesh per frame, gathered from the windows (same files as one job)."""
        input:
            windows=mesh_window_dirs,
        output:
            directory(f"{RESULTS}/{{session}}/mesh"),
        params:
            surfphase=SURFPHASE,
            code=code_version("mesh", "commands/mesh"),
        log:
            "logs/mesh/{session}.log",
        benchmark:
            "benchmarks/mesh/{session}.tsv"
        conda:
            "../../envs/surfphase.yaml"
        shell:
            "{params.surfphase} mesh-gather --windows {input.windows:q} --out {output:q}"
            " > {log:q} 2>&1"

else:

    rule mesh:
        """One mesh per frame (TSDF fusion of rendered depth, marching cubes), with velocity."""
        input:
            fit=lambda wc: final_fit(wc.session),
            ingest=f"{RESULTS}/{{session}}/ingest",
            masks=f"{RESULTS}/{{session}}/masks",
        output:
            directory(f"{RESULTS}/{{session}}/mesh"),
        params:
            surfphase=SURFPHASE,
            settings=MESH_SETTINGS,
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
            " --masks {input.masks:q}"
            " --out {output:q} --device {params.device} --threads {threads}"
            " --params-json {params.settings:q} > {log:q} 2>&1"
