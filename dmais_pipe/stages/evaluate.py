"""`dmais evaluate`: the errors of every pose (evaluate) and the statistics the report shows.

Writes evaluation.csv, evaluation_<label>.csv per camera subset, tables/pose_methods.csv,
tables/conf.csv (when subsets were solved), tables/residuals.csv (flight residuals per camera of the
observations each pose used) and, when markers were extracted, tables/marker_cameras.csv and
tables/marker_images.csv (marker quality, markers.quality). The report renders these files and
computes nothing of its own.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from ..evaluate import (POS, angular_errors, conf_table, evaluate_poses, every_camera_eps_proj, group_offsets,
                        mean_focal_px, pose_methods_table, residual_table, subset_cameras, used_observations)
from ..markers.quality import FLAG_FACTOR, FLAG_MIN_SIGMA_PX, camera_quality, image_quality
from ..rig import Rig
from ..workspace import CENTER, ResultsError, Workspace
from . import setting

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conf:
    """The evaluation's settings; an image's markers are flagged as poor when their median sigma
    exceeds both flag_factor x its camera's median and flag_min_sigma_px."""

    flag_factor: float = setting(FLAG_FACTOR, "flag an image whose median marker sigma exceeds this many times "
                                              "its camera's median", above=0)
    flag_min_sigma_px: float = setting(FLAG_MIN_SIGMA_PX, "... and exceeds this (px)", minimum=0)


CONFS = {"default": Conf()}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    rig, whole_rig = workspace.load_rig(), workspace.load_pose_observations()
    return _poses(workspace, rig, whole_rig) + _residuals(workspace, rig, whole_rig) + _markers(workspace, conf)


def _poses(workspace: Workspace, rig: Rig, whole_rig: pd.DataFrame | None) -> list[Path]:
    """evaluation.csv, tab:pose_methods and, per camera subset, evaluation_<label>.csv and tab:conf.
    whole_rig: poses.csv's per-observation table (None when it has none)."""
    dataset = workspace.dataset
    truth, poses = workspace.load_truth_frames(), workspace.load_poses()
    pos = dataset.frames.set_index("frame").loc[poses["frame"], list(POS)].to_numpy(dtype=float)
    offsets = group_offsets(poses[list(CENTER)].to_numpy(dtype=float), pos, poses["group"])
    for group, offset in offsets.items():
        log.info("lever-arm offset (estimate - POS) of group %s: (%.3f, %.3f, %.3f) m", group, *offset)
    observations = workspace.load_observations()
    evaluation = evaluate_poses(poses, dataset, rig, truth, offsets, used_observations(observations, whole_rig))
    table = pose_methods_table(evaluation)
    written = [workspace.save_evaluation(evaluation), workspace.save_table("pose_methods", table)]
    subsets = {}
    for label, path in workspace.subset_labels().items():
        try:
            allowed = subset_cameras(label, rig)
        except ValueError as error:
            raise ResultsError(path, str(error)) from None
        used = used_observations(observations, whole_rig, workspace.load_pose_observations(path))
        subset = evaluate_poses(workspace.load_poses(path, allowed), dataset, rig, truth, offsets, used)
        subset["eps_proj_all_px"] = every_camera_eps_proj(dataset, rig, subset, used)
        subset["eps_ang_all_arcmin"] = angular_errors(subset["eps_proj_all_px"], mean_focal_px(rig, rig.camera_names))
        subsets[label] = subset
        written.append(workspace.save_evaluation(subset, label))
    written += _replace_table(workspace, "conf", conf_table(subsets, rig) if subsets else None)
    for row in table.itertuples(index=False):
        log.info("group %s: %d frames, eps_pos %.3f m, eps_ang %.3f', eps_proj %.3f px, %.2f ms", row.group,
                 row.n_frames, row.eps_pos_mean_m, row.eps_ang_mean_arcmin, row.eps_proj_mean_px, row.time_mean_ms)
    return written


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
