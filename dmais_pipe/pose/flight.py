"""Every flight frame through the generalized solver: the pose stage's algorithm (`stages.pose` writes).

`estimate_poses` solves the frames (`frames.flight_observations_by_frame`) and returns the poses
table, with the columns of docs/design.md

    frame, group, cameras, n_points, qw, qx, qy, qz, tx, ty, tz, x, y, z, eps_proj_px, time_ms, certified,
    heading_deg, pitch_deg, roll_deg, sigma_x_m, sigma_y_m, sigma_z_m,
    sigma_heading_arcmin, sigma_pitch_arcmin, sigma_roll_arcmin, noise_px, <frames.csv extras>

(rig_from_world, rig centre x, y, z in the world, eps_proj_px the RMS reprojection distance over the
observations used, time_ms the wall time of the solve alone, certified the solver's certificate of
global optimality, the attitude and the 1-sigma uncertainties of `uncertainty.py` under each
group's error model (`error_model.py`, `solve_flight`), then the extra
columns of frames.csv as they are), and one row per observation of the solved frames with whether
the pose used it and its residual. Frames with fewer than 3 usable observations, that the solver
rejects, or whose pose puts an observed point behind its camera, are left out with a warning
naming them.

Frames past the linearisation (nonlinear.py: one narrow camera alone) get their sigmas from
re-solving drawn errors.

Only the solves run frame by frame; rays, residuals and statistics are computed for all frames at
once, the error model and the covariances group by group (on at most 64 frames for the model), so
that the stage runs at nearly the solver's speed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..blas import single_threaded_blas
from ..dataset import FRAME_COLUMNS, PRIOR_QUAT, Dataset, point_sigma
from ..errors import PoseError
from ..frames import FlightObservations, flight_observations_by_frame
from ..geometry import Rigid3, quat_from_rotation
from ..rig import Rig
from ..workspace import POSE_BUDGET_COLUMNS, POSE_COLUMNS, POSE_OBSERVATION_COLUMNS, POSE_UNCERTAINTY_COLUMNS
from ._error import frame_points
from .error_model import UNITS, ErrorModel, Geometry, estimate, estimation_frames, linearised_solve
from .nonlinear import DRAWS, NONLINEAR_INDEX, bootstrap_variances, curvature_index, observation_noise
from .robust import solve_robust
from .solver import solve_generalized_pose
from .uncertainty import PoseUncertainty, concatenated, pose_uncertainty

log = logging.getLogger(__name__)

#: poses.csv: the columns of every poses file, then `certified` (the solver's Lagrangian dual
#: certificate of global optimality, `GeneralizedPose.certified`; with --robust, the final solve's),
#: then the attitude and uncertainty columns; a dataset's extra frames.csv columns follow them.
COLUMNS = [*POSE_COLUMNS, "certified", *POSE_UNCERTAINTY_COLUMNS]
#: RANSAC threshold of --robust, in pixels (an angle per observation: this over its camera's fx).
ROBUST_THRESHOLD_PX = 20.0
#: Observations whose frames' sigmas are computed together (`_linearised_uncertainty`): the error model's
#: temporaries take ~3 KB per observation, 0.15 GB here, where a 10,000-frame line group's 1.35 M took 3.7 GB.
UNCERTAINTY_OBSERVATIONS = 50_000


def pixel_residuals(rig: Rig, pose: Rigid3, cameras: np.ndarray, uv: np.ndarray,
                    points: np.ndarray) -> np.ndarray:
    """(n, 2) observed pixels uv (n, 2) minus the projections of points (n, 3) in `cameras` (n,)."""
    return rows_pixel_residuals(rig, pose.R, pose.t, cameras, uv, points)


def rows_pixel_residuals(rig: Rig, R: np.ndarray, t: np.ndarray, cameras: np.ndarray, uv: np.ndarray,
                         points: np.ndarray) -> np.ndarray:
    """(n, 2) observed pixels uv (n, 2) minus the projections of points (n, 3) in `cameras` (n,), for
    one rig_from_world (R (3, 3), t (3,)) or one per row (R (n, 3, 3), t (n, 3)); NaN where a point is
    not imaged."""
    x_rig = np.einsum("...ij,...j->...i", R, points) + t
    residuals = np.empty_like(uv, dtype=float)
    for name in pd.unique(cameras):
        mask = cameras == name
        residuals[mask] = uv[mask] - rig.project_rig_points(str(name), x_rig[mask])
    return residuals


def solve_frame(origins: np.ndarray, directions: np.ndarray, points: np.ndarray, focal_px: np.ndarray,
                robust: bool, refine: bool, threshold_px: float = ROBUST_THRESHOLD_PX):
    """Pose of one frame from its observations' generalized rays (n, 3) and points (n, 3);
    focal_px (n,) the cameras' fx (for robust's per-observation threshold).

    Returns (R (3, 3), t (3,)) rig_from_world, solve time in ms, mask (n,) of the observations used,
    certified.
    """
    start = time.perf_counter()
    if robust:
        result = solve_robust(origins, directions, points, threshold_px / focal_px, refine=refine)
        R, t, used = result.R, result.t, result.inliers
        certified = bool(getattr(result.final, "certified", False))
    else:
        result = solve_generalized_pose(origins, directions, points, refine=refine)
        R, t, used = result.R, result.t, True
        certified = result.certified
    elapsed = (time.perf_counter() - start) * 1e3
    return R, t, elapsed, used, certified


@dataclass(frozen=True)
class FlightPoses:
    """`solve_flight`'s result: the poses table, the per-observation table, the error model behind
    the sigma columns of each group, and each component's variances per frame (`budget_table`);
    covariance (F, 6, 6) per row of the table, the linearised covariance of (rotation in the rig
    axes, centre in the world axes) (`uncertainty.PoseUncertainty.pose_covariance`), for the
    sigmas in other axes (geo.ned_sigmas)."""

    table: pd.DataFrame
    observations: pd.DataFrame
    error_model: dict[str, ErrorModel]
    budget: pd.DataFrame
    covariance: np.ndarray | None = None


def estimate_poses(dataset: Dataset, rig: Rig, observations: pd.DataFrame, cameras: list[str],
                   robust: bool = False, refine: bool = False, groups: list[str] | None = None,
                   threshold_px: float = ROBUST_THRESHOLD_PX, calibrated_noise_px: float = np.nan,
                   error_settings: dict | None = None, calibration_covariance: np.ndarray | None = None,
                   error_priors: dict | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """poses.csv rows (COLUMNS, then frames.csv's extra columns) for every flight frame (of `groups`,
    if given), and one row per observation of the solved frames (POSE_OBSERVATION_COLUMNS: whether
    the pose used it, with robust RANSAC's inliers at threshold_px, and its residual du, dv in px).
    The arguments as `solve_flight`'s.
    """
    result = solve_flight(dataset, rig, observations, cameras, robust, refine, groups, threshold_px,
                          calibrated_noise_px, error_settings, calibration_covariance, error_priors)
    return result.table, result.observations


def solve_flight(dataset: Dataset, rig: Rig, observations: pd.DataFrame, cameras: list[str],
                 robust: bool = False, refine: bool = False, groups: list[str] | None = None,
                 threshold_px: float = ROBUST_THRESHOLD_PX, calibrated_noise_px: float = np.nan,
                 error_settings: dict | None = None, calibration_covariance: np.ndarray | None = None,
                 error_priors: dict | None = None) -> FlightPoses:
    """`estimate_poses`' tables and the error model of its sigmas (error_model.py), one per group.

    Each group's model is estimated from the residuals of its frames solved with every camera of
    the rig: its components belong to the sensor and the flight, and a subset of the cameras (one
    alone above all) lets its solve absorb what would tell them. Per group, because a group's
    frames share its mounting and its ground points, and so that the workflow's per-group jobs
    give the sigmas of one run over all frames. calibrated_noise_px: the pixel noise
    where the frames have too few observations to estimate it; error_settings {component: sigma}
    (error_model.UNITS) fixes components, error_priors {component: sigma} stands in for those the
    residuals cannot tell (error_model.estimate); calibration_covariance the calibration's joint
    covariance (error_model.linearised_solve).
    """
    solution = _solve(dataset, rig, observations, cameras, robust, refine, groups, threshold_px)
    whole = solution if set(cameras) == set(rig.cameras) else \
        _solve(dataset, rig, observations, list(rig.cameras), robust, refine, groups, threshold_px)
    table = solution.table.copy()
    sigmas = np.full((len(table), len(POSE_UNCERTAINTY_COLUMNS)), np.nan)
    models, budgets = {}, []
    covariance = np.full((len(table), 6, 6), np.nan)

    def resolve(origins, directions, points):  # the re-solves of nonlinear.py: this stage's solver, no RANSAC
        return solve_frame(origins, directions, points, None, False, refine)[:2]

    for group in pd.unique(table["group"]):
        frames = np.flatnonzero(table["group"].to_numpy() == group)
        estimated_on = np.flatnonzero(whole.table["group"].to_numpy() == group)
        source, sample = (whole, estimated_on) if len(estimated_on) else (solution, frames)
        sample = sample[estimation_frames(len(sample))]
        models[group] = estimate(_geometry(dataset, rig, source, sample, not refine, calibration_covariance),
                                 error_settings, calibrated_noise_px, priors=error_priors)
        uncertainty, index = _linearised_uncertainty(dataset, rig, solution, frames, models[group], not refine,
                                                     calibration_covariance)
        weak = index > NONLINEAR_INDEX
        if weak.any():  # nonlinear.py: the linearised sigmas do not hold; these frames' solves re-drawn
            with single_threaded_blas():
                drawn = bootstrap_variances(_geometry(dataset, rig, solution, frames[weak], not refine,
                                                      calibration_covariance), models[group], resolve,
                                            np.random.default_rng(0))
            uncertainty = uncertainty.with_totals(np.flatnonzero(weak), *drawn)
            log.info("pose: group %s: the sigmas of %d frame(s) from %d re-solves each (their linearised "
                     "ones do not hold)", group, int(weak.sum()), DRAWS)
        sigmas[frames] = np.column_stack([uncertainty.attitude, uncertainty.sigma_position,
                                          uncertainty.sigma_attitude, uncertainty.noise_px])
        covariance[frames] = uncertainty.pose_covariance
        budgets.append(budget_table(table["frame"].to_numpy()[frames], uncertainty, models[group]))
    table[list(POSE_UNCERTAINTY_COLUMNS)] = sigmas
    budget = pd.concat(budgets, ignore_index=True) if budgets else pd.DataFrame(columns=list(POSE_BUDGET_COLUMNS))
    return FlightPoses(_with_frame_extras(table, dataset), solution.observations, models, budget, covariance)


@dataclass(frozen=True)
class _Solution:
    """The solved frames of one camera set: table (COLUMNS without the uncertainty ones), the
    per-observation table, R (F, 3, 3), t (F, 3), and the used observations' rows of `flight`."""

    table: pd.DataFrame
    observations: pd.DataFrame
    R: np.ndarray
    t: np.ndarray
    flight: FlightObservations
    rows: np.ndarray
    frame_of_row: np.ndarray


def _solve(dataset: Dataset, rig: Rig, observations: pd.DataFrame, cameras: list[str], robust: bool,
           refine: bool, groups: list[str] | None, threshold_px: float) -> _Solution:
    """Every frame (of `groups`) solved with `cameras`; frames that fail are left out with a warning."""
    flight = flight_observations_by_frame(dataset, rig, observations, cameras, groups)
    focal = _per_observation(flight.cameras, {name: rig.cameras[name].fx for name in cameras})
    R, t, ms, used, certified, failures = _solve_frames(flight, focal, robust, refine, threshold_px)
    index = flight.frame_index
    residuals = _frames_pixel_residuals(rig, R, t, index, flight.cameras, flight.uv, flight.points)
    hidden = np.bincount(index, used & ~np.isfinite(residuals).all(axis=1), minlength=len(flight)) > 0
    for k in np.flatnonzero(hidden & ~failures.astype(bool)):
        failures[k] = "the pose puts observed points behind their camera"
    solved = failures == ""
    if (~solved).any():
        log.warning("pose: %d frame(s) skipped: %s", int((~solved).sum()),
                    "; ".join(f"{flight.frames[k]} ({failures[k]})" for k in np.flatnonzero(~solved)))
    rows = solved[index]
    per_observation = pd.DataFrame({
        "frame": _str_column(flight.frames[index[rows]]), "image": _str_column(flight.images[rows]),
        "camera": _str_column(flight.cameras[rows]), "point_id": _str_column_of(flight.point_names, flight.point_index[rows]), "u": flight.uv[rows, 0],
        "v": flight.uv[rows, 1], "used": used[rows],
        "du": residuals[rows, 0], "dv": residuals[rows, 1]}, columns=list(POSE_OBSERVATION_COLUMNS))
    used_rows = used & rows
    frame_of_row = (np.cumsum(solved) - 1)[index[used_rows]]
    table = _poses_table(cameras, flight, solved, R, t, ms, certified, used_rows, frame_of_row, residuals)
    return _Solution(table, per_observation, R[solved], t[solved], flight, used_rows, frame_of_row)


def _frames_pixel_residuals(rig: Rig, R: np.ndarray, t: np.ndarray, frame: np.ndarray, cameras: np.ndarray,
                            uv: np.ndarray, points: np.ndarray) -> np.ndarray:
    """rows_pixel_residuals of each row under its frame's (frame (N,)) rig_from_world R (F, 3, 3), t (F, 3),
    without the rows' copies of the poses (`_error.frame_points`)."""
    x_rig = frame_points(R, t, frame, points)
    residuals = np.empty_like(uv, dtype=float)
    left = np.ones(len(cameras), bool)
    for name in rig.cameras:
        mask = cameras == name
        if mask.any():
            residuals[mask] = uv[mask] - rig.project_rig_points(name, x_rig[mask])
            left &= ~mask
    for name in pd.unique(cameras[left]):  # not the rig's: project_rig_points names it
        mask = cameras == name
        residuals[mask] = uv[mask] - rig.project_rig_points(str(name), x_rig[mask])
    return residuals


def _str_column_of(names: np.ndarray, index: np.ndarray):
    """names[index] (names (k,) numpy str, index (n,)) as the str array pandas makes of it, of one str object per
    name (pandas makes one per row: a line's 1.4 million observations' point ids, 90 MB)."""
    return pd.array(names, dtype="str").take(index)


def _str_column(values: np.ndarray):
    """values (n,) numpy str as the str array pandas makes of them, each run of equal values (a frame's rows, an
    image's) made one str: pandas makes a str object per row."""
    if not len(values):
        return pd.array(values, dtype="str")
    change = np.r_[True, values[1:] != values[:-1]]
    return pd.array(values[change], dtype="str").take(np.cumsum(change) - 1)


def _geometry(dataset: Dataset, rig: Rig, solution: _Solution, frames: np.ndarray, object_space: bool,
              calibration_covariance) -> Geometry:
    """error_model.Geometry of the used observations of a _Solution's frames (ascending rows (k,) of
    its table), numbered 0 ... k - 1."""
    renumber = np.full(len(solution.table), -1)
    renumber[frames] = np.arange(len(frames))
    frame_of_row = renumber[solution.frame_of_row]
    rows = np.flatnonzero(solution.rows)[frame_of_row >= 0]
    flight = solution.flight
    return linearised_solve(rig, flight.cameras[rows], flight.uv[rows], flight.origins[rows],
                            flight.directions[rows], flight.points[rows], frame_of_row[frame_of_row >= 0],
                            solution.R[frames], solution.t[frames], solution.table["group"].to_numpy()[frames],
                            flight.point_ids[rows], object_space,
                            point_sigma(dataset.ground_points, flight.point_ids[rows]), calibration_covariance)


def _linearised_uncertainty(dataset: Dataset, rig: Rig, solution: _Solution, frames: np.ndarray, model: ErrorModel,
                            object_space: bool, calibration_covariance) -> tuple[PoseUncertainty, np.ndarray]:
    """pose_uncertainty of a _Solution's frames (ascending rows (F,) of its table) under `model`, and their
    curvature_index (F,), computed UNCERTAINTY_OBSERVATIONS at a time: every number is a frame's own, and the
    error model's per-observation arrays stay bounded whatever the group's size."""
    counts = np.bincount(solution.frame_of_row, minlength=len(solution.table))[frames]
    block = (np.cumsum(counts) - 1) // UNCERTAINTY_OBSERVATIONS  # (F,) the block of each frame's last observation
    parts, indexes = [], []
    for chunk in np.split(frames, np.flatnonzero(np.diff(block)) + 1):
        geometry = _geometry(dataset, rig, solution, chunk, object_space, calibration_covariance)
        parts.append(pose_uncertainty(geometry, model, solution.R[chunk], solution.t[chunk]))
        indexes.append(curvature_index(geometry, parts[-1].covariance, observation_noise(geometry, model)))
    return concatenated(parts), np.concatenate(indexes)


def _solve_frames(flight: FlightObservations, focal: np.ndarray, robust: bool, refine: bool,
                  threshold_px: float):
    """Every frame's solve: R (F, 3, 3), t (F, 3) (NaN where not solved), time_ms (F,), used (N,),
    certified (F,), failures (F,) str ('' where solved)."""
    n_frames, bounds = len(flight), flight.bounds
    R, t = np.full((n_frames, 3, 3), np.nan), np.full((n_frames, 3), np.nan)
    ms, certified = np.zeros(n_frames), np.zeros(n_frames, bool)
    used = np.zeros(len(flight.uv), bool)
    failures = np.zeros(n_frames, dtype=object)
    failures[:] = ""
    origins, directions, points = flight.origins, flight.directions, flight.points
    warm = False
    with single_threaded_blas():  # small matrices: threads only add hand-offs (20x under load)
        for k in range(n_frames):
            part = slice(bounds[k], bounds[k + 1])
            problem = (origins[part], directions[part], points[part], focal[part], robust, refine, threshold_px)
            try:
                if not warm:  # one untimed solve loads the template: time_ms is the solve alone
                    solve_frame(*problem)
                    warm = True
                R[k], t[k], ms[k], used[part], certified[k] = solve_frame(*problem)
            except PoseError as error:
                failures[k] = str(error)
    return R, t, ms, used, certified, failures


def _poses_table(cameras: list[str], flight: FlightObservations, solved: np.ndarray, R, t, ms, certified,
                 rows: np.ndarray, frame_of_row: np.ndarray, residuals: np.ndarray) -> pd.DataFrame:
    """The COLUMNS of the solved frames but the uncertainty ones, from the per-frame arrays; rows
    (N,) the used observations of solved frames, frame_of_row their row in the table."""
    R, t = R[solved], t[solved]
    n_frames = len(R)
    n_points = np.bincount(frame_of_row, minlength=n_frames)
    squares = np.bincount(frame_of_row, np.sum(residuals[rows] ** 2, axis=1), minlength=n_frames)
    q = quat_from_rotation(R)
    centre = -np.einsum("fji,fj->fi", R, t)
    columns = {"frame": flight.frames[solved], "group": flight.groups[solved],
               "cameras": _cameras_used(cameras, flight.cameras[rows], frame_of_row, n_frames), "n_points": n_points,
               "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
               "tx": t[:, 0], "ty": t[:, 1], "tz": t[:, 2], "x": centre[:, 0], "y": centre[:, 1], "z": centre[:, 2],
               "eps_proj_px": np.sqrt(squares / np.maximum(n_points, 1)), "time_ms": ms[solved],
               "certified": certified[solved]}
    return pd.DataFrame(columns, columns=COLUMNS)


def budget_table(frames: np.ndarray, uncertainty, model: ErrorModel) -> pd.DataFrame:
    """POSE_BUDGET_COLUMNS of frames (F,): per component, the model's sigma and its variances of each
    frame (`uncertainty.PoseUncertainty`)."""
    parts = []
    for name, position in uncertainty.variance_position.items():
        angles = uncertainty.variance_attitude[name]
        parts.append(pd.DataFrame({
            "frame": frames, "component": name, "sigma": model.sigma[name], "unit": UNITS[name],
            "source": model.source[name], **{f"var_{a}_m2": position[:, k] for k, a in enumerate("xyz")},
            **{f"var_{a}_arcmin2": angles[:, k] for k, a in enumerate(("heading", "pitch", "roll"))}}))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=list(POSE_BUDGET_COLUMNS))


def _with_frame_extras(table: pd.DataFrame, dataset: Dataset) -> pd.DataFrame:
    """`table` with the extra columns of frames.csv (as read, text) of its frames appended; an extra
    column named like one of COLUMNS is left out with a warning."""
    frames = dataset.frames
    extras = [c for c in frames.columns if c not in (*FRAME_COLUMNS, *PRIOR_QUAT)]
    clashing = [c for c in extras if c in COLUMNS]
    if clashing:
        log.warning("pose: frames.csv column(s) %s not copied to the poses file: the pose stage writes "
                    "columns of that name", clashing)
    extras = [c for c in extras if c not in COLUMNS]
    if not extras:
        return table
    values = frames.set_index("frame").loc[table["frame"], extras].reset_index(drop=True)
    return pd.concat([table, values], axis=1)


def _per_observation(cameras: np.ndarray, value_of: dict[str, float]) -> np.ndarray:
    """(n,) value_of[camera] of each observation's camera (n,)."""
    out = np.empty(len(cameras))
    for name, value in value_of.items():
        out[cameras == name] = value
    return out


def _cameras_used(cameras: list[str], observed: np.ndarray, frame_of_row: np.ndarray, n_frames: int) -> np.ndarray:
    """(F,) the cameras (in `cameras` order) of each frame's used observations (observed (N,),
    frame_of_row (N,)), joined by '+'."""
    present = np.zeros((n_frames, len(cameras)), bool)
    for c, name in enumerate(cameras):
        present[frame_of_row[observed == name], c] = True
    bits = present @ (1 << np.arange(len(cameras)))
    labels = {b: "+".join(name for c, name in enumerate(cameras) if b >> c & 1) for b in np.unique(bits)}
    return np.array([labels[b] for b in bits], dtype=object)
