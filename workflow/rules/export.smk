#: The COLMAP model's formats (the export section's `formats`, default both) and their files.
EXPORT_FILES = {"text": "txt", "binary": "bin"}
EXPORT_FORMATS = (config.get("export") or {}).get("formats", list(EXPORT_FILES))


rule export_colmap:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        poses=f"{RESULTS}/poses.csv",
        observations=f"{RESULTS}/poses.observations.csv",
    output:
        **{fmt: multiext(f"{RESULTS}/colmap/{fmt}/", *(f"{name}.{EXPORT_FILES[fmt]}" for name in
                                                      ("cameras", "images", "points3D", "rigs", "frames")))
           for fmt in EXPORT_FORMATS},
        rig_config=f"{RESULTS}/colmap/rig_config.json",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
        settings=stage_settings("export"),
    log:
        f"{LOGS}/export_colmap.log",
    benchmark:
        f"{BENCHMARKS}/export_colmap.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais export-colmap {params.dataset_dir} --out {params.results} {params.settings} > {log} 2>&1"


# Only for a dataset with a crs (rule all asks for it through geojson_outputs()).
rule export_geojson:
    input:
        manifest=lambda wildcards: dataset_ready(),
        rig=f"{RESULTS}/rig.json",
        poses=f"{RESULTS}/poses.csv",
        subsets=lambda wildcards: expand(f"{RESULTS}/poses_{{subset}}.csv", subset=subset_labels()),
        observations=f"{RESULTS}/poses.observations.csv",
    output:
        frames=f"{RESULTS}/geojson/frames.geojson",
        footprints=f"{RESULTS}/geojson/footprints.geojson",
    params:
        dataset_dir=DATASET_DIR,
        results=RESULTS,
    log:
        f"{LOGS}/export_geojson.log",
    benchmark:
        f"{BENCHMARKS}/export_geojson.tsv"
    conda:
        DMAIS_ENV
    shell:
        "dmais export-geojson {params.dataset_dir} --out {params.results} > {log} 2>&1"
