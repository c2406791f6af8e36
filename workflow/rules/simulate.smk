if config.get("simulate"):

    rule simulate:
        input:
            config=config["simulate"],
        output:
            manifest=f"{DATASET_DIR}/dataset.yaml",
        log:
            f"{LOGS}/simulate.log",
        threads: workflow.cores
        shell:
            "dmais simulate {input.config} --out {DATASET_DIR} --jobs {threads} > {log} 2>&1"
