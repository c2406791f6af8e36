"""`dmais intrinsics`: calibrate every camera that has intrinsics images (calib.intrinsics).

- `run_cameras` (the workflow's job: one camera), each camera with the lens model its dataset.yaml
  entry names (`model:`, radial1 by default): RESULTS/intrinsics/<camera>.json (ours),
  <camera>.methods.csv (that camera's row of every method) and <camera>.residuals.csv (our
  calibration's residual per observation, calibration and held-out images). A calibration beyond the conf's
  plausibility bounds stops the job before anything of that camera is written;
- `write_table`: RESULTS/tables/intrinsics.csv (tab:intrinsics) from every camera's methods file;
- `run`: every camera, then the table;
- `import_cameras`: intrinsics calibrated elsewhere (an OpenCV calibration file or a COLMAP cameras
  file, calib.import_intrinsics) written as the calibration's files, so the stages after this one
  run without intrinsics images.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..calib.intrinsics import (METHODS, TABLE_COLUMNS, IntrinsicsResult, Plausibility, calibrate_camera,
                                calibrate_camera_dlt_lm, calibrate_camera_opencv, check_plausible,
                                table_columns)
from ..calib.import_intrinsics import (DEFAULT_MAX_RESIDUAL_PX, ForeignCamera, convert_camera, imported_record,
                                       read_colmap_cameras, read_opencv_file, split_pair)
from ..camera import MODELS
from ..dataset import largest_point_sigma
from ..errors import DmaisError
from ..workspace import CALIBRATION_RESIDUAL_COLUMNS, Workspace
from . import setting

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conf:
    """The methods to run and the plausibility bounds of a result (calib.intrinsics.Plausibility)."""

    methods: tuple = setting(METHODS, "'ours' and the baselines to run beside it (tab:intrinsics)")
    max_eps_calib_px: float = setting(Plausibility.max_eps_calib_px,
                                      "refuse a calibration whose eps_calib exceeds this (px)", above=0)
    max_focal_deviation: float = setting(Plausibility.max_focal_deviation,
                                         "refuse fx, fy further than this fraction from focal_px or from each other",
                                         above=0)
    max_import_residual_px: float = setting(
        DEFAULT_MAX_RESIDUAL_PX, "refuse an imported camera whose distortion its dataset.yaml model misses by "
                                 "more than this anywhere in the image (px)", above=0)


#: "paper": ours and both baselines of tab:intrinsics; "ours": the paper's procedure alone (faster).
CONFS = {"paper": Conf(), "ours": Conf(methods=("ours",))}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    """Every camera with intrinsics images, then tables/intrinsics.csv."""
    return run_cameras(workspace, calibrated_cameras(workspace), conf) + write_table(workspace)


def run_cameras(workspace: Workspace, names: list[str], conf: Conf = Conf()) -> list[Path]:
    """Each named camera's calibration (ours, checked) and every method's table row (the
    workflow's job: one camera). A refused camera stops before anything of it is written."""
    unknown = set(conf.methods) - set(METHODS)
    if unknown or "ours" not in conf.methods:
        raise DmaisError(f"intrinsics: methods must include 'ours' and be among {', '.join(METHODS)}, "
                         f"got {', '.join(conf.methods)}")
    available = calibrated_cameras(workspace)
    for name in names:
        if name not in available:
            raise DmaisError(f"intrinsics: camera {name} has no intrinsics images in "
                             f"{workspace.dataset.root / 'images.csv'} (cameras with some: {available})")
    observations, written = workspace.load_observations(), []
    for name in names:
        ours, rows = _calibrate(workspace, name, conf, observations)
        written += workspace.save_intrinsics(name, ours.to_dict(), rows)
        written.append(workspace.save_calibration_residuals(name, residual_table(workspace.dataset, ours,
                                                                                observations)))
    return written


def calibrated_cameras(workspace: Workspace) -> list[str]:
    """The dataset's cameras that have intrinsics images, in manifest order."""
    cameras = workspace.dataset.cameras_with_intrinsics_images()
    if not cameras:
        raise DmaisError(f"{workspace.dataset.root}: no intrinsics images")
    return cameras


def write_table(workspace: Workspace) -> list[Path]:
    """RESULTS/tables/intrinsics.csv from every calibrated camera's <camera>.methods.csv."""
    cameras = calibrated_cameras(workspace)
    absent = [str(workspace.methods_path(c)) for c in cameras if not workspace.methods_path(c).is_file()]
    if absent:
        raise DmaisError(f"intrinsics table: missing {absent}; run `dmais intrinsics --camera` for those cameras")
    models = {c: workspace.dataset.cameras[c].model for c in cameras}
    tables = [workspace.load_methods(c) for c in cameras]
    for camera, methods in zip(cameras, tables):
        if list(methods.columns) != list(table_columns(models[camera])):
            raise DmaisError(f"intrinsics table: {workspace.methods_path(camera)} has the columns "
                             f"{', '.join(methods.columns)}, not those of camera {camera}'s model {models[camera]} "
                             f"in dataset.yaml; run `dmais intrinsics --camera {camera}` again")
    table = pd.concat(tables, ignore_index=True)
    order = {m: i for i, m in enumerate(METHODS)}
    table = table.sort_values(["camera", "method"], key=lambda s: s.map(order) if s.name == "method" else s,
                              kind="stable")
    return [workspace.save_table("intrinsics", table[_table_columns(models.values())])]


def _table_columns(models) -> list[str]:
    """tables/intrinsics.csv's columns for cameras of `models`: TABLE_COLUMNS when all are radial1
    (the paper's table, unchanged); else the parameters of every model present in
    calib.intrinsics.table_columns' order (radial1's d, opencv's k1 .. k3), a camera's row empty
    in the columns its model lacks."""
    present = set(models)
    columns = [c for model in MODELS if model in present for c in table_columns(model)]
    parameters = [c for c in dict.fromkeys(columns) if c not in TABLE_COLUMNS[:2] + TABLE_COLUMNS[-2:]]
    return [*TABLE_COLUMNS[:2], *parameters, *TABLE_COLUMNS[-2:]]


def _calibrate(workspace: Workspace, name: str, conf: Conf, observations: pd.DataFrame
               ) -> tuple[IntrinsicsResult, pd.DataFrame]:
    dataset = workspace.dataset
    calib_images = dataset.images_of("intrinsics", name, "calib")["image"].tolist()
    eval_images = dataset.images_of("intrinsics", name, "eval")["image"].tolist()
    log.info("camera %s: %d calib + %d eval images", name, len(calib_images), len(eval_images))
    if not observations["image"].isin(calib_images).any():
        raise DmaisError(f"camera {name}: none of its {len(calib_images)} calibration images has an identified "
                         "observation; `dmais markers` identifies markers from each image's prior centre and "
                         "attitude and the camera's focal_px (see its warnings, and docs/dataset.md, "
                         "'What each stage needs')")
    X, uv, survey = _per_image(observations, dataset.points, calib_images)
    eX, euv, _ = _per_image(observations, dataset.points, eval_images)
    spec = dataset.cameras[name]
    common = dict(eval_points_world_per_image=eX, eval_uv_per_image=euv, name=name, model=spec.model)
    ours = calibrate_camera(X, uv, spec.width, spec.height, survey=survey, **common)
    check_plausible(ours, spec.focal_px, Plausibility(conf.max_eps_calib_px, conf.max_focal_deviation))
    # the PnPf mean of a 3-D field (a flat field's OpenCV baseline starts on its own)
    focal_guess = spec.focal_px or float(np.mean(list(ours.pnpf_focal_px.values()) or [ours.camera.fx]))
    baselines = {"opencv": lambda: calibrate_camera_opencv(X, uv, spec.width, spec.height, focal_guess,
                                                           warn_skipped=False, **common),
                 "dlt_lm": lambda: calibrate_camera_dlt_lm(X, uv, spec.width, spec.height, warn_skipped=False,
                                                           survey=survey, **common)}
    rows = [ours.table_row()]
    for method in [m for m in METHODS if m in conf.methods and m != "ours"]:
        try:
            rows.append(baselines[method]().table_row())
        except DmaisError as error:
            log.warning("%s", error)
            rows.append({"method": method, "camera": name})
    return ours, pd.DataFrame(rows, columns=list(table_columns(spec.model)))


def import_cameras(workspace: Workspace, names: list[str], source: Path, conf: Conf = Conf()) -> list[Path]:
    """intrinsics/<camera>.json and <camera>.methods.csv (method "imported") of each named camera from
    `source`: an OpenCV calibration file (one camera; FILE:M<n> the pair M<n>, D<n> of a stereo
    calibration, whose image size is the dataset's) or a COLMAP cameras.txt / cameras.bin (its
    cameras in camera-id order, one per name). Every camera is checked and converted before anything
    is written. Each is converted into its dataset.yaml model (`convert_camera`); the record's
    "method" says where it came from, its methods row holds the model's parameters
    (`table_columns`)."""
    dataset, source = workspace.dataset, Path(source)
    unknown = [n for n in names if n not in dataset.cameras]
    if unknown:
        raise DmaisError(f"intrinsics: camera(s) {', '.join(unknown)} are not cameras of "
                         f"{dataset.root / 'dataset.yaml'} ({', '.join(dataset.cameras)})")
    foreign = _foreign_cameras(source, names)
    conversions = {}
    for name in names:
        spec = dataset.cameras[name]
        if not foreign[name].width:  # a stereo calibration file has no image size
            foreign[name].width, foreign[name].height = spec.width, spec.height
        if (foreign[name].width, foreign[name].height) != (spec.width, spec.height):
            raise DmaisError(f"camera {name}: {source} is for {foreign[name].width}x{foreign[name].height} images, "
                             f"dataset.yaml says {spec.width}x{spec.height}")
        _check_nominal_focal(name, foreign[name], spec.focal_px, conf.max_focal_deviation, source)
        conversions[name] = convert_camera(foreign[name], name, spec.model, conf.max_import_residual_px)
    written = []
    for name, conversion in conversions.items():
        camera = conversion.camera
        distortion = ", ".join(f"{k} = {v:.6g}" for k, v in zip(camera.parameter_names[4:], camera.parameters[4:]))
        log.info("camera %s: imported from %s (%s): %s, fit residual %.3g px max, %.3g px RMS over the image",
                 name, source, foreign[name].model, distortion, conversion.residual_max_px,
                 conversion.residual_rms_px)
        record = imported_record(name, conversion, foreign[name], source)
        columns = table_columns(camera.model)
        row = {"method": "imported", **{k: record[k] for k in columns[1:-2]}}  # camera and the model's parameters
        written += workspace.save_intrinsics(name, record, pd.DataFrame([row], columns=list(columns)))
    return written


def _check_nominal_focal(name: str, foreign: ForeignCamera, focal_px: float | None, max_deviation: float,
                         source: Path) -> None:
    """Refuse a file whose focal lengths are far from the manifest's focal_px (another camera's file?)."""
    deviation = max(abs(f / focal_px - 1.0) for f in (foreign.fx, foreign.fy)) if focal_px else 0.0
    if not deviation <= max_deviation:
        raise DmaisError(f"camera {name}: {source} has fx {foreign.fx:.1f}, fy {foreign.fy:.1f} px, {deviation:.0%} "
                         f"from dataset.yaml's focal_px {focal_px:g} (limit {max_deviation:.0%}, "
                         "--max-focal-deviation); is it another camera's file?")


def _foreign_cameras(source: Path, names: list[str]) -> dict[str, ForeignCamera]:
    """Each named camera as `source` describes it: COLMAP for .txt / .bin, OpenCV's FileStorage otherwise."""
    path, pair = split_pair(source)
    if path.suffix in (".txt", ".bin"):
        if pair:
            raise DmaisError(f"{source}: a COLMAP cameras file has no {pair}; name its cameras with --camera")
        cameras = read_colmap_cameras(source)
        if len(cameras) != len(names):
            raise DmaisError(f"{source}: holds {len(cameras)} camera(s) (ids {', '.join(map(str, sorted(cameras)))}) "
                             f"for {len(names)} --camera name(s); give one name per camera, in camera-id order")
        return dict(zip(names, (cameras[k] for k in sorted(cameras))))
    if len(names) != 1:
        raise DmaisError(f"{source}: an OpenCV calibration file holds one camera; give exactly one --camera")
    return {names[0]: read_opencv_file(path, pair)}


def residual_table(dataset, result: IntrinsicsResult, observations: pd.DataFrame) -> pd.DataFrame:
    """One row per observation of every image `result` used: image, split, point_id, u, v and the
    residual du, dv observed minus projected (px). Observations are matched to the residuals by
    their order within the image, the order `_per_image` gave them to the calibration."""
    split_of = dict(zip(dataset.images["image"], dataset.images["split"]))
    parts = []
    for image, residuals in result.image_residuals_px.items():
        obs = observations[observations["image"] == image]
        parts.append(pd.DataFrame({"image": image, "split": split_of[image], "point_id": obs["point_id"].to_numpy(),
                                   "u": obs["u"].to_numpy(float), "v": obs["v"].to_numpy(float),
                                   "du": -residuals[:, 0], "dv": -residuals[:, 1]}))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=list(CALIBRATION_RESIDUAL_COLUMNS))


def _per_image(observations: pd.DataFrame, points: pd.DataFrame, images) -> tuple[dict, dict, dict]:
    """Per image: world points (n, 3), pixels (n, 2) and (point ids (n,), survey sigmas (n,)) (the
    points' largest survey sigma, dataset.largest_point_sigma) of its observations."""
    X, uv, survey = {}, {}, {}
    for image in images:
        obs = observations[observations["image"] == image]
        X[image] = points.loc[obs["point_id"], ["x", "y", "z"]].to_numpy(dtype=float)
        uv[image] = obs[["u", "v"]].to_numpy(dtype=float)
        survey[image] = (obs["point_id"].to_numpy(dtype=str), largest_point_sigma(points, obs["point_id"]))
    return X, uv, survey
