import csv
import functools
from pathlib import Path

import yaml

DATASET = config["dataset"]
RESULTS = f"results/{DATASET}"
#: A simulated dataset lives in a folder the workflow owns; a user's dataset is only ever read.
DATASET_DIR = f"{RESULTS}/dataset" if config.get("simulate") else config["dataset_dir"]
REPORTS = f"reports/{DATASET}"
LOGS = f"logs/{DATASET}"
BENCHMARKS = f"benchmarks/{DATASET}"
POSE = config.get("pose", {})
#: Camera subsets of tab:conf, as camera indexes in the manifest's order ("01" = first two cameras).
SUBSETS = config.get("subsets", ["0", "01", "012", "1234"])
BENCH_POSE = {"repeats": 50, "batch_frames": 100, **config.get("bench_pose", {})}


def dataset_manifest():
    """The dataset's manifest: written by `simulate` or given by the user (an input, never an output)."""
    return f"{DATASET_DIR}/dataset.yaml"


def dataset_ready():
    """The manifest path once the dataset exists: with `simulate`, waits for that checkpoint so that
    the images, cameras and frame groups below are read from the simulated files."""
    if config.get("simulate"):
        return checkpoints.simulate.get().output.manifest
    return dataset_manifest()


def folder_of(name, up=0):
    """A params function: the folder holding the rule's input or output file `name`, or the one
    `up` levels above it (e.g. RESULTS from RESULTS/markers/<image>.csv with up=1)."""

    def folder(wildcards, input, output):
        files = {**dict(input.items()), **dict(output.items())}
        return str(Path(files[name]).parents[up])

    return folder


def _rows(name):
    """The rows of the dataset's CSV file `name` as dicts.

    The workflow reads the dataset's CSV files itself rather than importing dmais_pipe (whose
    Dataset and markers.stage.images_to_extract answer the same questions): with --use-conda,
    snakemake runs where the package need not be installed. `dmais validate` checks the files."""
    return _read_rows(str(Path(dataset_ready()).parent / name))


@functools.lru_cache(maxsize=None)
def _read_rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def cameras():
    """Camera names in the manifest's (= the rig's) order."""
    with open(dataset_ready()) as handle:
        return list(yaml.safe_load(handle)["cameras"])


def image_table():
    """images.csv rows by image id."""
    return {row["image"]: row for row in _rows("images.csv")}


def extracted_images(stage):
    """Images of `stage` whose markers the workflow extracts: with a file and no given observations."""
    given_path = Path(dataset_ready()).parent / "observations.csv"
    given = {row["image"] for row in _rows("observations.csv")} if given_path.exists() else set()
    return [image for image, row in image_table().items()
            if row["stage"] == stage and row.get("path") and image not in given]


def calibrated_cameras():
    """Cameras with intrinsics images, in manifest order."""
    having = {row["camera"] for row in image_table().values() if row["stage"] == "intrinsics"}
    return [c for c in cameras() if c in having]


def groups():
    """Flight frame groups, in the order of frames.csv."""
    return list(dict.fromkeys(row["group"] for row in _rows("frames.csv")))


def subset_cameras(label):
    """Camera names of a subset label ("012" -> C0,C1,C2 for a rig C0..C4); "all" -> every camera."""
    names = cameras()
    return names if label == "all" else [names[int(k)] for k in label]


def subset_labels():
    """The configured subsets that are proper subsets of this rig (the whole rig is poses.csv)."""
    n = len(cameras())
    return [s for s in SUBSETS if all(int(k) < n for k in s) and len(set(s)) < n]


def pose_flags():
    return " ".join(f"--{key}" for key in ("robust", "refine") if POSE.get(key))


def marker_inputs(wildcards):
    """An image's prerequisites: extrinsics images are identified with the calibrated intrinsics of
    their camera, flight images with the calibrated rig."""
    row = image_table()[wildcards.image]
    inputs = {"manifest": dataset_ready()}
    if row["stage"] == "extrinsics":
        inputs["intrinsics"] = f"{RESULTS}/intrinsics/{row['camera']}.json"
    elif row["stage"] == "flight":
        inputs["rig"] = f"{RESULTS}/rig.json"
    return inputs


def pose_parts(label):
    """An input function: the per-group pose files of subset `label` (None: the wildcard's)."""

    def parts(wildcards):
        return expand(f"{RESULTS}/poses/{label or wildcards.subset}/{{group}}.csv", group=groups())

    return parts


DMAIS_ENV = "../envs/dmais.yaml"
