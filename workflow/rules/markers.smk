rule markers:
    input:
        unpack(marker_inputs),
    output:
        csv=f"{RESULTS}/markers/{{image}}.csv",
    params:
        dataset_dir=folder_of("manifest"),
        results=folder_of("csv", up=1),
        settings=stage_settings("markers"),
    log:
        f"{LOGS}/markers/{{image}}.log",
    benchmark:
        f"{BENCHMARKS}/markers/{{image}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais markers {params.dataset_dir} --out {params.results} --image {wildcards.image} {params.settings} "
        "> {log} 2>&1"


rule observations:
    input:
        manifest=lambda wildcards: dataset_ready(),
        markers=lambda wildcards: expand(f"{RESULTS}/markers/{{image}}.csv", image=extracted_images(wildcards.stage)),
    output:
        csv=f"{RESULTS}/observations/{{stage}}.csv",
    wildcard_constraints:
        stage="intrinsics|extrinsics|flight",
    params:
        dataset_dir=folder_of("manifest"),
        results=folder_of("csv", up=1),
    log:
        f"{LOGS}/observations/{{stage}}.log",
    benchmark:
        f"{BENCHMARKS}/observations/{{stage}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais markers {params.dataset_dir} --out {params.results} --collect {wildcards.stage} > {log} 2>&1"
