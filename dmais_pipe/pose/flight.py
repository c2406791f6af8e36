"""Every flight frame through the generalized solver: the pose stage's algorithm (`stages.pose` writes).

`estimate_poses` walks the frames (`frames.frame_observations`) and returns the poses table, with
the columns of docs/design.md

    frame, group, cameras, n_points, qw, qx, qy, qz, tx, ty, tz, x, y, z, eps_proj_px, time_ms, certified

(rig_from_world, rig centre x, y, z in the world, eps_proj_px the RMS reprojection distance over the
observations used, time_ms the wall time of the solve alone, certified the solver's certificate of
global optimality), and one row per observation of the solved frames with whether the pose used it
and its residual. Frames with fewer than 3 usable observations, that the solver rejects, or whose
pose puts an observed point behind its camera, are left out with a warning naming them.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pandas as pd

from ..dataset import Dataset
from ..frames import FrameObservations, frame_observations
from ..geometry import Rigid3, quat_from_rotation
from ..rig import Rig
from ..errors import PoseError
from ..workspace import POSE_COLUMNS, POSE_OBSERVATION_COLUMNS
from .robust import solve_robust
from .solver import solve_generalized_pose

log = logging.getLogger(__name__)

#: poses.csv: the columns of every poses file, then `certified` (the solver's Lagrangian dual
#: certificate of global optimality, `GeneralizedPose.certified`; with --robust, the final solve's).
COLUMNS = [*POSE_COLUMNS, "certified"]
#: RANSAC threshold of --robust, in pixels (an angle per observation: this over its camera's fx).
ROBUST_THRESHOLD_PX = 20.0


def pixel_residuals(rig: Rig, pose: Rigid3, cameras: np.ndarray, uv: np.ndarray,
                           points: np.ndarray) -> np.ndarray:
    """(n, 2) observed pixels uv (n, 2) minus the projections of points (n, 3) in `cameras` (n,)."""
    residuals = np.empty_like(uv, dtype=float)
    for name in np.unique(cameras):
        mask = cameras == name
        residuals[mask] = uv[mask] - rig.project(str(name), pose, points[mask])
    return residuals


def solve_frame(rig: Rig, frame: FrameObservations, robust: bool, refine: bool,
                threshold_px: float = ROBUST_THRESHOLD_PX):
    """Pose of one frame from its observations' generalized rays.

    Returns (Rigid3 rig_from_world, solve time in ms, mask (n,) of the observations used, certified).
    """
    origins, directions, points = frame.origins, frame.directions, frame.points
    start = time.perf_counter()
    if robust:
        focal = np.array([rig.cameras[str(c)].fx for c in frame.cameras])
        result = solve_robust(origins, directions, points, threshold_px / focal, refine=refine)
        R, t, used = result.R, result.t, result.inliers
        certified = bool(getattr(result.final, "certified", False))
    else:
        result = solve_generalized_pose(origins, directions, points, refine=refine)
        R, t, used = result.R, result.t, np.ones(len(points), dtype=bool)
        certified = result.certified
    elapsed = (time.perf_counter() - start) * 1e3
    return Rigid3(R, t), elapsed, used, certified


def _frame_row(frame: str, group: str, cameras_used: list[str], pose: Rigid3, n: int, eps: float, ms: float,
               certified: bool) -> dict:
    q = quat_from_rotation(pose.R)
    centre = pose.center
    return {"frame": frame, "group": group, "cameras": "+".join(cameras_used), "n_points": n,
            "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3], "tx": pose.t[0], "ty": pose.t[1], "tz": pose.t[2],
            "x": centre[0], "y": centre[1], "z": centre[2], "eps_proj_px": eps, "time_ms": ms,
            "certified": certified}


def estimate_poses(dataset: Dataset, rig: Rig, observations: pd.DataFrame, cameras: list[str],
                   robust: bool = False, refine: bool = False, groups: list[str] | None = None,
                   threshold_px: float = ROBUST_THRESHOLD_PX) -> tuple[pd.DataFrame, pd.DataFrame]:
    """poses.csv rows (COLUMNS) for every flight frame (of `groups`, if given), and one row per
    observation of the solved frames (POSE_OBSERVATION_COLUMNS: whether the pose used it, with
    robust RANSAC's inliers at threshold_px, and its residual du, dv in px)."""
    rows, per_observation, skipped = [], [], []
    warm = False
    for frame in frame_observations(dataset, rig, observations, cameras, groups):
        try:
            if not warm:  # one untimed solve loads the template: time_ms is the solve alone
                solve_frame(rig, frame, robust, refine, threshold_px)
                warm = True
            pose, ms, used, certified = solve_frame(rig, frame, robust, refine, threshold_px)
        except PoseError as error:
            skipped.append(f"{frame.frame} ({error})")
            continue
        residuals = pixel_residuals(rig, pose, frame.cameras, frame.uv, frame.points)
        if not np.isfinite(residuals[used]).all():
            skipped.append(f"{frame.frame} (the pose puts observed points behind their camera)")
            continue
        eps = float(np.sqrt(np.mean(np.sum(residuals[used] ** 2, axis=1))))
        used_cameras = [c for c in cameras if c in set(frame.cameras[used])]
        rows.append(_frame_row(frame.frame, frame.group, used_cameras, pose, int(used.sum()), eps, ms, certified))
        per_observation.append(pd.DataFrame({
            "frame": frame.frame, "image": frame.images, "camera": frame.cameras, "point_id": frame.point_ids,
            "u": frame.uv[:, 0], "v": frame.uv[:, 1], "used": used, "du": residuals[:, 0], "dv": residuals[:, 1]}))
    if skipped:
        log.warning("pose: %d frame(s) skipped: %s", len(skipped), "; ".join(skipped))
    observation_rows = (pd.concat(per_observation, ignore_index=True) if per_observation
                        else pd.DataFrame(columns=list(POSE_OBSERVATION_COLUMNS)))
    return pd.DataFrame(rows, columns=COLUMNS), observation_rows[list(POSE_OBSERVATION_COLUMNS)]
