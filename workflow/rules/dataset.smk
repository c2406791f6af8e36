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
    log:
        f"{LOGS}/dataset_report.log",
    shell:
        "dmais summarize {DATASET_DIR} --out {REPORTS} > {log} 2>&1"
