"""`dmais pose DATASET --out RESULTS`: every flight frame through the generalized solver.

Reads RESULTS/rig.json (extrinsics stage), the identified observations (RESULTS/observations.csv or
the dataset's) and the ground points; writes RESULTS/poses.csv (all cameras) or
RESULTS/poses_<label>.csv for a camera subset, label = the digits of the cameras' positions in the
rig (e.g. 012), with the columns of docs/design.md

    frame, group, cameras, n_points, qw, qx, qy, qz, tx, ty, tz, x, y, z, eps_proj_px, time_ms, certified

(rig_from_world, rig centre x, y, z in the world, eps_proj_px the RMS reprojection distance over the
observations used, time_ms the wall time of the solve alone, certified the solver's certificate of
global optimality) and beside it <poses>.observations.csv, one row per observation of the solved
frames with whether the pose used it and its residual. Frames with fewer than 3 usable
observations, or that the solver rejects, are left out with a warning naming them. A per-group
job (`groups`) with no solvable frame writes an empty part with a warning, so that one group seen
badly by a camera subset does not stop the workflow; the merge fails only when every part is empty.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ..blas import single_threaded_blas
from ..dataset import Dataset
from ..errors import DmaisError
from ..frames import FrameObservations, frame_observations
from ..geometry import Rigid3, quat_from_rotation
from ..rig import Rig
from ..workspace import POSE_COLUMNS, POSE_OBSERVATION_COLUMNS, Workspace, pose_observations_path
from ..errors import PoseError
from .robust import solve_robust
from .solver import solve_generalized_pose

log = logging.getLogger(__name__)

#: poses.csv: the columns of every poses file, then `certified` (the solver's Lagrangian dual
#: certificate of global optimality, `GeneralizedPose.certified`; with --robust, the final solve's).
COLUMNS = [*POSE_COLUMNS, "certified"]
#: RANSAC threshold of --robust, in pixels (an angle per observation: this over its camera's fx).
ROBUST_THRESHOLD_PX = 20.0


def subset_label(rig: Rig, cameras: list[str]) -> str:
    """Digits of the cameras' positions in the rig, e.g. ['C0', 'C2'] -> '02'."""
    names = rig.camera_names
    return "".join(str(names.index(c)) for c in sorted(cameras, key=names.index))


def poses_path(workspace: Workspace, rig: Rig, cameras: list[str]) -> Path:
    """RESULTS/poses.csv for all cameras, RESULTS/poses_<label>.csv for a subset."""
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


def pixel_residuals(rig: Rig, pose: Rigid3, cameras: np.ndarray, uv: np.ndarray,
                           points: np.ndarray) -> np.ndarray:
    """(n, 2) observed pixels uv (n, 2) minus the projections of points (n, 3) in `cameras` (n,)."""
    residuals = np.empty_like(uv, dtype=float)
    for name in np.unique(cameras):
        mask = cameras == name
        residuals[mask] = uv[mask] - rig.project(str(name), pose, points[mask])
    return residuals


def solve_frame(rig: Rig, frame: FrameObservations, robust: bool, refine: bool):
    """Pose of one frame from its observations' generalized rays.

    Returns (Rigid3 rig_from_world, solve time in ms, mask (n,) of the observations used, certified).
    """
    origins, directions, points = frame.origins, frame.directions, frame.points
    start = time.perf_counter()
    if robust:
        focal = np.array([rig.cameras[str(c)].fx for c in frame.cameras])
        result = solve_robust(origins, directions, points, ROBUST_THRESHOLD_PX / focal, refine=refine)
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
                   robust: bool = False, refine: bool = False, groups: list[str] | None = None
                   ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """poses.csv rows (COLUMNS) for every flight frame (of `groups`, if given), and one row per
    observation of the solved frames (POSE_OBSERVATION_COLUMNS: whether the pose used it, with
    --robust RANSAC's inliers, and its residual du, dv in px)."""
    rows, per_observation, skipped = [], [], []
    warm = False
    for frame in frame_observations(dataset, rig, observations, cameras, groups):
        try:
            if not warm:  # one untimed solve loads the template: time_ms is the solve alone
                solve_frame(rig, frame, robust, refine)
                warm = True
            pose, ms, used, certified = solve_frame(rig, frame, robust, refine)
        except PoseError as error:
            skipped.append(f"{frame.frame} ({error})")
            continue
        residuals = pixel_residuals(rig, pose, frame.cameras, frame.uv, frame.points)
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


def run_pose(dataset_dir, results_dir, cameras: list[str] | None = None, robust: bool = False,
             refine: bool = False, groups: list[str] | None = None, out: Path | None = None) -> Path:
    """Estimate every flight frame's pose; write poses.csv (or poses_<label>.csv) and its
    per-observation file beside it (`workspace.pose_observations_path`). Returns the poses path."""
    workspace = Workspace.open(dataset_dir, results_dir)
    rig = workspace.load_rig()
    chosen = _cameras(rig, cameras)
    with single_threaded_blas():  # small matrices: threads only add hand-offs to time_ms
        table, per_observation = estimate_poses(workspace.dataset, rig, workspace.load_observations(), chosen,
                                                robust, refine, groups)
    if table.empty and not groups:
        raise DmaisError(f"pose: no flight frame of {dataset_dir} could be solved with cameras {chosen}")
    if table.empty:
        log.warning("pose: no flight frame of group(s) %s could be solved with cameras %s", groups, chosen)
    path = out or poses_path(workspace, rig, chosen)
    workspace.save_poses(table, per_observation, path)
    if len(table):
        log.info("pose: %d frames -> %s (median %.2f ms per solve)", len(table), path, table["time_ms"].median())
    return path


def merge_poses(dataset_dir, results_dir, parts: list[Path], cameras: list[str] | None = None,
                out: Path | None = None) -> Path:
    """Concatenate per-group pose files (the workflow's jobs, `run_pose(groups=[g], out=part)`) of
    one camera set, with their per-observation files, into poses.csv or poses_<label>.csv. Returns the path."""
    workspace = Workspace.open(dataset_dir, results_dir)
    rig = workspace.load_rig()
    tables, observations = [], []
    for part in parts:
        table = pd.read_csv(part, dtype={"frame": str, "group": str, "cameras": str})
        if list(table.columns) != COLUMNS:
            raise DmaisError(f"{part}: columns {list(table.columns)}, expected {COLUMNS}")
        tables.append(table)
        observations.append(_part_observations(part))
    if not tables:
        raise DmaisError("pose: no per-group pose file to merge")
    merged = pd.concat(tables, ignore_index=True)
    if merged.empty:
        raise DmaisError(f"pose: none of the {len(parts)} per-group pose files has a solved frame")
    repeated = merged["frame"][merged["frame"].duplicated()]
    if len(repeated):
        raise DmaisError(f"pose: frame {repeated.iloc[0]!r} appears in more than one of {[str(p) for p in parts]}")
    unknown = sorted(set(merged["frame"]) - set(workspace.dataset.frames["frame"].astype(str)))
    if unknown:
        raise DmaisError(f"pose: frame(s) {unknown[:5]} of the pose files are not in {dataset_dir}/frames.csv")
    path = out or poses_path(workspace, rig, _cameras(rig, cameras))
    workspace.save_poses(merged.sort_values("frame", kind="stable"),
                         pd.concat(observations, ignore_index=True).sort_values("frame", kind="stable"), path)
    return path


def _part_observations(part: Path) -> pd.DataFrame:
    path = pose_observations_path(part)
    if not path.is_file():
        raise DmaisError(f"{path}: missing; the per-group pose job writes it beside {part}")
    return pd.read_csv(path, dtype={c: str for c in ("frame", "image", "camera", "point_id")}, keep_default_na=False)
