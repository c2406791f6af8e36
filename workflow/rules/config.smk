import sys

import jsonschema
import yaml
from snakemake.utils import validate

CONFIG_SCHEMA = "../schemas/config.schema.yaml"  # relative to this file
#: The stages whose config section holds `dmais <stage>` settings (docs/design.md, "Stage settings").
STAGES = ("markers", "intrinsics", "extrinsics", "pose", "evaluate", "export", "report")


def check_config(config):
    """Stop with one line naming the fault of the workflow config (no default config is loaded:
    the demo's must never lie under a user's run), then validate it, filling in the defaults."""
    if not config:
        sys.exit("no configuration: run with --configfile config/config.yaml (the demo) "
                 "or a config of your own (README, 'Your own dataset')")
    if ("dataset_dir" in config) == ("simulate" in config):
        sys.exit("config: give either dataset_dir (your dataset, only read) or simulate (a simulator "
                 "preset, simulated into results/<dataset>/dataset/)")
    with open(workflow.source_path(CONFIG_SCHEMA)) as handle:
        schema = yaml.safe_load(handle)
    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(config))
    if error is not None:
        where = ".".join(str(key) for key in error.absolute_path) or "(top level)"
        sys.exit(f"config: {where}: {error.message}")
    validate(config, CONFIG_SCHEMA)


#: Each stage's settings as the user wrote them, before `validate` fills in the schema's defaults:
#: only these are passed on, so that a named conf's own values are not overwritten by defaults.
GIVEN_SETTINGS = {stage: dict(config.get(stage) or {}) for stage in STAGES}
check_config(config)
