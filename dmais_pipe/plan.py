"""`dmais plan DATASET`: what the workflow needs to know of a dataset, as JSON.

The Snakefile reads this instead of parsing the dataset's files a second time, so that the jobs it
schedules (one per batch of images to extract, per camera to calibrate, per frame group) follow the
same rules as the stages, and a faulty dataset stops the dry run with the loader's one-line error.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the CLI reads MARKERS_PER_JOB for every command: the dataset module loads only when used
    from .dataset import Dataset

#: Images per marker job: a 12 MP image costs ~0.24 s, so a job runs for about half a minute and its
#: start-up (a Snakemake, a Python and the dataset per cluster job: ~6 s for 50,055 images) is ~0.06 s
#: per image (`dmais bench campaign`, docs/design.md).
MARKERS_PER_JOB = 100


def marker_batches(dataset: Dataset, per_job: int = MARKERS_PER_JOB) -> dict[str, dict]:
    """The images to extract in batches of at most `per_job`, per stage and camera (extrinsics images
    need their camera's intrinsics, flight images the rig): name -> {stage, camera, images}.

    A stage's images of one camera are split in images.csv order into near-equal runs; names are
    `<stage>-<camera>-<k>` with k from 1, zero-padded to the count's width.
    """
    from .dataset import STAGES

    if per_job < 1:
        raise ValueError(f"per_job must be at least 1, got {per_job}")
    camera_of = dict(zip(dataset.images["image"], dataset.images["camera"]))
    batches = {}
    for stage in STAGES:
        by_camera = {camera: [] for camera in dataset.cameras}
        for image in dataset.images_to_extract(stage):
            by_camera[camera_of[image]].append(image)
        for camera, of_camera in by_camera.items():
            count = math.ceil(len(of_camera) / per_job)
            for k in range(count):
                run = of_camera[len(of_camera) * k // count: len(of_camera) * (k + 1) // count]
                name = f"{stage}-{camera}-{k + 1:0{len(str(count))}d}"
                batches[name] = {"stage": stage, "camera": camera, "images": run}
    return batches


def workflow_plan(dataset: Dataset, per_job: int = MARKERS_PER_JOB) -> dict:
    """The workflow's view of `dataset`:

    cameras: camera names in the manifest's (= the rig's) order; calibrated_cameras: those with
    intrinsics images; batches: per stage, the marker batches (`marker_batches`, their images
    left out) as name -> {camera, images: how many}; groups: the flight frame groups in the order
    of frames.csv; geodetic: whether dataset.yaml names a crs (the GeoJSON export needs one).
    """
    from .dataset import STAGES

    batches = {stage: {} for stage in STAGES}
    for name, batch in marker_batches(dataset, per_job).items():
        batches[batch["stage"]][name] = {"camera": batch["camera"], "images": len(batch["images"])}
    return {
        "cameras": list(dataset.cameras),
        "calibrated_cameras": dataset.cameras_with_intrinsics_images(),
        "batches": batches,
        "groups": list(dict.fromkeys(dataset.frames["group"])),
        "geodetic": dataset.geo is not None,
    }
