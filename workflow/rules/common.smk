DATASET = config["dataset"]
DATASET_DIR = config["dataset_dir"]
RESULTS = f"results/{DATASET}"
REPORTS = f"reports/{DATASET}"
LOGS = f"logs/{DATASET}"


def dataset_manifest():
    """The dataset's manifest: produced by `simulate` or given by the user."""
    return f"{DATASET_DIR}/dataset.yaml"
