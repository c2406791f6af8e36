from pathlib import Path

DATASET = config["dataset"]
DATASET_DIR = config["dataset_dir"]
RESULTS = f"results/{DATASET}"
REPORTS = f"reports/{DATASET}"
LOGS = f"logs/{DATASET}"


def dataset_manifest():
    """The dataset's manifest: produced by `simulate` or given by the user."""
    return f"{DATASET_DIR}/dataset.yaml"


def folder_of(name):
    """A params function: the folder holding the rule's input or output file `name`."""

    def folder(wildcards, input, output):
        files = {**dict(input.items()), **dict(output.items())}
        return str(Path(files[name]).parent)

    return folder
