rule intrinsics:
    input:
        manifest=lambda wildcards: dataset_ready(),
        observations=f"{RESULTS}/observations/intrinsics.csv",
    output:
        json=f"{RESULTS}/intrinsics/{{camera}}.json",
        methods=f"{RESULTS}/intrinsics/{{camera}}.methods.csv",
        residuals=f"{RESULTS}/intrinsics/{{camera}}.residuals.csv",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
        settings=stage_settings("intrinsics"),
    log:
        f"{LOGS}/intrinsics/{{camera}}.log",
    benchmark:
        f"{BENCHMARKS}/intrinsics/{{camera}}.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais intrinsics {params.dataset_dir} --out {params.results} --camera {wildcards.camera} {params.settings} "
        "> {log} 2>&1"


rule intrinsics_table:
    input:
        manifest=lambda wildcards: dataset_ready(),
        methods=lambda wildcards: expand(f"{RESULTS}/intrinsics/{{camera}}.methods.csv", camera=calibrated_cameras()),
    output:
        csv=report(f"{RESULTS}/tables/intrinsics.csv", caption="../report/intrinsics_table.rst", category="Tables",
                   subcategory="Calibration"),
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
    log:
        f"{LOGS}/intrinsics_table.log",
    benchmark:
        f"{BENCHMARKS}/intrinsics_table.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais intrinsics {params.dataset_dir} --out {params.results} --table > {log} 2>&1"


rule extrinsics:
    input:
        manifest=lambda wildcards: dataset_ready(),
        intrinsics=lambda wildcards: expand(f"{RESULTS}/intrinsics/{{camera}}.json", camera=calibrated_cameras()),
        intrinsics_observations=f"{RESULTS}/observations/intrinsics.csv",
        observations=f"{RESULTS}/observations/extrinsics.csv",
    output:
        rig=f"{RESULTS}/rig.json",
        rig_config=f"{RESULTS}/rig_config.json",
        rotations=report(f"{RESULTS}/tables/extrinsics_R.csv", caption="../report/extrinsics_tables.rst",
                         category="Tables", subcategory="Calibration"),
        translations=report(f"{RESULTS}/tables/extrinsics_t.csv", caption="../report/extrinsics_tables.rst",
                            category="Tables", subcategory="Calibration"),
        survey=report(f"{RESULTS}/tables/survey_sigma.csv", caption="../report/survey_sigma.rst",
                      category="Tables", subcategory="Calibration"),
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
        settings=stage_settings("extrinsics"),
    log:
        f"{LOGS}/extrinsics.log",
    benchmark:
        f"{BENCHMARKS}/extrinsics.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais extrinsics {params.dataset_dir} --out {params.results} {params.settings} > {log} 2>&1"
