# No `configfile:`: the demo's config must never lie under a user's run (`--configfile` is required).
include: "workflow/rules/config.smk"
include: "workflow/rules/common.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/dataset.smk"
include: "workflow/rules/markers.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/pose.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/export.smk"


rule all:
    input:
        rules.dataset_report.output.html,
        rules.report.output.html,
        rules.export_colmap.output.rig_config,
        lambda wildcards: geojson_outputs(),
    default_target: True
