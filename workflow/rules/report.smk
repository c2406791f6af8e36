rule evaluate:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        poses=f"{RESULTS}/poses.csv",
        budget=f"{RESULTS}/poses.budget.csv",
        mounting=f"{RESULTS}/poses.mounting.csv",
        subsets=lambda wildcards: expand(f"{RESULTS}/poses_{{subset}}.csv", subset=subset_labels()),
        subset_budgets=lambda wildcards: expand(f"{RESULTS}/poses_{{subset}}.budget.csv", subset=subset_labels()),
    output:
        evaluation=report(f"{RESULTS}/evaluation.csv", caption="../report/evaluation.rst", category="Tables",
                          subcategory="Pose"),
        pose_methods=report(f"{RESULTS}/tables/pose_methods.csv", caption="../report/pose_methods.rst",
                            category="Tables", subcategory="Pose"),
        lever_arm=report(f"{RESULTS}/tables/lever_arm.csv", caption="../report/lever_arm.rst", category="Tables",
                         subcategory="Pose"),
        residuals=report(f"{RESULTS}/tables/residuals.csv", caption="../report/flight_residuals.rst",
                         category="Tables", subcategory="Pose"),
        **({"conf": report(f"{RESULTS}/tables/conf.csv", caption="../report/conf.rst", category="Tables",
                           subcategory="Pose")} if SUBSETS else {}),
        error_budget=report(f"{RESULTS}/tables/error_budget.csv", caption="../report/error_budget.rst",
                            category="Tables", subcategory="Pose"),
        mounting=report(f"{RESULTS}/tables/mounting.csv", caption="../report/mounting.rst", category="Tables",
                        subcategory="Pose"),
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
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
        csv=report(f"{RESULTS}/tables/time_points.csv", caption="../report/time_points.rst", category="Tables",
                   subcategory="Runtime"),
        batch=report(f"{RESULTS}/tables/time_points_batch.csv", caption="../report/time_points.rst",
                     category="Tables", subcategory="Runtime"),
        **({"stage": report(f"{RESULTS}/tables/time_points_stage.csv", caption="../report/time_points.rst",
                            category="Tables", subcategory="Runtime")} if BENCH_POSE["stage_frames"] else {}),
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


def compared_conf_tables(wildcards):
    """tables/conf.csv of the runs the report compares with (report: compare_with) that exist, so that
    the report is made again when one changes; one not made yet is named in the report, not built here."""
    names = GIVEN_SETTINGS["report"].get("compare_with") or []
    folders = [Path(name) if "/" in name else Path(RESULTS).parent / name for name in names]
    return [str(folder / "tables" / "conf.csv") for folder in folders
            if folder.resolve() != Path(RESULTS).resolve() and (folder / "tables" / "conf.csv").is_file()]


rule report:
    input:
        manifest=lambda wildcards: dataset_ready(),
        compared=compared_conf_tables,
        intrinsics=f"{RESULTS}/tables/intrinsics.csv",
        extrinsics=f"{RESULTS}/tables/extrinsics_R.csv",
        evaluation=f"{RESULTS}/evaluation.csv",
        time_points=f"{RESULTS}/tables/time_points.csv",
        flight_observations=f"{RESULTS}/observations/flight.csv",
        calibration_residuals=lambda wildcards: expand(f"{RESULTS}/intrinsics/{{camera}}.residuals.csv",
                                                       camera=calibrated_cameras()),
    output:
        html=report(f"{REPORTS}/report.html", caption="../report/report.rst", category="Report"),
        figures=report(directory(f"{REPORTS}/figures"), patterns=["{name}.svg", "{name}.jpg"],
                       caption="../report/figures.rst", category="Figures"),
        tables=report(directory(f"{REPORTS}/tables"), patterns=["{name}_vs_paper.csv"],
                      caption="../report/paper_tables.rst", category="Tables", subcategory="Versus the paper"),
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
        benchmarks=BENCHMARKS,
        settings=stage_settings("report"),
    log:
        f"{LOGS}/report.log",
    benchmark:
        f"{BENCHMARKS}/report.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais report {params.dataset_dir} --out {params.results} --html {output.html} "
        "--benchmarks {params.benchmarks} {params.settings} > {log} 2>&1"
