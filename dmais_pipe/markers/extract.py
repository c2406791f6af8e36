"""Markers of one image: detect, refine and identify diagonal markers, then verify the ids.

`process_image` returns one image's detections (u, v, score, sigma_px, fit_residual, point_id, id_refusal;
point_id '' when unidentified); `observation_table` turns the identified detections of a stage's
images, with the dataset's own observations, into observation rows. Reading and writing results
is the markers stage's (`stages.markers`).

Predicted projections for identification come from the priors:
- calibration images: images.csv prior centre + prior attitude (cam_from_world) with, for
  extrinsics images, the calibrated camera when the stage has one (RESULTS/intrinsics/<camera>.json),
  else (and always for intrinsics images) a nominal pinhole (dataset.yaml focal_px, principal point
  at the image centre, no distortion);
- flight images: frames.csv POS position + INS attitude (rig_from_world) and the calibrated rig;
  without a rig (before `dmais extrinsics`) flight detections stay unidentified. With the POS lever
  arm l (the POS reference point in the rig frame, surveyed or an earlier run's tables/lever_arm.csv)
  the rig's centre is the POS position less R_world_from_rig l (the POS convention of `evaluate`), and
  the position bound need only cover the POS's own error.

With priors, the markers are searched first in windows about their predicted pixels
(`search_windows`): each as wide as the priors' error bounds (PRIOR_ATTITUDE_DEG, PRIOR_POSITION_M)
can move the prediction, plus the identification's gate; `windows.detect_in_windows` finds there
exactly what `detect` finds in the whole image. The whole image is searched instead where the
windows would cover more than MAX_WINDOW_SHARE of it, where there are no priors, and after the
windows where no detection in them is identified (a prior worse than its bound).

Ids of calibration images are then verified with a pose: a PnPf fit (pose and focal length,
principal point at the centre, no distortion) to the identified detections; ids whose residual
exceeds the gate (VERIFY_GATE_PX) are dropped one at a time, worst first. The gate leaves room for
the unmodelled distortion (up to ~25 px at the corners of a 45000 px, d = 3 camera) while a wrong
id, a neighbouring marker hundreds of pixels away, fails it.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pandas as pd

from ..camera import Camera, image_centre, project_unmasked
from ..dataset import Dataset
from ..errors import DmaisError
from ..geometry import Rigid3, exp_so3
from ..rig import Rig
from .detect import detect, uv_of
from .identify import GATE_PX, MIN_INLIERS, identify_with_reasons
from .windows import detect_in_windows

log = logging.getLogger(__name__)

OBSERVATION_COLUMNS = ["image", "camera", "point_id", "u", "v"]
PREDICTION_MARGIN_PX = 3000.0  # keep predictions this far outside the image (attitude prior errors)
VERIFY_GATE_PX = 40.0
#: `wide_field`: the prior attitude error it allows for (the simulator's calibration priors: 1 deg)
#: and the keystone (px) beyond which identification models it (half of identify's 12 px gate).
PRIOR_TURN_DEG = 1.0
KEYSTONE_PX = 6.0
#: The priors' error bounds the search windows allow for (`search_windows`): the attitude's (the
#: simulator's INS: 0.5 deg per axis beside a 0.5 deg boresight; its calibration priors: 1 deg per
#: axis) and the centre's (RTK or POS: cm, beside the rig's lever arm to the POS, 0.37 m there,
#: when the lever arm is not given).
PRIOR_ATTITUDE_DEG = 3.0
PRIOR_POSITION_M = 0.5
#: Windows covering more than this share of an image (summed) cost about as much as the whole image.
MAX_WINDOW_SHARE = 0.5
_QUAT = ("prior_qw", "prior_qx", "prior_qy", "prior_qz")


def _nominal_camera(dataset: Dataset, camera: str, calibrated: Camera | None) -> Camera | None:
    if calibrated is not None:
        return calibrated
    spec = dataset.cameras[camera]
    if not spec.focal_px:
        return None
    return Camera(spec.focal_px, spec.focal_px, *image_centre(spec.width, spec.height), 0.0, spec.width, spec.height)


_IMAGE_COLUMNS = ("camera", "stage", "placement", "prior_x", "prior_y", "prior_z") + _QUAT
_FRAME_COLUMNS = ("pos_x", "pos_y", "pos_z") + _QUAT


def _first_row(table: pd.DataFrame, column: str, value, names: tuple) -> dict:
    """{name: value} of `names` in the first row of `table` whose `column` is `value` (IndexError where
    none), as `table[table[column] == value].iloc[0]` has them, without making that frame and Series."""
    at = np.flatnonzero(table[column].to_numpy() == value)[0]
    return {name: table.iat[at, table.columns.get_loc(name)] for name in names}


def _prediction_model(dataset: Dataset, image: str, rig: Rig | None = None, calibrated: Camera | None = None,
                      lever_arm: np.ndarray | None = None):
    """(camera, cam_from_world, points) that predict where `image` sees the known points, or a
    sentence saying what is missing for that (which priors, focal_px, the calibrated rig).
    lever_arm (3,): the POS reference point in the rig frame (m), taken off a flight image's POS
    position; None: the POS position stands for the rig's centre."""
    row = _first_row(dataset.images, "image", image, _IMAGE_COLUMNS)
    camera_name = row["camera"]
    if row["stage"] == "flight":
        if rig is None:
            return "flight images are identified with the calibrated rig, and RESULTS has no rig.json yet " \
                   "(run `dmais extrinsics` first)"
        if camera_name not in rig.cameras:
            return f"camera {camera_name} is not in rig.json"
        frame = _first_row(dataset.frames, "frame", row["placement"], _FRAME_COLUMNS)
        q = np.array([frame[c] for c in _QUAT], dtype=float)
        centre = np.array([frame[c] for c in ("pos_x", "pos_y", "pos_z")], dtype=float)
        if not np.all(np.isfinite(q)):
            return f"frame {row['placement']!r} of frames.csv has no prior_qw..prior_qz (the INS attitude)"
        rig_from_world = Rigid3.from_quat(q, np.zeros(3))
        if lever_arm is not None:  # POS = centre + R_world_from_rig @ lever_arm
            centre = centre - rig_from_world.R.T @ np.asarray(lever_arm, dtype=float)
        rig_from_world = Rigid3.from_quat(q, -rig_from_world.R @ centre)
        points = dataset.ground_points if len(dataset.ground_points) else dataset.points
        return rig.cameras[camera_name], rig.cam_from_rig[camera_name] * rig_from_world, points
    q = np.array([row[c] for c in _QUAT], dtype=float)
    centre = np.array([row[c] for c in ("prior_x", "prior_y", "prior_z")], dtype=float)
    missing = [f"{name} in images.csv" for name, values in (("prior_x..prior_z (camera centre)", centre),
                                                            ("prior_qw..prior_qz (attitude)", q))
               if not np.all(np.isfinite(values))]
    # Intrinsics images are the calibration's input: identified with the nominal camera only,
    # so that their ids never depend on an earlier calibration.
    camera = _nominal_camera(dataset, camera_name, calibrated if row["stage"] == "extrinsics" else None)
    if camera is None:
        missing.append(f"focal_px of camera {camera_name} in dataset.yaml")
    if missing:
        return (f"{row['stage']} images are identified from their prior centre and attitude and the camera's "
                f"focal_px; missing {' and '.join(missing)}")
    R = Rigid3.from_quat(q, np.zeros(3)).R
    return camera, Rigid3(R, -R @ centre), dataset.control_points


def wide_field(camera: Camera) -> bool:
    """Whether a turn of the prior's attitude by PRIOR_TURN_DEG about an image axis moves the
    predictions of `camera` by more than KEYSTONE_PX beyond a similarity at the image's corners
    (f w r^2 / f^2 for a corner r px from the centre): then `identify` fits that keystone too. A
    DMAIS camera (5.4 deg) stays far below it, a 60 deg oblique far above."""
    corner = 0.5 * np.hypot(camera.width, camera.height)
    return np.radians(PRIOR_TURN_DEG) * corner**2 / camera.fx > KEYSTONE_PX


def predicted_projections(dataset: Dataset, image: str, rig: Rig | None = None, calibrated: Camera | None = None,
                          margin_px: float = PREDICTION_MARGIN_PX, lever_arm: np.ndarray | None = None):
    """(uv (m, 2), point ids (m,)) of the known points predicted in `image` from the priors, or None
    when the priors (or a camera model) are missing. Only points in front of the camera and within
    margin_px of the image are kept. rig: for flight images; calibrated: the image camera's
    calibrated intrinsics, used for extrinsics images; lever_arm: as `_prediction_model`."""
    model = _prediction_model(dataset, image, rig, calibrated, lever_arm)
    return None if isinstance(model, str) else _projections(model, margin_px)


def _projections(model, margin_px: float):
    """(uv (m, 2), point ids (m,)) of `predicted_projections` from a `_prediction_model`."""
    return _projected_points(model, margin_px)[:2]


def _projected_points(model, margin_px: float):
    """`_projections` and the points' world positions (m, 3)."""
    camera, cam_from_world, points = model
    xyz = points[["x", "y", "z"]].to_numpy(dtype=float)
    uv = camera.project(cam_from_world.apply(xyz))
    m = margin_px
    keep = (np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > -m) & (uv[:, 0] < camera.width + m)
            & (uv[:, 1] > -m) & (uv[:, 1] < camera.height + m))
    return uv[keep], points.index.to_numpy(dtype=object)[keep], xyz[keep]


def prediction_radius(camera: Camera, xyz: np.ndarray, turn_deg: float, shift_m: float) -> np.ndarray:
    """(n,) px: how far the projections of points xyz (n, 3) (camera frame) move when the camera turns
    by turn_deg about any axis and moves by shift_m in any direction: the largest singular values of
    the secants (2, 3) of such turns about, and moves along, its three axes, added; inf where a
    point or a moved one is not projectable."""
    uv = camera.project(xyz)
    turns = [exp_so3(np.radians(turn_deg) * axis) for axis in np.eye(3)]
    turned = np.stack([camera.project(xyz @ R.T) - uv for R in turns], axis=2)  # (n, 2, 3)
    moved = np.stack([camera.project(xyz + shift_m * axis) - uv for axis in np.eye(3)], axis=2)
    radius = np.full(len(xyz), np.inf)
    ok = np.all(np.isfinite(turned), axis=(1, 2)) & np.all(np.isfinite(moved), axis=(1, 2))
    radius[ok] = np.linalg.norm(turned[ok], ord=2, axis=(1, 2)) + np.linalg.norm(moved[ok], ord=2, axis=(1, 2))
    return radius


def search_windows(model, attitude_deg: float = PRIOR_ATTITUDE_DEG, position_m: float = PRIOR_POSITION_M,
                   gate_px: float = GATE_PX, margin_px: float = PREDICTION_MARGIN_PX,
                   projected: tuple | None = None) -> np.ndarray | None:
    """Windows (m, 4) x0, y0, x1, y1 (px) about the predicted pixel of every known point a
    `_prediction_model` puts near its image (within margin_px, as `predicted_projections`): the
    prediction's move under the priors' error bounds (`prediction_radius`) plus `gate_px`, only
    those reaching into the image. None where they cover more than MAX_WINDOW_SHARE of the image
    (summed): then it is searched whole. projected: `_projected_points(model, margin_px)` if already made."""
    camera, cam_from_world, _ = model
    uv, _, world = _projected_points(model, margin_px) if projected is None else projected
    xyz = cam_from_world.apply(world)
    reach = prediction_radius(camera, xyz, attitude_deg, position_m) + gate_px
    boxes = np.column_stack([uv - reach[:, None], uv + reach[:, None]])
    image = np.array([-0.5, -0.5, camera.width - 0.5, camera.height - 0.5])
    clipped = np.column_stack([np.maximum(boxes[:, :2], image[:2]), np.minimum(boxes[:, 2:], image[2:])])
    size = clipped[:, 2:] - clipped[:, :2]
    seen = np.all(size > 0, axis=1)
    if np.prod(size[seen], axis=1).sum() > MAX_WINDOW_SHARE * camera.width * camera.height:
        return None
    return clipped[seen]


# ------------------------------------------------------------------------------ per image


def process_image(dataset: Dataset, image: str, rig: Rig | None = None, calibrated: Camera | None = None,
                  margin_px: float = PREDICTION_MARGIN_PX, gate_px: float = VERIFY_GATE_PX,
                  identify_gate_px: float = GATE_PX, identify_min_inliers: int = MIN_INLIERS,
                  seconds: dict | None = None, attitude_deg: float | None = PRIOR_ATTITUDE_DEG,
                  position_m: float = PRIOR_POSITION_M, lever_arm: np.ndarray | None = None) -> pd.DataFrame:
    """Detections of one image with ids: DataFrame of `detect`'s columns, point_id ('' when unidentified)
    and id_refusal (why a detection has no id, '' where it has one; not written to the markers file).

    rig, calibrated: as `predicted_projections`; margin_px: how far outside the image predictions
    are kept; gate_px: the pose verification's residual gate for calibration images;
    identify_gate_px, identify_min_inliers: `identify`'s final gate and fewest matches;
    attitude_deg, position_m: the priors' error bounds of the search windows (`search_windows`;
    attitude_deg None: the whole image is searched); lever_arm: the POS lever arm (`_prediction_model`);
    seconds: if given, receives the wall time of each phase (decode_s, detect_s, refine_s,
    identify_s), the windows searched (0: none) and whole_image (1 where the whole image was).
    """
    seconds = {} if seconds is None else seconds
    seconds.update(detect_s=0.0, refine_s=0.0, identify_s=0.0)
    started = time.perf_counter()
    pixels = dataset.read_image(image)
    seconds["decode_s"] = time.perf_counter() - started
    model = _prediction_model(dataset, image, rig, calibrated, lever_arm)  # a sentence: why there is none
    projected = None if isinstance(model, str) else _projected_points(model, margin_px)  # windows' and identify's
    windows = None if projected is None or attitude_deg is None else search_windows(
        model, attitude_deg, position_m, identify_gate_px, margin_px, projected)
    seconds["detect_s"] = time.perf_counter() - started - seconds["decode_s"]  # the windows are detection's
    seconds["windows"], seconds["whole_image"] = 0 if windows is None else len(windows), 0
    named = (gate_px, identify_gate_px, identify_min_inliers)
    if windows is not None and len(windows):
        found = _identified(dataset, image, pixels, (model, projected), named, seconds, windows)
        if (found["point_id"] != "").any():
            return found
        log.info("markers %s: nothing identified in the %d windows about the predictions: the whole image "
                 "(are the priors within %g deg and %g m?)", image, len(windows), attitude_deg, position_m)
    seconds["whole_image"] = 1
    return _identified(dataset, image, pixels, (model, projected), named, seconds)


def _identified(dataset: Dataset, image: str, pixels: np.ndarray, predicted: tuple, settings: tuple, seconds: dict,
                windows: np.ndarray | None = None) -> pd.DataFrame:
    """`process_image`'s detections of `image` (pixels (h, w)) in `windows` (m, 4) (None: the whole
    image) named from predicted: the `_prediction_model` (or why there is none) and its `_projected_points`
    (None where there is none); settings: its gate_px, identify_gate_px and identify_min_inliers.
    Adds each phase's seconds to `seconds`."""
    model, projected = predicted
    gate_px, identify_gate_px, identify_min_inliers = settings
    phases = {}
    if windows is None:
        found, rejected = detect(pixels, with_rejected=True, seconds=phases)
    else:
        found, rejected = detect_in_windows(pixels, windows, with_rejected=True, seconds=phases)
    started = time.perf_counter()
    found["point_id"] = ""
    found["id_refusal"] = ""
    if isinstance(model, str) and len(found):
        found["id_refusal"] = model
        log.warning("markers %s: %d detected, none can be identified: %s", image, len(found), model)
    if not isinstance(model, str) and len(found):
        uv, ids = projected[:2]
        height, width = pixels.shape
        named = identify_with_reasons(uv_of(found), uv, ids, (width, height),
                                      rejected=uv_of(rejected), gate_px=identify_gate_px,
                                      min_inliers=identify_min_inliers, projective=wide_field(model[0]))
        found["point_id"], found["id_refusal"] = named.ids, named.reasons
        if _first_row(dataset.images, "image", image, ("stage",))["stage"] != "flight":
            verified = verify_with_pose(uv_of(found), named.ids, dataset.points,
                                        image_centre(width, height), gate_px)
            found.loc[(verified == "") & (named.ids != ""), "id_refusal"] = (
                f"the pose fitted to the image's ids misses it by more than {gate_px:g} px")
            found["point_id"] = verified
        if not (found["point_id"] != "").any() and windows is None:
            log.warning("markers %s: %d detected, none identified: the priors predict %d known point(s) near the "
                        "image and none matches a detection (check the prior centre and attitude, and focal_px)",
                        image, len(found), len(uv))
    phases["identify_s"] = time.perf_counter() - started
    for phase, value in phases.items():
        seconds[phase] = seconds.get(phase, 0.0) + value
    return found


def verify_with_pose(uv: np.ndarray, ids: np.ndarray, points: pd.DataFrame, principal_point,
                     gate_px: float = VERIFY_GATE_PX) -> np.ndarray:
    """Ids (n,) ('' = none) of detections uv (n, 2) that one camera pose explains.

    Fits pose + focal length (PnPf) to the identified detections and drops the worst id while its
    residual exceeds gate_px. With too few ids left for a fit, all are dropped: an id no
    pose confirms is not trusted.
    """
    from ..calib.pnpf import solve_pnpf  # with scipy.optimize: for calibration images, not a flight batch's job

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
        uv_fit = project_unmasked(cam_from_world.apply(X), Camera(focal, focal, *principal_point, 0.0, 0, 0))
        residual = np.hypot(*(uv_fit - uv[keep]).T)
        worst = int(np.argmax(residual))
        if residual[worst] <= gate_px:
            return ids
        ids[keep[worst]] = ""


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
