"""`dmais evaluate`: the errors of every pose (evaluate) and the statistics the report shows.

Writes evaluation.csv, evaluation_<label>.csv per camera subset, tables/lever_arm.csv (the POS
lever arm and the INS boresight, pos_calibration), tables/pose_methods.csv, tables/conf.csv (when
subsets were solved; the full rig is the label of all its cameras), tables/error_budget.csv (each
camera set's error budget from the poses files' budgets, evaluate.error_budget_table),
tables/mounting.csv (the rig watched in flight, poses.mounting.csv's), tables/residuals.csv (flight
residuals per camera of the observations each pose used) and, when markers were extracted,
tables/marker_cameras.csv and tables/marker_images.csv (marker quality, markers.quality). The
report renders these files and computes nothing of its own.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ..dataset import PRIOR_QUAT, Dataset
from ..evaluate import (ARCMIN_PER_RAD, angular_errors, conf_table, error_budget_table, evaluate_poses,
                        every_camera_eps_proj, fit_pos_lever_arm, group_offsets, mean_focal_px, pos_positions,
                        pose_methods_table, residual_table, subset_cameras, used_observations)
from ..geo import ned_attitude
from ..geometry import exp_so3, rotation_from_quat
from ..markers.quality import FLAG_FACTOR, FLAG_MIN_SIGMA_PX, camera_quality, image_quality
from ..pos_calibration import Boresight, LeverArm, calibration_table, fit_boresight
from ..rig import Rig
from ..workspace import CENTER, QUAT, ResultsError, Workspace
from . import setting
from .pose import subset_label

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conf:
    """The evaluation's settings; an image's markers are flagged as poor when their median sigma
    exceeds both flag_factor x its camera's median and flag_min_sigma_px. The POS calibration:
    pos_calibration."""

    flag_factor: float = setting(FLAG_FACTOR, "flag an image whose median marker sigma exceeds this many times "
                                              "its camera's median", above=0)
    flag_min_sigma_px: float = setting(FLAG_MIN_SIGMA_PX, "... and exceeds this (px)", minimum=0)
    boresight: bool = setting(True, "also estimate the INS boresight from frames.csv's INS attitudes (prior_q*)")
    min_attitude_spread_deg: float = setting(
        5.0, "below this attitude spread over the frames a lever arm cannot be told from a world offset, which is "
             "fitted instead", minimum=0)


CONFS = {"default": Conf()}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    rig, whole_rig = workspace.load_rig(), workspace.load_pose_observations()
    return _poses(workspace, rig, whole_rig, conf) + _residuals(workspace, rig, whole_rig) + _markers(workspace, conf)


def _poses(workspace: Workspace, rig: Rig, whole_rig: pd.DataFrame | None, conf: Conf) -> list[Path]:
    """tables/lever_arm.csv, evaluation.csv, tab:pose_methods and, per camera subset,
    evaluation_<label>.csv and tab:conf. whole_rig: poses.csv's per-observation table (None when
    it has none)."""
    dataset = workspace.dataset
    truth, poses = workspace.load_truth_frames(), workspace.load_poses()
    lever_arm = fit_pos_lever_arm(poses, dataset, conf.min_attitude_spread_deg)
    boresight = _boresight(poses, dataset) if conf.boresight else None
    _log_calibration(lever_arm, boresight)
    offsets = group_offsets(poses[list(CENTER)].to_numpy(dtype=float), pos_positions(poses, dataset), poses["group"])
    for group, offset in offsets.items():
        log.info("mean offset (estimate - POS) of group %s: (%.3f, %.3f, %.3f) m", group, *offset)
    observations = workspace.load_observations()
    used_by_rig = used_observations(observations, whole_rig)
    evaluation = with_local_pos_comparison(evaluate_poses(poses, dataset, rig, truth, offsets, used_by_rig, lever_arm),
                                           dataset, lever_arm, boresight)
    table = pose_methods_table(evaluation)
    written = [workspace.save_table("lever_arm", calibration_table(lever_arm, boresight, _simulator_truth(dataset))),
               workspace.save_evaluation(evaluation), workspace.save_table("pose_methods", table)]
    subsets = {}
    for label, path in workspace.subset_labels().items():
        try:
            allowed = subset_cameras(label, rig)
        except ValueError as error:
            raise ResultsError(path, str(error)) from None
        used = used_observations(observations, whole_rig, workspace.load_pose_observations(path))
        subset = with_local_pos_comparison(evaluate_poses(workspace.load_poses(path, allowed), dataset, rig, truth,
                                                          offsets, used, lever_arm), dataset, lever_arm, boresight)
        subsets[label] = _with_every_camera(subset, dataset, rig, used)
        written.append(workspace.save_evaluation(subsets[label], label))
    full_rig = subset_label(rig, rig.camera_names)  # tab:conf's #01234
    if subsets and full_rig not in subsets:
        subsets[full_rig] = _with_every_camera(evaluation, dataset, rig, used_by_rig)
    written += _replace_table(workspace, "conf", conf_table(subsets, rig) if subsets else None)
    budgets = {label: workspace.load_pose_budget(path) for label, path in workspace.subset_labels().items()}
    budgets[full_rig] = workspace.load_pose_budget()
    budget = error_budget_table({**subsets, full_rig: subsets.get(full_rig, evaluation)}, budgets)
    written += _replace_table(workspace, "error_budget", budget if len(budget) else None)
    mounting = workspace.load_pose_mounting()
    written += _replace_table(workspace, "mounting", mounting)
    for row in table.itertuples(index=False):
        log.info("group %s: %d frames, eps_pos %.3f m (per-group offset: %.3f m), eps_ang %.3f', eps_proj %.3f px, "
                 "%.2f ms", row.group, row.n_frames, row.eps_pos_mean_m, row.eps_pos_group_mean_m,
                 row.eps_ang_mean_arcmin, row.eps_proj_mean_px, row.time_mean_ms)
    return written


#: evaluation.csv's POS and INS comparison in local terms, with dataset.yaml's crs: the estimate
#: (centre + lever arm; the boresight times the rig's attitude) minus the POS and the INS, along
#: north, east, down at the frame (m) and in NED heading, pitch, roll (arc-min).
LOCAL_COMPARISON_COLUMNS = ("pos_diff_north_m", "pos_diff_east_m", "pos_diff_down_m", "ins_diff_heading_arcmin",
                            "ins_diff_pitch_arcmin", "ins_diff_roll_arcmin")


def with_local_pos_comparison(evaluation: pd.DataFrame, dataset: Dataset, lever_arm: LeverArm,
                              boresight: Boresight | None) -> pd.DataFrame:
    """evaluation + LOCAL_COMPARISON_COLUMNS where the dataset has a crs (the INS columns where a
    boresight was fitted); the table as it is otherwise."""
    if dataset.geo is None or not len(evaluation):
        return evaluation
    centres = evaluation[list(CENTER)].to_numpy(dtype=float)
    world_from_rig = np.swapaxes(rotation_from_quat(evaluation[list(QUAT)].to_numpy(dtype=float)), 1, 2)
    ned_from_world = dataset.geo.ned_from_enu(centres)
    difference = centres + lever_arm.pos_offsets(world_from_rig) - pos_positions(evaluation, dataset)
    out = evaluation.copy()
    out[list(LOCAL_COMPARISON_COLUMNS[:3])] = np.einsum("fij,fj->fi", ned_from_world, difference)
    if boresight is not None:
        ins = rotation_from_quat(dataset.frames.set_index("frame").loc[evaluation["frame"], list(PRIOR_QUAT)]
                                 .to_numpy(dtype=float))
        imu_from_rig = exp_so3(boresight.rotvec)
        estimated = ned_attitude(ned_from_world, world_from_rig @ imu_from_rig.T)
        given = ned_attitude(ned_from_world, np.swapaxes(ins, 1, 2))
        difference = (estimated - given + 180.0) % 360.0 - 180.0
        out[list(LOCAL_COMPARISON_COLUMNS[3:])] = difference * 60.0
    return out


def _with_every_camera(evaluation: pd.DataFrame, dataset: Dataset, rig: Rig, used: pd.DataFrame) -> pd.DataFrame:
    """evaluation + eps_proj_all_px, eps_ang_all_arcmin: its poses reprojected into every camera."""
    out = evaluation.copy()
    out["eps_proj_all_px"] = every_camera_eps_proj(dataset, rig, out, used)
    out["eps_ang_all_arcmin"] = angular_errors(out["eps_proj_all_px"], mean_focal_px(rig, rig.camera_names))
    return out


def _boresight(poses: pd.DataFrame, dataset: Dataset) -> Boresight | None:
    """The INS boresight of poses' frames, None (logged) when frames.csv lacks an INS attitude."""
    ins = dataset.frames.set_index("frame").loc[poses["frame"], list(PRIOR_QUAT)].to_numpy(dtype=float)
    lacking = poses["frame"][~np.isfinite(ins).all(axis=1)].tolist()
    if lacking:
        log.info("no boresight: frames.csv has no INS attitude (prior_qw..prior_qz) for frame(s) %s",
                 ", ".join(lacking[:5]) + (", ..." if len(lacking) > 5 else ""))
        return None
    estimated = rotation_from_quat(poses[list(QUAT)].to_numpy(dtype=float))
    return fit_boresight(estimated, rotation_from_quat(ins))


def _log_calibration(lever_arm: LeverArm, boresight: Boresight | None) -> None:
    name = "lever arm (POS point in the rig frame)" if lever_arm.frame == "rig" else "world offset POS - estimate"
    log.info("%s over %d frames: (%.3f, %.3f, %.3f) m +- (%.3f, %.3f, %.3f) m; residual RMS per world axis "
             "(%.3f, %.3f, %.3f) m", name, lever_arm.n_frames, *lever_arm.value, *lever_arm.sigma,
             *lever_arm.residual_rms_m)
    if boresight is not None:
        log.info("INS boresight (imu_from_rig rotation vector, rig axes) over %d frames: (%.2f, %.2f, %.2f)' "
                 "+- (%.2f, %.2f, %.2f)'; residual RMS %.2f'", boresight.n_frames,
                 *boresight.rotvec * ARCMIN_PER_RAD, *boresight.sigma * ARCMIN_PER_RAD,
                 boresight.residual_rms_rad * ARCMIN_PER_RAD)


def _simulator_truth(dataset: Dataset) -> dict[str, float] | None:
    """lever_arm.csv's parameter -> the simulator's value (truth/simulation.yaml), None for a real dataset."""
    path = dataset.truth_dir / "simulation.yaml"
    if not path.is_file():
        return None
    flight = (yaml.safe_load(path.read_text()) or {}).get("flight", {})
    lever = flight.get("lever_arm_m", [np.nan] * 3)
    boresight = np.multiply(flight.get("ins_boresight_deg", [0.0] * 3), 60.0)  # none before it was simulated
    return {**{f"lever_{a}": float(v) for a, v in zip("xyz", lever)},
            **{f"boresight_{a}": float(v) for a, v in zip("xyz", boresight)}}


def _residuals(workspace: Workspace, rig: Rig, observations: pd.DataFrame | None) -> list[Path]:
    """tables/residuals.csv: per camera, the residuals of the observations the whole rig's poses used
    (observations: poses.csv's per-observation table)."""
    if observations is None:
        log.warning("%s has no per-observation file beside it: no residual table", workspace.poses_path())
        return _replace_table(workspace, "residuals", None)
    used = observations[observations["used"]].dropna(subset=["du", "dv"])
    cameras = [c for c in rig.camera_names if c in set(used["camera"])]
    return [workspace.save_table("residuals", residual_table(used, cameras))]


def _markers(workspace: Workspace, conf: Conf) -> list[Path]:
    """tables/marker_images.csv and marker_cameras.csv from every extracted image's markers."""
    dataset = workspace.dataset
    extracted = [i for i in dataset.images_to_extract() if workspace.markers_path(i).is_file()]
    markers = {image: workspace.load_markers(image) for image in extracted}
    images = cameras = None
    if markers:
        camera_of = dict(zip(dataset.images["image"], dataset.images["camera"]))
        images = image_quality(markers, camera_of, conf.flag_factor, conf.flag_min_sigma_px)
        cameras = camera_quality(images, markers, camera_of)
    return _replace_table(workspace, "marker_images", images) + _replace_table(workspace, "marker_cameras", cameras)


def _replace_table(workspace: Workspace, name: str, table: pd.DataFrame | None) -> list[Path]:
    """Write the table, or remove a stale one of an earlier run when this run has none."""
    if table is not None:
        return [workspace.save_table(name, table)]
    if workspace.table_path(name).exists():
        log.info("removing the stale %s: this run has no such table", workspace.table_path(name))
        workspace.table_path(name).unlink()
    return []
