"""`dmais pose`: the rig pose of every flight frame (pose.flight), for the whole rig or a camera subset.

Reads rig.json and the identified observations; writes poses.csv (every camera) or
poses_<label>.csv for a camera subset (label = the digits of the cameras' positions in the rig,
e.g. 012), each with its per-observation file and its error budget (each frame's variances per
component of the error model) beside it (Workspace.save_poses).

- `run`: every frame (of `groups`, when given). A per-group job with no solvable frame writes an
  empty part with a warning, so that one group seen badly by a camera subset does not stop the
  workflow;
- `merge`: the workflow's per-group parts of one camera set into one poses file; it fails only
  when every part is empty.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..blas import single_threaded_blas
from ..dataset import FRAME_COLUMNS, Dataset, factorized, point_sigma
from ..errors import DmaisError
from ..geometry import rotation_from_quat
from ..pose.error_model import CALIBRATION_PARAMETERS, COMPONENTS, UNITS, calibration_parameters, survey_sigma
from ..pose.flight import ROBUST_THRESHOLD_PX, FlightPoses, solve_flight
from ..pose.mounting import GroupRig, adjust_group_rig, mounting_table
from ..rig import Rig
from ..geo import Geo, ned_attitude, ned_sigmas
from ..workspace import (CENTER, MOUNTING_COLUMNS, POSE_GEO_COLUMNS, POSE_UNCERTAINTY_COLUMNS, QUAT, TRANSLATION,
                         ResultsError, Workspace)
from . import setting, three_numbers

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conf:
    """How every frame is solved (pose.flight)."""

    robust: bool = setting(False, "LO-RANSAC against wrong correspondences before the paper's solver")
    refine: bool = setting(False, "polish every pose on the reprojection error")
    robust_threshold_px: float = setting(
        ROBUST_THRESHOLD_PX, "RANSAC's inlier threshold (px; an angle per observation: this over its camera's fx)",
        above=0)
    error_sigmas: tuple = setting((), "components of the sigmas' error model fixed at a known 1-sigma, "
                                  "NAME=VALUE: pixel (px), survey (m, horizontal; also the vertical unless "
                                  "survey_vertical is given), survey_vertical (m), jitter, mounting (arc-min), focal "
                                  "(ppm), calibration (a factor on rig.json's covariance); the others are estimated")
    in_flight_rig: bool = setting(False, "solve every frame again with its group's rig watched in flight (the "
                                  "mounting file's, pose.mounting) instead of the calibrated one")
    error_priors: tuple = setting(("mounting=0.15",), "the 1-sigma, NAME=VALUE as error_sigmas, of components "
                                  "the flight's residuals cannot tell (not estimable or not significant), used "
                                  "instead of 0")
    pos_lever_arm: tuple = setting((), "the POS reference point in the rig frame, x,y,z (m; tables/lever_arm.csv "
                                   "of an earlier run): given, the rig watched in flight holds each frame's centre "
                                   "to frames.csv's POS position less it, which fixes the cameras' common tilt "
                                   "that the rig's height otherwise trades against")
    pos_sigma: tuple = setting((0.02, 0.02, 0.03), "the POS positions' 1-sigma along the world x,y,z (m), "
                               "with pos_lever_arm")


#: "paper": the paper's solver alone; "robust": RANSAC first and a polished pose, for wrong ids.
CONFS = {"paper": Conf(), "robust": Conf(robust=True, refine=True)}


def run(workspace: Workspace, conf: Conf = Conf(), cameras: list[str] | None = None,
        groups: list[str] | None = None, out: Path | None = None) -> list[Path]:
    """Solve the frames (of `groups`) with `cameras` (default every camera); write `out` (default
    poses.csv or poses_<label>.csv) and its per-observation file."""
    rig = workspace.load_rig()
    chosen = _cameras(rig, cameras)
    prior = pos_prior(conf)
    record = _rig_record(workspace)
    calibration = calibration_covariance(record, rig.camera_names, calibration_parameters(rig))
    solved = _solve(workspace, conf, rig, record, calibration, chosen, groups)
    if set(chosen) == set(rig.camera_names) and len(solved.table):
        watched = watch_rig(workspace.dataset, rig, solved, calibrated_noise_px(record, chosen), *prior,
                            calibration=calibration)
        if conf.in_flight_rig:
            solved = _with_in_flight_rigs(workspace, conf, rig, record, calibration, solved, watched)
        mounting = mounting_table(watched)
    else:  # the rig is watched through the whole rig's solves only
        mounting = pd.DataFrame(columns=list(MOUNTING_COLUMNS))
    table = solved.table
    if table.empty and not groups:
        raise DmaisError(f"pose: no flight frame of {workspace.dataset.root} could be solved with cameras {chosen}")
    if table.empty:
        log.warning("pose: no flight frame of group(s) %s could be solved with cameras %s", groups, chosen)
    if workspace.dataset.geo is not None and len(table):
        table = with_geodetic_columns(table, workspace.dataset.geo, solved.covariance)
    path = out or poses_path(workspace, rig, chosen)
    written = workspace.save_poses(table, solved.observations, path, solved.budget, mounting)
    if len(table):
        log.info("pose: %d frames -> %s (median %.2f ms per solve)", len(table), path, table["time_ms"].median())
    return written


def merge(workspace: Workspace, parts: list[Path], cameras: list[str] | None = None,
          out: Path | None = None) -> list[Path]:
    """Concatenate per-group pose files (`run(groups=[g], out=part)`) of one camera set, with their
    per-observation files and error budgets, into `out` (default poses.csv or poses_<label>.csv)."""
    if not parts:
        raise DmaisError("pose: no per-group pose file to merge")
    rig = workspace.load_rig()
    chosen = _cameras(rig, cameras)
    tables, observations, budgets, mountings = [], [], [], []
    for part in parts:
        tables.append(workspace.load_poses(part, chosen, empty_ok=True))
        observations.append(workspace.load_pose_observations(part))
        budgets.append(workspace.load_pose_budget(part))
        mountings.append(workspace.load_pose_mounting(part))
        if observations[-1] is None:
            raise ResultsError(part, "has no per-observation file beside it; the per-group pose job writes one")
    merged = pd.concat(tables, ignore_index=True)
    if merged.empty:
        raise DmaisError(f"pose: none of the {len(parts)} per-group pose files has a solved frame")
    repeated = merged["frame"][merged["frame"].duplicated()]
    if len(repeated):
        raise DmaisError(f"pose: frame {repeated.iloc[0]!r} appears in more than one of {[str(p) for p in parts]}")
    path = out or poses_path(workspace, rig, chosen)
    # the budget and the mounting when every part has one (parts written before them have none)
    budget = None if any(b is None for b in budgets) else \
        pd.concat(budgets, ignore_index=True).sort_values("frame", kind="stable")
    mounting = None if any(m is None for m in mountings) else pd.concat(mountings, ignore_index=True)
    return workspace.save_poses(merged.sort_values("frame", kind="stable"),
                                pd.concat(observations, ignore_index=True).sort_values("frame", kind="stable"), path,
                                budget, mounting)


def _solve(workspace: Workspace, conf: Conf, rig: Rig, record: dict, calibration: np.ndarray, chosen: list[str],
           groups: list[str] | None) -> FlightPoses:
    """pose.flight.solve_flight of the frames (of `groups`) with `chosen` cameras of `rig`; record:
    rig.json as written, calibration its `calibration_covariance`."""
    with single_threaded_blas():  # small matrices: threads only add hand-offs to time_ms
        return solve_flight(workspace.dataset, rig, workspace.load_observations(), chosen, conf.robust, conf.refine,
                            groups, conf.robust_threshold_px, calibrated_noise_px(record, chosen),
                            error_settings=error_settings(conf.error_sigmas, "error_sigmas"),
                            error_priors=error_settings(conf.error_priors, "error_priors"),
                            calibration_covariance=calibration)


#: The least pixel noise the rig adjustment weighs the markers with (px): where the error model's
#: pixel term is 0 (not told from the survey's) and rig.json has no calibration noise.
WATCH_MIN_PIXEL_PX = 0.05
#: The least survey sigma (m) of the rig adjustment's points, whose surveyed coordinates are priors:
#: where the points are exact (sigma_m 0, a printed board) or the survey term is not significant.
WATCH_MIN_SURVEY_M = 1e-4


def watch_rig(dataset: Dataset, rig: Rig, solved: FlightPoses, calibrated_noise: float,
              lever_arm: np.ndarray | None = None, pos_sigma: np.ndarray | None = None,
              calibration: np.ndarray | None = None) -> dict[str, GroupRig]:
    """pose.mounting's group rig adjustment of every group of `solved` (the whole rig's solves), with
    the group's error model: its pixel noise (at least the calibration's, `calibrated_noise`, and
    WATCH_MIN_PIXEL_PX), its camera rotation per frame (jitter and mounting together: the model
    tells their sum far better than their split, and an adjustment without the vibration there is
    turns the cameras by tens of arc-min to fit it) and its survey sigma (a point's own `sigma_m`
    where given; at least WATCH_MIN_SURVEY_M); with a lever_arm (3,) m in the rig frame, the frames' centres held to their POS
    positions less it, per-axis sigma pos_sigma (3,) m; with the calibration's joint covariance
    `calibration` (`calibration_covariance`), the changes' sigmas carry its share (a calibration error
    is not flagged as a change). A group it cannot adjust is left out with a warning naming it."""
    table, rows = solved.table, _WatchedRows.of(dataset, solved)
    pos = dataset.frames.set_index("frame")[list(FRAME_COLUMNS[2:])]  # pos_x, pos_y, pos_z
    table_groups = table["group"].astype(str).to_numpy(object)
    watched = {}
    for group, model in solved.error_model.items():
        chosen = np.flatnonzero(table_groups == str(group))  # the group's rows of the table
        frames = table.iloc[chosen]
        place = np.full(len(table) + 1, -1)  # each table row's place among the group's frames; -1 past the end
        place[chosen] = np.arange(len(chosen))
        frame_index = place[rows.table_row]
        kept = np.flatnonzero(frame_index >= 0)
        pixel = max(model.sigma["pixel"], calibrated_noise if np.isfinite(calibrated_noise) else 0.0,
                    WATCH_MIN_PIXEL_PX)
        rotation = float(np.hypot(model.sigma["jitter"], model.sigma["mounting"]))
        point = rows.point[kept]
        survey = np.maximum(survey_sigma(rows.point_sigma, model), WATCH_MIN_SURVEY_M)  # (p, 3) per distinct point
        R = rotation_from_quat(frames[list(QUAT)].to_numpy(float))
        centres = None if lever_arm is None else \
            pos.loc[frames["frame"]].to_numpy(float) - np.einsum("fji,j->fi", R, lever_arm)
        try:  # the per-observation arguments are the callee's alone (no ** call), which frees them once read
            watched[str(group)] = adjust_group_rig(
                rig, rows.cameras[kept], rows.uv[kept], rows.point_ids[kept], rows.xyz[point], frame_index[kept], R,
                frames[list(TRANSLATION)].to_numpy(float), pixel, rotation, survey[point], center_prior_m=centres,
                center_sigma_m=None if lever_arm is None else pos_sigma, calibration_covariance=calibration)
        except DmaisError as error:
            log.warning("pose: the rig of group %s is not watched in flight: %s", group, error)
    return watched


@dataclass(frozen=True)
class _WatchedRows:
    """The used observations (n) of `solve_flight`'s per-observation table, in its order, as `watch_rig`
    reads them: table_row (n,) the row of each one's frame in the poses table (-1: none), cameras and
    point_ids (n,) str objects, uv (n, 2); point (n,) each one's distinct point, of the point ids' xyz (p, 3)
    and point_sigma (p, 3) (dataset.point_sigma). Every id is looked up once per distinct id, not per row."""

    table_row: np.ndarray
    cameras: np.ndarray
    point_ids: np.ndarray
    uv: np.ndarray
    point: np.ndarray
    xyz: np.ndarray
    point_sigma: np.ndarray

    @classmethod
    def of(cls, dataset: Dataset, solved: FlightPoses) -> _WatchedRows:
        observations = solved.observations
        used = observations["used"].to_numpy(bool)
        frame, frames = factorized(observations["frame"].to_numpy(object)[used])  # hashed a frame's block at once
        point_ids = observations["point_id"].to_numpy(object)[used]
        point, ids = pd.factorize(point_ids)
        ids = np.asarray(ids, dtype=object)
        table_row = pd.Index(solved.table["frame"]).get_indexer(frames)[frame] if len(frames) else frame
        points = dataset.points
        return cls(table_row, observations["camera"].to_numpy(object)[used], point_ids,
                   observations[["u", "v"]].to_numpy(float)[used], point,
                   points.loc[ids, ["x", "y", "z"]].to_numpy(float).reshape(-1, 3), point_sigma(points, ids))


def with_geodetic_columns(table: pd.DataFrame, geo: Geo, covariance: np.ndarray) -> pd.DataFrame:
    """The poses `table` (computation frame) with POSE_GEO_COLUMNS after its uncertainty columns: the
    centre's WGS 84 latitude, longitude, height, the NED attitude at it (geo.ned_attitude) and their
    1-sigma (geo.ned_sigmas, from covariance (F, 6, 6), FlightPoses.covariance)."""
    centres = table[list(CENTER)].to_numpy(float)
    ned_from_world = geo.ned_from_enu(centres)
    world_from_rig = np.swapaxes(rotation_from_quat(table[list(QUAT)].to_numpy(float)), 1, 2)
    attitude = ned_attitude(ned_from_world, world_from_rig)
    sigma_position, sigma_attitude = ned_sigmas(
        ned_from_world, table[["heading_deg", "pitch_deg", "roll_deg"]].to_numpy(float), attitude,
        table[["sigma_x_m", "sigma_y_m", "sigma_z_m"]].to_numpy(float),
        table[["sigma_heading_arcmin", "sigma_pitch_arcmin", "sigma_roll_arcmin"]].to_numpy(float), covariance)
    values = np.column_stack([geo.geodetic_from_enu(centres), attitude, sigma_position, sigma_attitude])
    at = list(table.columns).index(POSE_UNCERTAINTY_COLUMNS[-1]) + 1
    out = table.drop(columns=[c for c in POSE_GEO_COLUMNS if c in table.columns])  # a frames.csv column of that name
    return pd.concat([out.iloc[:, :at], pd.DataFrame(values, columns=list(POSE_GEO_COLUMNS), index=out.index),
                      out.iloc[:, at:]], axis=1)


def pos_prior(conf: Conf) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The settings pos_lever_arm (3,) m and pos_sigma (3,) m as numbers, (None, None) without a lever
    arm; DmaisError naming the setting where one is not three finite numbers (pos_sigma above 0)."""
    if not conf.pos_lever_arm:
        return None, None
    lever, sigma = (np.array(three_numbers(getattr(conf, key), f"pose: setting {key}"))
                    for key in ("pos_lever_arm", "pos_sigma"))
    if not (sigma > 0).all():
        given = ",".join(map(str, conf.pos_sigma))
        raise DmaisError(f"pose: setting pos_sigma: every value must be above 0, got {given}")
    return lever, sigma


def _with_in_flight_rigs(workspace: Workspace, conf: Conf, rig: Rig, record: dict, calibration: np.ndarray,
                         solved: FlightPoses, watched: dict[str, GroupRig]) -> FlightPoses:
    """`solved` with each watched group's frames solved again with its in-flight rig."""
    parts = [_solve(workspace, conf, watched[g].rig, record, calibration, rig.camera_names, [g]) if g in watched
             else _group_of(solved, g) for g in pd.unique(solved.table["group"].astype(str))]
    return FlightPoses(pd.concat([p.table for p in parts], ignore_index=True),
                       pd.concat([p.observations for p in parts], ignore_index=True),
                       {g: m for p in parts for g, m in p.error_model.items()},
                       pd.concat([p.budget for p in parts], ignore_index=True),
                       np.concatenate([p.covariance for p in parts]))


def _group_of(solved: FlightPoses, group: str) -> FlightPoses:
    """The part of `solved` of one group."""
    frames = set(solved.table.loc[solved.table["group"].astype(str) == group, "frame"])
    rows = solved.table["frame"].isin(frames).to_numpy()
    return FlightPoses(solved.table[rows], solved.observations[solved.observations["frame"].isin(frames)],
                       {g: m for g, m in solved.error_model.items() if str(g) == group},
                       solved.budget[solved.budget["frame"].isin(frames)], solved.covariance[rows])


def _rig_record(workspace: Workspace) -> dict:
    """rig.json as written (its extra keys: rms_px, calibration_covariance), {} where unreadable
    (load_rig has read it already, and says what is wrong)."""
    try:
        record = json.loads(workspace.rig_path.read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def calibrated_noise_px(record: dict, cameras: list[str]) -> float:
    """Per-axis pixel noise of the calibration (rig.json's largest per-camera RMS reprojection
    distance `rms_px` of `cameras`, over sqrt 2), NaN when rig.json has none: the uncertainty's
    noise when no frame has enough observations for its own estimate."""
    try:
        rms = record.get("rms_px") or {}
        values = [float(rms[c]) for c in cameras if c in rms]
    except (ValueError, TypeError, AttributeError):
        return np.nan
    values = [v for v in values if np.isfinite(v) and v > 0]
    return max(values) / np.sqrt(2.0) if values else np.nan


def error_settings(items: tuple, key: str) -> dict[str, float]:
    """{component: sigma} of the NAME=VALUE items of the setting `key`; a name that is not a
    component, a repeated one, or a value that is not a finite non-negative number is a DmaisError."""
    settings: dict[str, float] = {}
    for item in items:
        name, _, text = str(item).partition("=")
        name = name.strip()
        if name not in COMPONENTS:
            raise DmaisError(f"pose: setting {key}: {item!r} is not NAME=VALUE with NAME one of "
                             f"{', '.join(COMPONENTS)}")
        if name in settings:
            raise DmaisError(f"pose: setting {key}: {name} is given twice")
        try:
            value = float(text)
        except ValueError:
            value = np.nan
        if not np.isfinite(value) or value < 0:
            raise DmaisError(f"pose: setting {key}: {name}={text.strip()!r} is not a non-negative number "
                             f"({UNITS[name]})")
        settings[name] = value
    return settings


def calibration_covariance(record: dict, cameras: list[str], parameters=CALIBRATION_PARAMETERS) -> np.ndarray:
    """(K C, K C) the joint covariance of `parameters` (K per camera, error_model.calibration_parameters)
    of the rig's `cameras` (in that order) from rig.json's `calibration_covariance`
    (calib.extrinsics.calibration_covariance: parameters "<camera>.<name>", an opencv camera's k1 for
    "d", and their matrix); a parameter it lacks counts as 0, and one that is not readable gives a
    warning and no calibration term."""
    k_all = len(parameters)
    index = {f"{camera}.{name}": k_all * c + k for c, camera in enumerate(cameras)
             for k, name in enumerate(parameters)}
    index.update({f"{camera}.k1": k_all * c + parameters.index("d") for c, camera in enumerate(cameras)})
    covariance = np.zeros((k_all * len(cameras), k_all * len(cameras)))
    given = record.get("calibration_covariance")
    if not given:
        return covariance
    try:
        labels = [str(label) for label in given["parameters"]]
        matrix = np.asarray(given["matrix"], dtype=float).reshape(len(labels), len(labels))
        if not np.isfinite(matrix).all():
            raise ValueError("not finite")
    except (KeyError, ValueError, TypeError) as error:
        log.warning("pose: rig.json's calibration_covariance is not readable (%s); the calibration's error is "
                    "left out", error)
        return covariance
    known = [k for k, label in enumerate(labels) if label in index]
    rows = [index[labels[k]] for k in known]
    covariance[np.ix_(rows, rows)] = matrix[np.ix_(known, known)]
    return covariance


def subset_label(rig: Rig, cameras: list[str]) -> str:
    """Digits of the cameras' positions in the rig, e.g. ['C0', 'C2'] -> '02'."""
    names = rig.camera_names
    return "".join(str(names.index(c)) for c in sorted(cameras, key=names.index))


def poses_path(workspace: Workspace, rig: Rig, cameras: list[str]) -> Path:
    """poses.csv for all cameras, poses_<label>.csv for a subset."""
    if sorted(cameras) == sorted(rig.camera_names):
        return workspace.poses_path()
    return workspace.poses_path(subset_label(rig, cameras))


def _cameras(rig: Rig, requested: list[str] | None) -> list[str]:
    if not requested:
        return rig.camera_names
    unknown = sorted(set(requested) - set(rig.camera_names))
    if unknown:
        raise DmaisError(f"pose: unknown camera(s) {unknown}; the rig has {rig.camera_names}")
    return [c for c in rig.camera_names if c in requested]
