"""Accuracy of the flight poses (paper, "Pose Estimation Results"): the metrics the evaluate stage writes.

Per frame of RESULTS/poses.csv (and of every camera-subset file RESULTS/poses_<label>.csv):

- eps_pos_m: distance between the estimated rig centre moved by the POS lever arm and the POS
  reference position. The paper calibrates the POS "by calculating the average offset between the
  estimated position provided by the DMAIS and the position reported by the POS"; a POS user's
  calibration is a lever arm, the POS reference point in the rig frame (pos_calibration.py: POS =
  centre + world_from_rig.R @ l), fitted once by least squares over every frame of poses.csv (the
  full rig, the hardware calibration) and applied unchanged to the camera subsets with each pose's
  own attitude, so that a group's or a subset's bias counts as error.
- eps_pos_group_m: the literal reading of "average offset": the mean offset estimate - POS (a
  world-frame 3-vector) per frame group, taken from poses.csv and subtracted before the distance
  (a group absent from poses.csv uses the subset's own mean). It absorbs every group's bias, so
  it is the scatter within a group; a group with a single frame has 0 by construction (warning).
- eps_ang_arcmin = eps_proj_px x angular resolution, the angular size of one pixel, 1 / f rad with
  f the mean focal length ((fx + fy) / 2, RESULTS/rig.json) of the cameras the frame used.
- with simulator truth (DATASET/truth/frames.csv): true_pos_err_m, the distance between the
  estimated and the true rig centre, and true_ang_err_arcmin, the angle of R_est R_true^T; and
  crb_pos_m, crb_ang_arcmin, the Cramer-Rao bound of the same frame's geometry at the true pose for
  pixel noise of the frame's eps_proj (`cramer_rao_errors`).

The evaluate stage (`stages.evaluate`) writes evaluation.csv and evaluation_<label>.csv (the
poses columns + the errors), tables/lever_arm.csv (the lever arm and the INS boresight with their
1-sigma), tables/pose_methods.csv (tab:pose_methods: per group mean and sample std (ddof = 1) of
eps_pos, eps_pos_group, eps_ang, eps_proj and the mean time) and, when subset files exist,
tables/conf.csv (tab:conf: per group and subset label the means of eps_pos, eps_pos_group, eps_ang,
eps_proj, with the full rig of poses.csv as the label of all its cameras, 01234). A subset label is
the digits of the camera indexes in rig order (C0..C4): 0, 01, 012, 1234, 01234. A subset's
evaluation also has eps_proj_all_px / eps_ang_all_arcmin: the subset's pose reprojected into every
camera. tab:conf's #0 (57 px, 4.5') can only be read that way, since one camera's own few points
are fitted to a few pixels by its 6-dof pose; conf.csv reports those, and the subset's own as
eps_proj_used_mean_px.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import pandas as pd

from .dataset import Dataset
from .frames import frame_observations
from .geometry import rotation_error, rotation_from_quat
from .pos_calibration import ARCMIN_PER_RAD, LeverArm, fit_lever_arm
from .pose.refine import cramer_rao_bound
from .rig import Rig
from .workspace import CENTER, QUAT, ResultsError, rig_from_world_of

log = logging.getLogger(__name__)

POS = ("pos_x", "pos_y", "pos_z")
ERROR_COLUMNS = ("eps_pos_m", "eps_pos_group_m", "eps_ang_arcmin")
TRUE_ERROR_COLUMNS = ("true_pos_err_m", "true_ang_err_arcmin")
ALL_GROUPS = "all"


# ------------------------------------------------------------------------------ pure metrics


def group_offsets(estimated, reference, groups) -> dict[str, np.ndarray]:
    """Mean offset (3,) estimated - reference per group: eps_pos_group's calibration.

    estimated, reference: (n, 3) positions; groups: (n,) group labels.
    """
    delta = np.asarray(estimated, dtype=float) - np.asarray(reference, dtype=float)
    groups = np.asarray(groups).astype(str)
    return {g: delta[groups == g].mean(axis=0) for g in _ordered(np.unique(groups))}


def position_errors(estimated, reference, groups, offsets: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """(n,) distances |estimated - reference - offset[group]| (m).

    estimated, reference: (n, 3); groups: (n,). `offsets` (group -> (3,)) default to the mean
    offsets of these rows (`group_offsets`); a group missing from `offsets` uses its own mean.
    """
    estimated = np.asarray(estimated, dtype=float)
    reference = np.asarray(reference, dtype=float)
    groups = np.asarray(groups).astype(str)
    own = group_offsets(estimated, reference, groups)
    offsets = {**own, **(offsets or {})}
    offset = np.array([offsets[g] for g in groups]).reshape(-1, 3)
    return np.linalg.norm(estimated - reference - offset, axis=1)


def world_from_rig_rotations(poses: pd.DataFrame) -> np.ndarray:
    """(n, 3, 3) world_from_rig rotations R^T of poses' rig_from_world quaternions (qw..qz)."""
    return np.swapaxes(rotation_from_quat(poses[list(QUAT)].to_numpy(dtype=float).reshape(-1, 4)), -1, -2)


def fit_pos_lever_arm(poses: pd.DataFrame, dataset: Dataset, min_spread_deg: float = 5.0) -> LeverArm:
    """The lever arm (pos_calibration.fit_lever_arm) of `poses` (Workspace.load_poses) against the
    POS positions of dataset.frames; the frames of a flight group share an error."""
    return fit_lever_arm(poses[list(CENTER)].to_numpy(dtype=float), pos_positions(poses, dataset),
                         world_from_rig_rotations(poses), np.radians(min_spread_deg), poses["group"])


def pos_positions(poses: pd.DataFrame, dataset: Dataset) -> np.ndarray:
    """(n, 3) POS positions (frames.csv pos_x..pos_z) of poses' frames."""
    return dataset.frames.set_index("frame").loc[poses["frame"], list(POS)].to_numpy(dtype=float)


def angular_resolution_arcmin(focal_px) -> np.ndarray:
    """Angular size of one pixel (arc-min), 1 / f rad, for focal lengths f (px), scalar or (n,)."""
    return ARCMIN_PER_RAD / np.asarray(focal_px, dtype=float)


def angular_errors(eps_proj_px, focal_px) -> np.ndarray:
    """eps_ang (arc-min) = eps_proj (px) x angular resolution; both (n,) or scalars."""
    return np.asarray(eps_proj_px, dtype=float) * angular_resolution_arcmin(focal_px)


def mean_focal_px(rig: Rig, cameras: Sequence[str]) -> float:
    """Mean of (fx + fy) / 2 over the named cameras of `rig`."""
    return float(np.mean([(rig.cameras[c].fx + rig.cameras[c].fy) / 2.0 for c in cameras]))


def true_errors(quat_est, center_est, quat_true, center_true) -> tuple[np.ndarray, np.ndarray]:
    """Position error (n,) in metres and attitude error (n,) in arc-min against the truth.

    quat_*: (n, 4) rig_from_world (w, x, y, z); center_*: (n, 3) rig centres in the world. The
    attitude error is the angle of R_est R_true^T.
    """
    position = np.linalg.norm(np.asarray(center_est, float) - np.asarray(center_true, float), axis=1)
    R_est = rotation_from_quat(np.asarray(quat_est, float).reshape(-1, 4))
    R_true = rotation_from_quat(np.asarray(quat_true, float).reshape(-1, 4))
    return position, rotation_error(R_est, R_true) * ARCMIN_PER_RAD


def subset_cameras(label: str, rig: Rig) -> list[str]:
    """Camera names of a subset label (digits = indexes in rig order): '012' -> ['C0', 'C1', 'C2']."""
    names = rig.camera_names
    bad = [d for d in label if int(d) >= len(names)]
    if not label or bad:
        raise ValueError(f"subset label {label!r}: the rig has cameras 0..{len(names) - 1} ({', '.join(names)})")
    return [names[int(d)] for d in label]


# ------------------------------------------------------------------------------ tables


def pose_methods_table(evaluation: pd.DataFrame) -> pd.DataFrame:
    """tab:pose_methods: one row per group and one for all frames (group 'all').

    evaluation: the columns of evaluation.csv. Columns: group, n_frames, eps_pos_mean_m,
    eps_pos_std_m [, eps_pos_group_mean_m, eps_pos_group_std_m], eps_ang_mean_arcmin, eps_ang_std_arcmin, eps_proj_mean_px, eps_proj_std_px,
    time_mean_ms [, true_pos_err_mean_m, true_pos_err_median_m, true_ang_err_mean_arcmin,
    true_ang_err_median_arcmin [, crb_pos_median_m, crb_ang_median_arcmin]]. Standard deviations
    are sample ones (ddof = 1).
    """
    rows = [_pose_methods_row(g, rows) for g, rows in _groups_and_all(evaluation)]
    return pd.DataFrame(rows)


def _pose_methods_row(group: str, rows: pd.DataFrame) -> dict:
    row = {"group": group, "n_frames": len(rows)}
    for name, column, unit in (("eps_pos", "eps_pos_m", "m"), ("eps_pos_group", "eps_pos_group_m", "m"),
                               ("eps_ang", "eps_ang_arcmin", "arcmin"), ("eps_proj", "eps_proj_px", "px")):
        if column not in rows:
            continue
        row[f"{name}_mean_{unit}"] = rows[column].mean()
        row[f"{name}_std_{unit}"] = rows[column].std(ddof=1)
    row["time_mean_ms"] = rows["time_ms"].mean()
    if TRUE_ERROR_COLUMNS[0] in rows:
        row.update(true_pos_err_mean_m=rows["true_pos_err_m"].mean(),
                   true_pos_err_median_m=rows["true_pos_err_m"].median(),
                   true_ang_err_mean_arcmin=rows["true_ang_err_arcmin"].mean(),
                   true_ang_err_median_arcmin=rows["true_ang_err_arcmin"].median())
    if "crb_pos_m" in rows:
        row.update(crb_pos_median_m=rows["crb_pos_m"].median(), crb_ang_median_arcmin=rows["crb_ang_arcmin"].median())
    return row


def conf_table(evaluations: dict[str, pd.DataFrame], rig: Rig) -> pd.DataFrame:
    """tab:conf in long form: one row per group (and 'all') and subset label.

    evaluations: label -> evaluation table of poses_<label>.csv. Columns: group, subset, cameras
    (names joined by '+'), n_frames, eps_pos_mean_m [, eps_pos_group_mean_m], eps_ang_mean_arcmin, eps_proj_mean_px,
    eps_proj_used_mean_px [, true_pos_err_mean_m, true_ang_err_mean_arcmin]. eps_proj and eps_ang
    are over every camera's observations where the table has eps_proj_all_px (run_evaluate adds
    it, see every_camera_eps_proj), eps_proj_used over the subset's own cameras.
    """
    rows = []
    labels = sorted(evaluations, key=lambda label: (len(label), label))
    for label in labels:
        for group, part in _groups_and_all(evaluations[label]):
            every = "eps_proj_all_px" in part  # over every camera's observations, as tab:conf
            row = {"group": group, "subset": label, "cameras": "+".join(subset_cameras(label, rig)),
                   "n_frames": len(part), "eps_pos_mean_m": part["eps_pos_m"].mean(),
                   **({"eps_pos_group_mean_m": part["eps_pos_group_m"].mean()} if "eps_pos_group_m" in part else {}),
                   "eps_ang_mean_arcmin": part["eps_ang_all_arcmin" if every else "eps_ang_arcmin"].mean(),
                   "eps_proj_mean_px": part["eps_proj_all_px" if every else "eps_proj_px"].mean(),
                   "eps_proj_used_mean_px": part["eps_proj_px"].mean()}
            if TRUE_ERROR_COLUMNS[0] in part:
                row.update(true_pos_err_mean_m=part["true_pos_err_m"].mean(),
                           true_ang_err_mean_arcmin=part["true_ang_err_arcmin"].mean())
            rows.append(row)
    table = pd.DataFrame(rows)
    order = {g: k for k, g in enumerate(_ordered(table["group"].unique()))}
    return table.sort_values(["group", "subset"], key=lambda s: s.map(order) if s.name == "group" else
                             s.map({label: k for k, label in enumerate(labels)}), kind="stable").reset_index(drop=True)


def error_budget_table(evaluations: dict[str, pd.DataFrame], budgets: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """The error budget of each camera set (label, as conf_table's) with a budget (<poses>.budget.csv).

    One row per component of the error model (pose/error_model.py): its sigma (median over the
    frames' groups, in its unit) and source (the most frequent), and its share of the predicted
    variance of the position (x + y + z) and of the attitude (heading + pitch + roll) over the
    set's frames (%); then a row `total`: the RMS over the frames of the predicted 3-D sigma of the
    position (m) and attitude (arc-min), beside the RMS of the error they describe, the simulator's
    true error where there is one (error_measure 'truth'), else eps_pos and eps_ang ('eps_pos').
    """
    rows = []
    for label in sorted(budgets, key=lambda label: (len(label), label)):
        budget, evaluation = budgets[label], evaluations.get(label)
        if budget is None or not len(budget):
            continue
        position = budget[["var_x_m2", "var_y_m2", "var_z_m2"]].sum(axis=1)
        attitude = budget[["var_heading_arcmin2", "var_pitch_arcmin2", "var_roll_arcmin2"]].sum(axis=1)
        parts = budget.assign(position=position, attitude=attitude).groupby("component", sort=False)
        totals = {name: values.groupby(budget["frame"]).sum()
                  for name, values in (("position", position), ("attitude", attitude))}
        for component, part in parts:
            rows.append({"subset": label, "component": component, "sigma": part["sigma"].median(),
                         "unit": part["unit"].iloc[0], "source": part["source"].mode().iloc[0],
                         "position_share_pct": 100 * part["position"].sum() / max(totals["position"].sum(), 1e-300),
                         "attitude_share_pct": 100 * part["attitude"].sum() / max(totals["attitude"].sum(), 1e-300)})
        total = {"subset": label, "component": "total",
                 "rms_sigma_position_m": float(np.sqrt(totals["position"].mean())),
                 "rms_sigma_attitude_arcmin": float(np.sqrt(totals["attitude"].mean()))}
        if evaluation is not None and len(evaluation):
            truth = TRUE_ERROR_COLUMNS[0] in evaluation
            columns = TRUE_ERROR_COLUMNS if truth else ("eps_pos_m", "eps_ang_arcmin")
            total.update(rms_error_position_m=float(np.sqrt(np.mean(evaluation[columns[0]] ** 2))),
                         rms_error_attitude_arcmin=float(np.sqrt(np.mean(evaluation[columns[1]] ** 2))),
                         error_measure="truth" if truth else "eps_pos")
        rows.append(total)
    return pd.DataFrame(rows)


def _groups_and_all(evaluation: pd.DataFrame):
    """(group, rows) per group in natural order, then ('all', every row)."""
    groups = _ordered(evaluation["group"].astype(str).unique())
    for group in groups:
        yield group, evaluation[evaluation["group"].astype(str) == group]
    yield ALL_GROUPS, evaluation


def _ordered(groups) -> list[str]:
    """Group labels in natural order: numbers numerically, then text; 'all' last."""
    def key(g: str):
        return (g == ALL_GROUPS, not g.isdigit(), int(g) if g.isdigit() else 0, g)
    return sorted((str(g) for g in groups), key=key)


# ------------------------------------------------------------------------------ evaluation


def evaluate_poses(poses: pd.DataFrame, dataset: Dataset, rig: Rig, truth: pd.DataFrame | None = None,
                   offsets: dict[str, np.ndarray] | None = None, observations: pd.DataFrame | None = None,
                   lever_arm: LeverArm | None = None) -> pd.DataFrame:
    """poses (Workspace.load_poses) + eps_pos_m, eps_pos_group_m, eps_ang_arcmin [+ true_pos_err_m,
    true_ang_err_arcmin [+ crb_pos_m, crb_ang_arcmin]].

    lever_arm: the POS lever arm (fit_pos_lever_arm) for eps_pos_m; default the one of `poses`.
    offsets: mean offsets per group (group_offsets) for eps_pos_group_m; default those of `poses`.
    truth: Workspace.load_truth_frames(); frames it lacks raise ResultsError.
    observations: those the poses used (`used_observations`); with truth, adds the Cramer-Rao bound.
    """
    pos = pos_positions(poses, dataset)
    centers = poses[list(CENTER)].to_numpy(dtype=float)
    focal = np.array([mean_focal_px(rig, c.split("+")) for c in poses["cameras"]])
    lever_arm = lever_arm if lever_arm is not None else fit_pos_lever_arm(poses, dataset)
    out = poses.copy()
    out["eps_pos_m"] = lever_arm.position_errors(centers, pos, world_from_rig_rotations(poses))
    out["eps_pos_group_m"] = position_errors(centers, pos, poses["group"], offsets)
    out["eps_ang_arcmin"] = angular_errors(poses["eps_proj_px"], focal)
    if truth is not None:
        missing = sorted(set(poses["frame"]) - set(truth.index))
        if missing:
            raise ResultsError(dataset.truth_dir / "frames.csv", f"has no row for frame(s) {', '.join(missing[:5])}")
        rows = truth.loc[poses["frame"]]
        out["true_pos_err_m"], out["true_ang_err_arcmin"] = true_errors(
            poses[list(QUAT)], centers, rows[list(QUAT)], rows[list(CENTER)])
        if observations is not None:
            out["crb_pos_m"], out["crb_ang_arcmin"] = cramer_rao_errors(dataset, rig, poses, rows, observations)
    _warn_single_frame_groups(poses)
    return out


def cramer_rao_errors(dataset: Dataset, rig: Rig, poses: pd.DataFrame, truth_rows: pd.DataFrame,
                      observations: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of `poses`: the Cramer-Rao bound (RMS position error in m, attitude in arc-min) at the
    true pose (truth_rows, aligned with poses) for the frame's observations of the cameras it used.

    The noise is the frame's own: independent Gaussian pixel errors whose RMS distance is eps_proj,
    i.e. eps_proj / sqrt(2) px per coordinate, as an angle through the cameras' mean focal length.
    The simulator's flight errors are not all of that kind (survey and in-flight mounting errors are
    shared by many rays), so the bound is what pixel noise alone would allow.
    """
    by_frame = {frame.frame: frame for frame in frame_observations(dataset, rig, observations)}
    bounds = np.full((len(poses), 2), np.nan)
    for k, (pose, true) in enumerate(zip(poses.itertuples(index=False), truth_rows.itertuples(index=False))):
        cameras = pose.cameras.split("+")
        frame = by_frame.get(pose.frame)
        mine = np.isin(frame.cameras, cameras) if frame is not None else None
        if frame is None or mine.sum() < 3 or not pose.eps_proj_px > 0:
            continue
        R = rotation_from_quat([true.qw, true.qx, true.qy, true.qz])
        sigma = pose.eps_proj_px / np.sqrt(2.0) / mean_focal_px(rig, cameras)
        position, attitude = cramer_rao_bound(frame.origins[mine], frame.directions[mine], frame.points[mine], R,
                                              np.array([true.tx, true.ty, true.tz]), sigma)
        bounds[k] = position, attitude * ARCMIN_PER_RAD
    return bounds[:, 0], bounds[:, 1]


def _warn_single_frame_groups(poses: pd.DataFrame) -> None:
    counts = poses["group"].value_counts()
    single = sorted(counts[counts < 2].index)
    if single:
        log.warning("group(s) %s have one frame: their mean offset is that frame's, so eps_pos_group = 0",
                    ", ".join(single))


def used_observations(observations: pd.DataFrame, *pose_observations: pd.DataFrame | None) -> pd.DataFrame:
    """`observations` without those a pose solve rejected (`used` false in any of the poses files'
    per-observation tables, e.g. RANSAC's outliers with --robust): the errors and the Cramer-Rao
    bound of a frame are about the observations its pose stands on."""
    rejected = [table.loc[~table["used"], ["image", "point_id"]] for table in pose_observations if table is not None]
    if not rejected:
        return observations
    rejected = pd.concat(rejected)
    key = pd.MultiIndex.from_frame(observations[["image", "point_id"]])
    return observations[~key.isin(pd.MultiIndex.from_frame(rejected))]


# ------------------------------------------------------------------------------ residuals


def reprojection_residuals(dataset: Dataset, rig: Rig, poses: pd.DataFrame, observations: pd.DataFrame,
                           every_camera: bool = False) -> pd.DataFrame:
    """Flight residuals observed - projected (px) of the frames in `poses`, of the cameras the pose
    used (every camera of the rig with `every_camera`).

    poses: as Workspace.load_poses (frame, cameras, qw..qz, tx..tz); observations: image, camera,
    point_id, u, v (Workspace.load_observations). Returns one row per observation: frame, camera, image, point_id,
    u, v, du, dv (NaN where the point does not project into the camera).
    """
    by_frame = {frame.frame: frame for frame in frame_observations(dataset, rig, observations)}
    parts = []
    for pose in poses.itertuples(index=False):
        frame = by_frame.get(pose.frame)
        if frame is None:
            continue
        rig_from_world = rig_from_world_of(pose)
        for camera in (rig.camera_names if every_camera else pose.cameras.split("+")):
            mine = frame.cameras == camera
            if not mine.any():
                continue
            projected = rig.project(camera, rig_from_world, frame.points[mine])
            parts.append(pd.DataFrame({"frame": frame.frame, "camera": camera, "image": frame.images[mine],
                                       "point_id": frame.point_ids[mine], "u": frame.uv[mine, 0],
                                       "v": frame.uv[mine, 1], "du": frame.uv[mine, 0] - projected[:, 0],
                                       "dv": frame.uv[mine, 1] - projected[:, 1]}))
    columns = ["frame", "camera", "image", "point_id", "u", "v", "du", "dv"]
    if not parts:
        return pd.DataFrame({c: pd.Series([], dtype=float if c in ("u", "v", "du", "dv") else object)
                             for c in columns})
    return pd.concat(parts, ignore_index=True)[columns]


def every_camera_eps_proj(dataset: Dataset, rig: Rig, poses: pd.DataFrame, observations: pd.DataFrame
                          ) -> np.ndarray:
    """Per frame of `poses` (n,): RMS reprojection distance (px) over the observations of every camera
    of the rig, also those the pose was not estimated from (NaN without observations).

    tab:conf's eps_proj of a camera subset reads this way: #0 reaches 57 px where one camera's own
    points are fitted to a few pixels, and its eps_ang (4.5') is the attitude error that shows.
    """
    residuals = reprojection_residuals(dataset, rig, poses, observations, every_camera=True)
    squared = (residuals["du"] ** 2 + residuals["dv"] ** 2).groupby(residuals["frame"]).mean()
    return np.sqrt(squared.reindex(poses["frame"]).to_numpy(dtype=float))


def residual_table(residuals: pd.DataFrame, cameras: list[str]) -> pd.DataFrame:
    """Per camera of `cameras`: observations, RMS / median / max distance (px), mean du, dv (px).

    residuals: rows with camera, du, dv (a poses file's per-observation table)."""
    rows = []
    for camera in cameras:
        r = residuals[residuals["camera"] == camera]
        d = np.hypot(r["du"], r["dv"])
        rows.append({"camera": camera, "observations": len(r), "rms_px": float(np.sqrt(np.mean(d**2))),
                     "median_px": float(np.median(d)), "max_px": float(d.max()),
                     "mean_du_px": float(r["du"].mean()), "mean_dv_px": float(r["dv"].mean())})
    return pd.DataFrame(rows, columns=["camera", "observations", "rms_px", "median_px", "max_px", "mean_du_px",
                                       "mean_dv_px"])
