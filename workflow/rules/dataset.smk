rule dataset_report:
    input:
        manifest=dataset_manifest(),
    output:
        html=report(
            f"{REPORTS}/dataset.html",
            caption="../report/dataset.rst",
            category="Dataset",
        ),
        summary=f"{REPORTS}/dataset_summary.csv",
    params:
        dataset_dir=DATASET_DIR,
        reports=REPORTS,
    log:
        f"{LOGS}/dataset_report.log",
    benchmark:
        f"{BENCHMARKS}/dataset_report.tsv"
    conda:
        "../envs/dmais.yaml"
    shell:
        "dmais summarize {params.dataset_dir} --out {params.reports} > {log} 2>&1"
