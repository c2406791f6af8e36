"""`dmais markers`: detect, refine and identify diagonal markers in every image of a dataset.

Writes RESULTS/markers/<image>.csv (u, v, score, point_id; point_id empty when unidentified) for
every image with a file, and RESULTS/observations.csv (image, camera, point_id, u, v): the
identified detections plus the dataset's own observations.csv rows (images listed there skip
extraction, docs/design.md). The workflow instead runs one job per image (`run_markers_image`) and
collects each stage into RESULTS/observations/<stage>.csv (`collect_observations`).

Predicted projections for identification come from the priors:
- calibration images: images.csv prior centre + prior attitude (cam_from_world) with, for
  extrinsics images, RESULTS/intrinsics/<camera>.json if it exists, else (and always for
  intrinsics images) a nominal pinhole (dataset.yaml focal_px, principal point at the image
  centre, no distortion);
- flight images: frames.csv POS position + INS attitude (rig_from_world) and the rig of
  RESULTS/rig.json; without a rig (before `dmais extrinsics`) flight detections stay unidentified.

Ids of calibration images are then verified with a pose: a PnPf fit (pose and focal length,
principal point at the centre, no distortion) to the identified detections; ids whose residual
exceeds VERIFY_GATE_PX are dropped one at a time, worst first. The gate leaves room for the
unmodelled distortion (up to ~25 px at the corners of a 45000 px, d = 3 camera) while a wrong id,
a neighbouring marker hundreds of pixels away, fails it.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ..camera import Camera, image_centre, project_unmasked
from ..dataset import Dataset
from ..errors import DatasetError, DmaisError
from ..geometry import Rigid3
from ..rig import Rig
from ..workspace import MARKER_COLUMNS, Workspace
from ..calib.pnpf import solve_pnpf
from .detect import detect
from .identify import identify

log = logging.getLogger(__name__)

OBSERVATION_COLUMNS = ["image", "camera", "point_id", "u", "v"]
PREDICTION_MARGIN_PX = 3000.0  # keep predictions this far outside the image (attitude prior errors)
VERIFY_GATE_PX = 40.0


def _nominal_camera(dataset: Dataset, camera: str, results_dir: Path | None) -> Camera | None:
    workspace = None if results_dir is None else Workspace(dataset, results_dir)
    if workspace is not None and workspace.intrinsics_path(camera).exists():
        return workspace.load_intrinsics(camera)[0]
    spec = dataset.cameras[camera]
    if not spec.focal_px:
        return None
    return Camera(spec.focal_px, spec.focal_px, *image_centre(spec.width, spec.height), 0.0, spec.width, spec.height)


def _load_rig(dataset: Dataset, results_dir: Path | None) -> Rig | None:
    workspace = None if results_dir is None else Workspace(dataset, results_dir)
    return workspace.load_rig() if workspace is not None and workspace.has_rig() else None


def _prediction_model(dataset: Dataset, image: str, results_dir=None, rig: Rig | None = None):
    """(camera, cam_from_world, points) that predict where `image` sees the known points, or a
    sentence saying what is missing for that (which priors, focal_px, the calibrated rig)."""
    row = dataset.images[dataset.images["image"] == image].iloc[0]
    camera_name = row["camera"]
    if row["stage"] == "flight":
        rig = rig if rig is not None else _load_rig(dataset, results_dir)
        if rig is None:
            return "flight images are identified with the calibrated rig, and RESULTS has no rig.json yet " \
                   "(run `dmais extrinsics` first)"
        if camera_name not in rig.cameras:
            return f"camera {camera_name} is not in rig.json"
        frame = dataset.frames[dataset.frames["frame"] == row["placement"]].iloc[0]
        q = frame[["prior_qw", "prior_qx", "prior_qy", "prior_qz"]].to_numpy(dtype=float)
        centre = frame[["pos_x", "pos_y", "pos_z"]].to_numpy(dtype=float)
        if not np.all(np.isfinite(q)):
            return f"frame {row['placement']!r} of frames.csv has no prior_qw..prior_qz (the INS attitude)"
        rig_from_world = Rigid3.from_quat(q, np.zeros(3))
        rig_from_world = Rigid3.from_quat(q, -rig_from_world.R @ centre)
        points = dataset.ground_points if len(dataset.ground_points) else dataset.points
        return rig.cameras[camera_name], rig.cam_from_rig[camera_name] * rig_from_world, points
    q = row[["prior_qw", "prior_qx", "prior_qy", "prior_qz"]].to_numpy(dtype=float)
    centre = row[["prior_x", "prior_y", "prior_z"]].to_numpy(dtype=float)
    missing = [f"{name} in images.csv" for name, values in (("prior_x..prior_z (camera centre)", centre),
                                                            ("prior_qw..prior_qz (attitude)", q))
               if not np.all(np.isfinite(values))]
    # Intrinsics images are the calibration's input: identified with the nominal camera only,
    # so that their ids never depend on an earlier calibration.
    camera = _nominal_camera(dataset, camera_name, results_dir if row["stage"] == "extrinsics" else None)
    if camera is None:
        missing.append(f"focal_px of camera {camera_name} in dataset.yaml")
    if missing:
        return (f"{row['stage']} images are identified from their prior centre and attitude and the camera's "
                f"focal_px; missing {' and '.join(missing)}")
    R = Rigid3.from_quat(q, np.zeros(3)).R
    return camera, Rigid3(R, -R @ centre), dataset.control_points


def identification_gap(dataset: Dataset, image: str, results_dir=None, rig: Rig | None = None) -> str | None:
    """Why the markers of `image` cannot be identified (docs/dataset.md, "What each stage needs"),
    or None when the priors and camera model to predict them are there."""
    model = _prediction_model(dataset, image, results_dir, rig)
    return model if isinstance(model, str) else None


def predicted_projections(dataset: Dataset, image: str, results_dir=None, rig: Rig | None = None):
    """(uv (m, 2), point ids (m,)) of the known points predicted in `image` from the priors, or None
    when the priors (or a camera model) are missing. Only points in front of the camera and within
    PREDICTION_MARGIN_PX of the image are kept."""
    model = _prediction_model(dataset, image, results_dir, rig)
    if isinstance(model, str):
        return None
    camera, cam_from_world, points = model
    xyz = points[["x", "y", "z"]].to_numpy(dtype=float)
    uv = camera.project(cam_from_world.apply(xyz))
    m = PREDICTION_MARGIN_PX
    keep = (np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > -m) & (uv[:, 0] < camera.width + m)
            & (uv[:, 1] > -m) & (uv[:, 1] < camera.height + m))
    return uv[keep], points.index.to_numpy(dtype=object)[keep]


# ------------------------------------------------------------------------------ per image

_WORKER: dict = {}


def _worker_dataset(dataset_dir: str) -> Dataset:
    if _WORKER.get("dir") != dataset_dir:
        _WORKER["dir"] = dataset_dir
        _WORKER["dataset"] = Dataset.load(dataset_dir)
    return _WORKER["dataset"]


def process_image(dataset: Dataset, image: str, results_dir=None, rig: Rig | None = None) -> pd.DataFrame:
    """Detections of one image with ids: DataFrame u, v, score, point_id ('' when unidentified)."""
    pixels = dataset.read_image(image)
    found = detect(pixels)
    found["point_id"] = ""
    prediction = predicted_projections(dataset, image, results_dir, rig)
    if prediction is None and len(found):
        log.warning("markers %s: %d detected, none can be identified: %s", image, len(found),
                    identification_gap(dataset, image, results_dir, rig))
    if prediction is not None and len(found):
        uv, ids = prediction
        height, width = pixels.shape
        found["point_id"] = identify(found[["u", "v"]].to_numpy(), uv, ids, (width, height))
        if dataset.images.loc[dataset.images["image"] == image, "stage"].iloc[0] != "flight":
            found["point_id"] = verify_with_pose(found[["u", "v"]].to_numpy(), found["point_id"].to_numpy(),
                                                 dataset.points, image_centre(width, height))
        if not (found["point_id"] != "").any():
            log.warning("markers %s: %d detected, none identified: the priors predict %d known point(s) near the "
                        "image and none matches a detection (check the prior centre and attitude, and focal_px)",
                        image, len(found), len(uv))
    return found[list(MARKER_COLUMNS)]


def verify_with_pose(uv: np.ndarray, ids: np.ndarray, points: pd.DataFrame, principal_point) -> np.ndarray:
    """Ids (n,) ('' = none) of detections uv (n, 2) that one camera pose explains.

    Fits pose + focal length (PnPf) to the identified detections and drops the worst id while its
    residual exceeds VERIFY_GATE_PX. With too few ids left for a fit, all are dropped: an id no
    pose confirms is not trusted.
    """
    ids = np.asarray(ids, dtype=object).copy()
    while True:
        keep = np.flatnonzero(ids != "")
        if len(keep) == 0:
            return ids
        X = points.loc[ids[keep], ["x", "y", "z"]].to_numpy(dtype=float)
        try:
            cam_from_world, focal = solve_pnpf(X, uv[keep], principal_point)
        except DmaisError:
            ids[keep] = ""
            return ids
        # the nominal pinhole (d = 0); PnPf's pose has every point in front, where nothing is masked
        uv_fit = project_unmasked(cam_from_world.apply(X), focal, focal, *principal_point, 0.0)
        residual = np.hypot(*(uv_fit - uv[keep]).T)
        worst = int(np.argmax(residual))
        if residual[worst] <= VERIFY_GATE_PX:
            return ids
        ids[keep[worst]] = ""


def _work(args):
    dataset_dir, results_dir, image = args
    try:
        dataset = _worker_dataset(dataset_dir)
        started = time.perf_counter()
        frame = process_image(dataset, image, results_dir)
        Workspace(dataset, results_dir).save_markers(image, frame)
        return image, frame, time.perf_counter() - started, None
    except DatasetError as error:
        return image, None, 0.0, ("dataset", error.path, error.message, error.line)
    except DmaisError as error:
        return image, None, 0.0, ("dmais", str(error))


def run_markers(dataset_dir, results_dir, jobs: int = 1) -> Path:
    """Detect, refine and identify markers in every image with a file; returns RESULTS/observations.csv.

    jobs: worker processes (1: in this process). Raises the dataset's DatasetError naming a missing
    or undecodable image.
    """
    dataset_dir, results_dir = str(Path(dataset_dir).absolute()), Path(results_dir).absolute()
    dataset = Dataset.load(dataset_dir)
    todo = dataset.images_to_extract()
    # Fail before any work on a missing file: the dataset's own error names it.
    for image in todo:
        if dataset.image_path(image) is None or not dataset.image_path(image).is_file():
            dataset.read_image(image)
    tasks = [(dataset_dir, str(results_dir), image) for image in todo]
    results = {}
    total = len(tasks)
    started = time.perf_counter()

    def collect(item, k):
        image, frame, seconds, error = item
        if error is not None:
            if pool is not None:
                pool.terminate()
            if error[0] == "dataset":
                raise DatasetError(error[1], error[2], error[3])
            raise DmaisError(error[1])
        results[image] = frame
        identified = int((frame["point_id"] != "").sum())
        log.info("markers %d/%d %s: %d detected, %d identified (%.2f s)", k, total, image, len(frame),
                 identified, seconds)

    pool = None
    if jobs > 1 and total > 1:
        _WORKER["dataset"] = dataset  # inherited by forked workers
        _WORKER["dir"] = dataset_dir
        ctx = multiprocessing.get_context("fork") if "fork" in multiprocessing.get_all_start_methods() else None
        pool = (ctx or multiprocessing).Pool(min(jobs, total))
        try:
            for k, item in enumerate(pool.imap_unordered(_work, tasks), 1):
                collect(item, k)
        finally:
            pool.close()
            pool.join()
    else:
        _WORKER["dataset"] = dataset
        _WORKER["dir"] = dataset_dir
        for k, task in enumerate(tasks, 1):
            collect(_work(task), k)
    log.info("markers: %d images in %.1f s", total, time.perf_counter() - started)

    return Workspace(dataset, results_dir).save_observations(observation_table(dataset, todo, results))


def observation_table(dataset: Dataset, images: list[str], markers: dict[str, pd.DataFrame],
                      stage: str | None = None) -> pd.DataFrame:
    """OBSERVATION_COLUMNS rows: the identified markers of `images` (image -> markers frame) and the
    dataset's own observations (of `stage`'s images only, when given)."""
    camera_of = dict(zip(dataset.images["image"], dataset.images["camera"]))
    rows = []
    for image in images:
        ok = markers[image][markers[image]["point_id"] != ""]
        rows.append(pd.DataFrame({"image": image, "camera": camera_of[image], "point_id": ok["point_id"],
                                  "u": ok["u"], "v": ok["v"]}))
    own = dataset.observations
    if stage is not None:
        own = own[own["image"].isin(dataset.images_of(stage)["image"])]
    if len(own):
        rows.append(pd.DataFrame({"image": own["image"], "camera": own["image"].map(camera_of),
                                  "point_id": own["point_id"], "u": own["u"], "v": own["v"]}))
    if not rows:
        return pd.DataFrame({c: pd.Series(dtype=float if c in "uv" else object) for c in OBSERVATION_COLUMNS})
    return pd.concat(rows, ignore_index=True)[OBSERVATION_COLUMNS]


def run_markers_image(dataset_dir, results_dir, image: str) -> Path:
    """One image's detections with ids -> RESULTS/markers/<image>.csv (the workflow's per-image job)."""
    dataset = Dataset.load(dataset_dir)
    if image not in dataset.images_to_extract():
        raise DmaisError(f"markers: {image!r} is not an image of {dataset.root / 'images.csv'} with a file "
                         "and no given observations")
    started = time.perf_counter()
    found = process_image(dataset, image, results_dir)
    log.info("markers %s: %d detected, %d identified (%.2f s)", image, len(found),
             int((found["point_id"] != "").sum()), time.perf_counter() - started)
    return Workspace(dataset, results_dir).save_markers(image, found)


def collect_observations(dataset_dir, results_dir, stage: str) -> Path:
    """RESULTS/observations/<stage>.csv from the stage's RESULTS/markers/<image>.csv files and the
    dataset's own observations of that stage (`Workspace.load_observations` reads it)."""
    workspace = Workspace.open(dataset_dir, results_dir)
    images = workspace.dataset.images_to_extract(stage)
    absent = [str(workspace.markers_path(image)) for image in images if not workspace.markers_path(image).is_file()]
    if absent:
        raise DmaisError(f"markers: {len(absent)} marker file(s) of stage {stage} missing, e.g. {absent[0]}; "
                         "run `dmais markers --image` for them")
    markers = {image: workspace.load_markers(image) for image in images}
    table = observation_table(workspace.dataset, images, markers, stage)
    return workspace.save_observations(table, stage)
