rule pose_slices:
    input:
        manifest=lambda wildcards: dataset_ready(),
        observations=f"{RESULTS}/observations/flight.csv",
    output:
        json=f"{RESULTS}/slices/pose.json",
    params:
        dataset_dir=DATASET_DIR,
        results=lambda wildcards, output: Path(output.json).parent.parent,
    log:
        f"{LOGS}/pose_slices.log",
    benchmark:
        f"{BENCHMARKS}/pose_slices.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais plan {params.dataset_dir} --out {params.results} --slices pose > {log} 2>&1"


rule pose_group:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        observations=f"{RESULTS}/observations/flight.csv",
        slices=f"{RESULTS}/slices/pose.json",
    output:
        csv=f"{RESULTS}/poses/{{subset}}/{{group}}.csv",
        observations=f"{RESULTS}/poses/{{subset}}/{{group}}.observations.csv",
        budget=f"{RESULTS}/poses/{{subset}}/{{group}}.budget.csv",
        mounting=f"{RESULTS}/poses/{{subset}}/{{group}}.mounting.csv",
    wildcard_constraints:
        subset=r"all|\d+",
    params:
        dataset_dir=DATASET_DIR,
        results=lambda wildcards, input: Path(input.rig).parent,
        cameras=lambda wildcards: ",".join(subset_cameras(wildcards.subset)),
        settings=stage_settings("pose"),
    log:
        f"{LOGS}/pose/{{subset}}/{{group}}.log",
    benchmark:
        f"{BENCHMARKS}/pose/{{subset}}_{{group}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais pose {params.dataset_dir} --out {params.results} --cameras {params.cameras} "
        "--groups {wildcards.group} --csv {output.csv} {params.settings} > {log} 2>&1"


rule poses:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        parts=pose_parts("all"),
    output:
        csv=f"{RESULTS}/poses.csv",
        observations=f"{RESULTS}/poses.observations.csv",
        budget=f"{RESULTS}/poses.budget.csv",
        mounting=f"{RESULTS}/poses.mounting.csv",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
    log:
        f"{LOGS}/poses.log",
    benchmark:
        f"{BENCHMARKS}/poses.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais pose {params.dataset_dir} --out {params.results} --merge {input.parts} --csv {output.csv} > {log} 2>&1"


rule poses_subset:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        parts=pose_parts(None),
    output:
        csv=f"{RESULTS}/poses_{{subset}}.csv",
        observations=f"{RESULTS}/poses_{{subset}}.observations.csv",
        budget=f"{RESULTS}/poses_{{subset}}.budget.csv",
        mounting=f"{RESULTS}/poses_{{subset}}.mounting.csv",
    wildcard_constraints:
        subset=r"\d+",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
        cameras=lambda wildcards: ",".join(subset_cameras(wildcards.subset)),
    log:
        f"{LOGS}/poses_{{subset}}.log",
    benchmark:
        f"{BENCHMARKS}/poses_subset/{{subset}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais pose {params.dataset_dir} --out {params.results} --cameras {params.cameras} --merge {input.parts} "
        "--csv {output.csv} > {log} 2>&1"
