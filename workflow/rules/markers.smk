rule markers:
    input:
        unpack(marker_inputs),
    output:
        csv=f"{RESULTS}/markers/batches/{{batch}}.csv",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
        per_job=MARKERS_PER_JOB,
        settings=stage_settings("markers"),
    log:
        f"{LOGS}/markers/{{batch}}.log",
    benchmark:
        f"{BENCHMARKS}/markers/{{batch}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais markers {params.dataset_dir} --out {params.results} --batch {wildcards.batch} "
        "--per-job {params.per_job} {params.settings} > {log} 2>&1"


rule observations:
    input:
        manifest=lambda wildcards: dataset_ready(),
        batches=lambda wildcards: expand(f"{RESULTS}/markers/batches/{{batch}}.csv",
                                         batch=marker_batches(wildcards.stage)),
    output:
        csv=f"{RESULTS}/observations/{{stage}}.csv",
    wildcard_constraints:
        stage="intrinsics|extrinsics|flight",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
    log:
        f"{LOGS}/observations/{{stage}}.log",
    benchmark:
        f"{BENCHMARKS}/observations/{{stage}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais markers {params.dataset_dir} --out {params.results} --collect {wildcards.stage} > {log} 2>&1"
