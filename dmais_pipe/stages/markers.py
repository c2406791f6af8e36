"""`dmais markers`: every image's markers, and the observations of each stage.

- `run_batch` (the workflow's job per batch of images, plan.marker_batches): RESULTS/markers/<image>.csv
  for each image of the batch, then RESULTS/markers/batches/<batch>.csv with each image's counts and
  time per phase. Each finished image is recorded at once in <batch>.progress with a digest of its
  inputs, so that a batch run again (killed or failed midway: a node lost, a corrupt image; or
  finished unnoticed by a controlling Snakemake that was killed) redoes only the images it had not
  finished from the same inputs and code;
- `run_image`: one image's RESULTS/markers/<image>.csv;
- `collect` (one job per stage): RESULTS/observations/<stage>.csv from the stage's marker files and
  the dataset's own observations of that stage;
- `run` (without the workflow): every image in turn, then RESULTS/observations.csv. Images run one
  after the other; Snakemake (`--cores`, a cluster profile) is the way to run them in parallel.

Flight images are identified with RESULTS/rig.json and extrinsics images with the calibrated
intrinsics when those exist (markers.extract).
"""

from __future__ import annotations

import csv
import functools
import hashlib
import io
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from ..camera import Camera
from ..errors import DmaisError
from ..markers.extract import (PREDICTION_MARGIN_PX, PRIOR_ATTITUDE_DEG, PRIOR_POSITION_M, VERIFY_GATE_PX,
                               observation_table, process_image)
from ..markers.identify import GATE_PX, MIN_INLIERS
from ..files import write_csv_atomic
from ..plan import MARKERS_PER_JOB
from . import setting, three_numbers
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
    prior_attitude_deg: float = setting(
        PRIOR_ATTITUDE_DEG, "the largest error of an image's prior attitude (deg; a flight image's: the INS's and "
                            "its boresight's): markers are searched in windows about their predictions as wide as "
                            "this and prior_position_m move them, the whole image where nothing there is "
                            "identified", minimum=0)
    prior_position_m: float = setting(
        PRIOR_POSITION_M, "the largest error of an image's prior centre (m; a flight image's: the POS's and its "
                          "lever arm's)", minimum=0)
    pos_lever_arm: tuple = setting((), "the POS reference point in the rig frame, x,y,z (m; surveyed, or "
                                   "tables/lever_arm.csv of an earlier run): given, a flight image's prior centre "
                                   "is frames.csv's POS position less it, and prior_position_m need only cover the "
                                   "POS's error and the lever arm's")
    whole_image: bool = setting(False, "search every image whole, not first the windows about the predictions")


CONFS = {"default": Conf()}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    """Every image with a file and no given observations -> markers/<image>.csv, then observations.csv."""
    dataset = workspace.dataset
    lever_arm(conf)  # a setting that does not parse stops the stage before any image
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
    lever_arm(conf)
    if image not in dataset.images_to_extract():
        raise DmaisError(f"markers: {image!r} is not an image of {dataset.root / 'images.csv'} with a file "
                         "and no given observations")
    rig = workspace.load_rig() if workspace.has_rig() else None
    return [workspace.save_markers(image, _extract(workspace, image, conf, rig))]


#: RESULTS/markers/batches/<batch>.csv: per image, its detections and identified ones, the windows
#: about the predictions searched (0: none) and whether the whole image was (1: no priors, windows
#: covering most of it, or nothing identified in them), the seconds of each phase (decode, detect,
#: refine, identify, write) and whether an earlier run of the batch had done it.
_COUNT_COLUMNS = ("detected", "identified", "windows", "whole_image")
_PHASE_COLUMNS = ("decode_s", "detect_s", "refine_s", "identify_s", "write_s")
BATCH_COLUMNS = ("image", "camera", *_COUNT_COLUMNS, *_PHASE_COLUMNS, "resumed")
#: <batch>.progress: an image, its inputs' digest, its markers file's size and mtime, then its batch row.
_PROGRESS_COLUMNS = ("image", "key", "markers", *BATCH_COLUMNS[2:-1])


def run_batch(workspace: Workspace, batch: str, per_job: int = MARKERS_PER_JOB, conf: Conf = Conf()) -> list[Path]:
    """The images of `batch` (plan.marker_batches of the dataset with `per_job`) -> their markers files
    and RESULTS/markers/batches/<batch>.csv. An image whose markers an earlier run of this batch wrote
    from the same inputs is not redone. An image that fails does not stop the others; the batch then
    fails naming the first, and its finished images are kept for the next run."""
    dataset = workspace.dataset
    lever_arm(conf)
    batches = workspace.marker_batches(per_job)
    if batch not in batches:
        raise DmaisError(f"markers: no batch {batch!r} among the {len(batches)} marker batches of {dataset.root} "
                         f"with {per_job} images per job (`dmais plan` lists them)")
    images, stage = batches[batch]["images"], batches[batch]["stage"]
    rig = workspace.load_rig() if stage == "flight" else None
    key = _inputs_key(workspace, batches[batch], conf)
    progress = workspace.marker_batch_path(batch).with_suffix(".progress")
    done = _finished(progress, workspace)
    rows, failed = [], []
    for k, image in enumerate(images, 1):
        image_key = _image_key(dataset, image, key)
        if done.get(image, {}).get("key") == image_key:
            rows.append({**done[image], "resumed": True})
            continue
        try:
            row = _extract_and_save(workspace, image, conf, rig, f"{k}/{len(images)} ")
        except (DmaisError, OSError) as error:
            log.error("markers %s: %s", image, error)
            failed.append((image, error))
            continue
        _record(progress, {"image": image, "key": image_key, "markers": _stamp(workspace.markers_path(image)), **row})
        rows.append({"image": image, **row, "resumed": False})
    if failed:
        image, error = failed[0]
        raise DmaisError(f"markers: {len(failed)} of {len(images)} images of batch {batch} failed, first {image}: "
                         f"{error} (the {len(images) - len(failed)} finished are kept for the next run)")
    table = pd.DataFrame(rows, columns=["image", *BATCH_COLUMNS[2:]])
    table.insert(1, "camera", batches[batch]["camera"])
    written = write_csv_atomic(workspace.marker_batch_path(batch), table.round(6))
    log.info("markers %s: %d images, %d done before (%.1f s of detection work)", batch, len(images),
             int(table["resumed"].sum()), float(table[list(_PHASE_COLUMNS)].to_numpy().sum()))
    return [written]


def _extract_and_save(workspace: Workspace, image: str, conf: Conf, rig: Rig | None, progress: str) -> dict:
    """One image's markers written; its counts and seconds per phase (a progress row without image and key)."""
    seconds = {}
    found = _extract(workspace, image, conf, rig, progress, seconds)
    started = time.perf_counter()
    workspace.save_markers(image, found)
    return {"detected": len(found), "identified": int((found["point_id"] != "").sum()), **seconds,
            "write_s": time.perf_counter() - started}


def _inputs_key(workspace: Workspace, batch: dict, conf: Conf) -> str:
    """A digest of what a batch's markers depend on besides the image file: the code, the settings, the
    dataset's tables and the calibration the stage identifies with (rig.json, or the camera's intrinsics)."""
    digest = hashlib.sha256(_code_digest().encode() + repr(conf).encode())
    root = workspace.dataset.root
    prerequisites = {"flight": [workspace.rig_path],
                     "extrinsics": [workspace.intrinsics_path(batch["camera"])]}.get(batch["stage"], [])
    for path in sorted(root.glob("*.csv")) + [root / "dataset.yaml"]:
        digest.update(f"{path.name}:{_stamp(path)};".encode())
    for path in prerequisites:
        digest.update(path.read_bytes() if path.is_file() else b"absent")
    return digest.hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """A digest of this package's source (a changed detector redoes every image)."""
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).resolve().parents[1].rglob("*")):
        if path.suffix in (".py", ".pyx", ".pxd"):
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _image_key(dataset, image: str, inputs_key: str) -> str:
    path = dataset.image_path(image)
    return f"{inputs_key}-{'' if path is None else _stamp(path)}"


def _finished(progress: Path, workspace: Workspace) -> dict[str, dict]:
    """The images earlier runs of a batch recorded in `progress` whose markers file is still the one
    they wrote: image -> its last progress row (without the markers file's stamp). A line cut short
    by a kill is ignored."""
    if not progress.is_file():
        return {}
    finished = {}
    for cells in list(csv.reader(progress.read_text(errors="replace").splitlines()))[1:]:
        if len(cells) != len(_PROGRESS_COLUMNS) or cells[2] != _stamp(workspace.markers_path(cells[0])):
            continue
        counted = 3 + len(_COUNT_COLUMNS)
        try:
            counts, seconds = [int(c) for c in cells[3:counted]], [float(c) for c in cells[counted:]]
        except ValueError:
            continue
        finished[cells[0]] = dict(zip(("image", "key", *_PROGRESS_COLUMNS[3:]), cells[:2] + counts + seconds))
    return finished


def _stamp(path: Path) -> str:
    """A file's size and modification time, '' when it is absent."""
    return f"{path.stat().st_size}-{path.stat().st_mtime_ns}" if path.is_file() else ""


def _record(progress: Path, row: dict) -> None:
    """Append one finished image to the batch's progress file, on disk before the next image starts
    (after a line a kill cut short, on a line of its own)."""
    progress.parent.mkdir(parents=True, exist_ok=True)
    lines = io.StringIO()
    if not progress.is_file():
        csv.writer(lines, lineterminator="\n").writerow(_PROGRESS_COLUMNS)
    else:
        with open(progress, "rb") as handle:
            if handle.seek(0, os.SEEK_END) and (handle.seek(-1, os.SEEK_END), handle.read(1))[1] != b"\n":
                lines.write("\n")
    csv.writer(lines, lineterminator="\n").writerow([row[c] for c in _PROGRESS_COLUMNS])
    with open(progress, "a") as handle:
        handle.write(lines.getvalue())
        handle.flush()
        os.fsync(handle.fileno())


def collect(workspace: Workspace, stage: str) -> list[Path]:
    """RESULTS/observations/<stage>.csv from the stage's marker files and the dataset's own observations."""
    images = workspace.dataset.images_to_extract(stage)
    absent = [str(workspace.markers_path(image)) for image in images if not workspace.markers_path(image).is_file()]
    if absent:
        raise DmaisError(f"markers: {len(absent)} marker file(s) of stage {stage} missing, e.g. {absent[0]}; "
                         "run `dmais markers --batch` or `--image` for them")
    markers = {image: workspace.load_markers(image) for image in images}
    return [workspace.save_observations(observation_table(workspace.dataset, images, markers, stage), stage)]


def _extract(workspace: Workspace, image: str, conf: Conf, rig: Rig | None, progress: str = "",
             seconds: dict | None = None):
    started = time.perf_counter()
    found = process_image(workspace.dataset, image, rig, _calibrated(workspace, image),
                          conf.prediction_margin_px, conf.verify_gate_px, conf.identify_gate_px,
                          conf.identify_min_inliers, seconds, None if conf.whole_image else conf.prior_attitude_deg,
                          conf.prior_position_m, lever_arm(conf))
    log.info("markers %s%s: %d detected, %d identified (%.2f s)", progress, image, len(found),
             int((found["point_id"] != "").sum()), time.perf_counter() - started)
    return found


def lever_arm(conf: Conf) -> tuple[float, float, float] | None:
    """The setting pos_lever_arm as three numbers (m), None where it is not given; DmaisError otherwise."""
    return three_numbers(conf.pos_lever_arm, "markers: setting pos_lever_arm") if conf.pos_lever_arm else None


def _calibrated(workspace: Workspace, image: str) -> Camera | None:
    """The calibrated intrinsics of an extrinsics image's camera, when RESULTS has them."""
    images = workspace.dataset.images
    row = images[images["image"] == image].iloc[0]
    if row["stage"] != "extrinsics" or not workspace.intrinsics_path(row["camera"]).exists():
        return None
    return workspace.load_intrinsics(row["camera"])[0]
