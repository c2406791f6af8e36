rule evaluate:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        poses=f"{RESULTS}/poses.csv",
        subsets=lambda wildcards: expand(f"{RESULTS}/poses_{{subset}}.csv", subset=subset_labels()),
    output:
        evaluation=f"{RESULTS}/evaluation.csv",
        pose_methods=f"{RESULTS}/tables/pose_methods.csv",
        lever_arm=f"{RESULTS}/tables/lever_arm.csv",
        residuals=f"{RESULTS}/tables/residuals.csv",
        **({"conf": f"{RESULTS}/tables/conf.csv"} if SUBSETS else {}),
    params:
        dataset_dir=folder_of("manifest"),
        results=folder_of("evaluation"),
        settings=stage_settings("evaluate"),
    log:
        f"{LOGS}/evaluate.log",
    benchmark:
        f"{BENCHMARKS}/evaluate.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais evaluate {params.dataset_dir} --out {params.results} {params.settings} > {log} 2>&1"


rule bench_pose:
    output:
        csv=f"{RESULTS}/tables/time_points.csv",
        batch=f"{RESULTS}/tables/time_points_batch.csv",
        **({"stage": f"{RESULTS}/tables/time_points_stage.csv"} if BENCH_POSE["stage_frames"] else {}),
    params:
        repeats=BENCH_POSE["repeats"],
        batch_frames=BENCH_POSE["batch_frames"],
        stage_frames=BENCH_POSE["stage_frames"],
    log:
        f"{LOGS}/bench_pose.log",
    benchmark:
        f"{BENCHMARKS}/bench_pose.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais bench pose --csv {output.csv} --repeats {params.repeats} --batch-frames {params.batch_frames} "
        "--stage-frames {params.stage_frames} > {log} 2>&1"


rule report:
    input:
        manifest=lambda wildcards: dataset_ready(),
        intrinsics=f"{RESULTS}/tables/intrinsics.csv",
        extrinsics=f"{RESULTS}/tables/extrinsics_R.csv",
        evaluation=f"{RESULTS}/evaluation.csv",
        time_points=f"{RESULTS}/tables/time_points.csv",
        flight_observations=f"{RESULTS}/observations/flight.csv",
    output:
        html=report(f"{REPORTS}/report.html", caption="../report/report.rst", category="Report"),
    params:
        dataset_dir=folder_of("manifest"),
        results=folder_of("evaluation"),
        benchmarks=BENCHMARKS,
        settings=stage_settings("report"),
    log:
        f"{LOGS}/report.log",
    conda:
        DMAIS_ENV
    shell:
        "dmais report {params.dataset_dir} --out {params.results} --html {output.html} "
        "--benchmarks {params.benchmarks} {params.settings} > {log} 2>&1"
