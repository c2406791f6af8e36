"""`dmais markers`: every image's markers, and the observations of each stage.

- `run_image` (the workflow's job per image): RESULTS/markers/<image>.csv;
- `collect` (one job per stage): RESULTS/observations/<stage>.csv from the stage's marker files and
  the dataset's own observations of that stage;
- `run` (without the workflow): every image in turn, then RESULTS/observations.csv. Images run one
  after the other; Snakemake (`--cores`, a cluster profile) is the way to run them in parallel.

Flight images are identified with RESULTS/rig.json and extrinsics images with the calibrated
intrinsics when those exist (markers.extract).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from ..camera import Camera
from ..errors import DmaisError
from ..markers.extract import PREDICTION_MARGIN_PX, VERIFY_GATE_PX, observation_table, process_image
from ..markers.identify import GATE_PX, MIN_INLIERS
from . import setting
from ..rig import Rig
from ..workspace import Workspace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conf:
    """How the detections of an image are identified (markers.identify, markers.extract)."""

    prediction_margin_px: float = setting(
        PREDICTION_MARGIN_PX, "known points predicted this far outside an image are still matched (px; "
                              "room for the attitude prior's error)", minimum=0)
    verify_gate_px: float = setting(
        VERIFY_GATE_PX, "a calibration image's id is dropped when the PnPf pose misses it by more (px)", above=0)
    identify_gate_px: float = setting(
        GATE_PX, "final gate between a detection and the aligned prediction of its point (px)", above=0)
    identify_min_inliers: int = setting(
        MIN_INLIERS, "fewest one-to-one matches for an image's ids to be accepted", minimum=3)


CONFS = {"default": Conf()}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    """Every image with a file and no given observations -> markers/<image>.csv, then observations.csv."""
    dataset = workspace.dataset
    todo = dataset.images_to_extract()
    for image in todo:  # fail before any work on a missing file: the dataset's own error names it
        if dataset.image_path(image) is None or not dataset.image_path(image).is_file():
            dataset.read_image(image)
    rig = workspace.load_rig() if workspace.has_rig() else None
    started, written, markers = time.perf_counter(), [], {}
    for k, image in enumerate(todo, 1):
        markers[image] = _extract(workspace, image, conf, rig, f"{k}/{len(todo)} ")
        written.append(workspace.save_markers(image, markers[image]))
    log.info("markers: %d images in %.1f s", len(todo), time.perf_counter() - started)
    written.append(workspace.save_observations(observation_table(dataset, todo, markers)))
    return written


def run_image(workspace: Workspace, image: str, conf: Conf = Conf()) -> list[Path]:
    """One image's detections with ids -> RESULTS/markers/<image>.csv."""
    dataset = workspace.dataset
    if image not in dataset.images_to_extract():
        raise DmaisError(f"markers: {image!r} is not an image of {dataset.root / 'images.csv'} with a file "
                         "and no given observations")
    rig = workspace.load_rig() if workspace.has_rig() else None
    return [workspace.save_markers(image, _extract(workspace, image, conf, rig))]


def collect(workspace: Workspace, stage: str) -> list[Path]:
    """RESULTS/observations/<stage>.csv from the stage's marker files and the dataset's own observations."""
    images = workspace.dataset.images_to_extract(stage)
    absent = [str(workspace.markers_path(image)) for image in images if not workspace.markers_path(image).is_file()]
    if absent:
        raise DmaisError(f"markers: {len(absent)} marker file(s) of stage {stage} missing, e.g. {absent[0]}; "
                         "run `dmais markers --image` for them")
    markers = {image: workspace.load_markers(image) for image in images}
    return [workspace.save_observations(observation_table(workspace.dataset, images, markers, stage), stage)]


def _extract(workspace: Workspace, image: str, conf: Conf, rig: Rig | None, progress: str = ""):
    started = time.perf_counter()
    found = process_image(workspace.dataset, image, rig, _calibrated(workspace, image),
                          conf.prediction_margin_px, conf.verify_gate_px, conf.identify_gate_px,
                          conf.identify_min_inliers)
    log.info("markers %s%s: %d detected, %d identified (%.2f s)", progress, image, len(found),
             int((found["point_id"] != "").sum()), time.perf_counter() - started)
    return found


def _calibrated(workspace: Workspace, image: str) -> Camera | None:
    """The calibrated intrinsics of an extrinsics image's camera, when RESULTS has them."""
    images = workspace.dataset.images
    row = images[images["image"] == image].iloc[0]
    if row["stage"] != "extrinsics" or not workspace.intrinsics_path(row["camera"]).exists():
        return None
    return workspace.load_intrinsics(row["camera"])[0]
