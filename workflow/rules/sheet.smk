# A session whose row of the sessions sheet is invalid (a non-numeric or non-positive
# fps, a malformed frame range: SESSION_PROBLEMS, common.smk) needs this job before its
# ingest, and only such a session: the job fails naming the sheet, the session, the
# column and the value, and the other sessions run (--keep-going).


rule session_sheet:
    """A session's row of the sessions sheet: fails naming the session, the column and
    the value when the row is invalid (only such sessions need this job)."""
    output:
        f"{RESULTS}/{{session}}/sheet_row.ok",
    params:
        problem=lambda wc: SESSION_PROBLEMS.get(wc.session, ""),
    localrule: True
    log:
        "logs/session_sheet/{session}.log",
    conda:
        "../../envs/surfphase.yaml"
    shell:
        "if [ -n {params.problem:q} ]; then printf '%s\\n' {params.problem:q} > {log:q}; exit 1; fi;"
        " touch {output:q} 2> {log:q}"
