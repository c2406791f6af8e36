# Only a config with `simulate:` (the demo's, the paper's) has this rule, and it writes into
# RESULTS/dataset, a folder of the workflow's own: a user's dataset is never an output of any rule.
if config.get("simulate"):

    checkpoint simulate:
        input:
            config=config["simulate"],
        output:
            manifest=f"{DATASET_DIR}/dataset.yaml",
        params:
            dataset_dir=DATASET_DIR,
        log:
            f"{LOGS}/simulate.log",
        benchmark:
            f"{BENCHMARKS}/simulate.tsv"
        threads: 8  # snakemake caps it at --cores
        conda:
            "../envs/dmais.yaml"
        shell:
            "dmais simulate {input.config} --out {params.dataset_dir} --jobs {threads} > {log} 2>&1"
