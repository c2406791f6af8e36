"""`dmais plan DATASET`: what the workflow needs to know of a dataset, as JSON.

The Snakefile reads this instead of parsing the dataset's files a second time, so that the jobs it
schedules (one per image to extract, per camera to calibrate, per frame group) follow the same
rules as the stages, and a faulty dataset stops the dry run with the loader's one-line error.
"""

from __future__ import annotations

from .dataset import STAGES, Dataset


def workflow_plan(dataset: Dataset) -> dict:
    """The workflow's view of `dataset`:

    cameras: camera names in the manifest's (= the rig's) order; calibrated_cameras: those with
    intrinsics images; extract: per stage, the images whose markers are extracted (a file and no
    given observations); image_stage, image_camera: stage and camera of each of those images;
    groups: the flight frame groups in the order of frames.csv.
    """
    extract = {stage: dataset.images_to_extract(stage) for stage in STAGES}
    images = dataset.images.set_index("image")
    extracted = [image for stage in STAGES for image in extract[stage]]
    return {
        "cameras": list(dataset.cameras),
        "calibrated_cameras": dataset.cameras_with_intrinsics_images(),
        "extract": extract,
        "image_stage": {image: images.at[image, "stage"] for image in extracted},
        "image_camera": {image: images.at[image, "camera"] for image in extracted},
        "groups": list(dict.fromkeys(dataset.frames["group"])),
    }
