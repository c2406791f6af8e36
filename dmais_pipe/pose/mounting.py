"""The rig watched in flight: each camera's in-flight mounting against the calibration, per flight group.

A group rig adjustment (issue 29, item 2): all frames of one flight group (the rig hovering over
one surveyed ground site) are adjusted at once, with the ground points as weighted control and
the calibrated rig as prior; each non-reference camera's rotation change is estimated with its
1-sigma.

Model. Unknowns, for F frames, K non-reference cameras with observations and P ground points:

- per frame f: rig_from_world (R_f, t_f), x_rig = R_f @ M + t_f, started from the per-frame solves
  (pose.flight), moved by a left rotation increment about the frame's points' centroid m_f and a
  translation: R_f <- exp([omega]) R_f, R_f m_f + t_f <- R_f m_f + t_f + dt (6; about the centroid
  rather than the world origin, kilometres away, the normal matrix is well conditioned);
- per camera c: delta_c (3), the rotation vector in the CAMERA frame of its mounting change,
  in-flight cam_from_rig = Rigid3(exp([delta_c]), 0) * calibrated cam_from_rig: the camera turns
  about its centre, whose place in the rig is unchanged (the simulator draws the change so). The
  reference camera's delta is 0 by definition: the rig frame is its frame, so a rotation common
  to all cameras is the platform's attitude;
- per ground point p: its world position M_p, the surveyed coordinates a prior of per-axis sigma;
- per frame f and camera c: a jitter rotation j_fc (3), that frame's cam_from_rig being
  exp([j_fc]) exp([delta_c]) calibrated, prior N(0, sigma_jitter^2) per axis: the vibration,
  which moves all points of one camera in one frame together. Without it the frames would look
  independent and delta's sigma would shrink as 1/sqrt(F) below what the vibration allows;
- a prior N(0, sigma_prior^2) per axis on delta_c (default 30 arc-min), a regulariser only;
- given the calibration's covariance, per camera c (the reference too) its relative focal change
  s_c, fx and fy scaled by 1 + s_c, prior N(0, sigma_s^2) with sigma_s the calibration's sigma of
  (dfx / fx + dfy / fy) / 2: the calibration's focal error, which no rotation takes up (C0's
  +400 ppm is 0.14 m of the rig's height at 350 m), or a change in flight (focus, temperature);
- optionally (not in the issue's model) a prior on the rig centres -R_f^T t_f, e.g. the POS
  positions less the lever arm (`adjust_group_rig`'s center_prior_m): see the bound below.

Observations: the markers' distorted pixels uv with a per-axis pixel sigma (per camera). The cost

    sum_i |(project_c(exp([j_fc]) exp([delta_c]) (C_c (R_f M_p + t_f) + t_c)) - uv_i) / sigma_px|^2
    + sum_p |(M_p - surveyed_p) / sigma_p|^2 + sum_fc |j_fc / sigma_jitter|^2 + sum_c |delta_c / sigma_prior|^2

((C_c, t_c) the calibrated cam_from_rig; project_c with the focal change, and sum_c |s_c /
sigma_s|^2 with it) is minimised by Levenberg-Marquardt; delta and j are
additive rotation vectors (exact Jacobians through geometry.left_jacobian_so3), the problem taken
about its points' mean. Each frame's pose and jitters (6 + 3K unknowns) touch only that frame's
observations, and each point's 3 only its own: pose.group_normal keeps the normal equations in
those blocks and eliminates the frames or the points first, whichever costs less (the frames when
hovering over the same markers, the points where frames see points of their own or along a line),
in time linear in the frames. LM stops where a step is shorter than STEP_TOLERANCE standard
deviations, after taking it.

Covariance: the inverse normal matrix at the minimum; the rig's block of it is the inverse of the
rig's Schur complement (the others marginalised); given the calibration's joint
covariance, plus its share (`_calibration_share`): the calibrated rig is a measurement too, and a
flight that resolves the rig better than the calibration did would flag its error as a change.
sigma: the square roots of its diagonal, in arc-min. chi2_c = delta_c^T cov_c^-1 delta_c;
`significant` where chi2_c exceeds chi2.ppf(1 - SIGNIFICANCE, 3): with no change and honest noise
values, a share SIGNIFICANCE (1%) of the (camera, group) rows is flagged.

Fisher-information bound: the sigma reported with the true noise values is the Cramer-Rao bound
of the geometry. For the simulator's groups (the paper's rig 350 m above ground, 8 markers in each
camera's footprint, 30 frames, 0.5 px, 0.3 arc-min vibration, 2.5 cm survey per axis) it is about
1.7, 2.2 and 3.4 arc-min about the tilted cameras' x, y and z (optical) axes (bench/mounting.py),
nearly proportional to the survey sigma (0.2, 0.3, 0.46 at 3 mm; 0.08, 0.09, 0.14 at 0.1 mm): the
same 8 points are seen in every frame, so their survey errors (2.5 cm at ~500 m: 0.17 arc-min a
point) do not average over frames. Most of it lies in three kinds of direction that the reference
camera's narrow view (5.4 x 4 deg) pins only weakly:

- all tilted cameras turned together about the rig's z axis: the reference camera's roll about
  its optical axis (~6 arc-min along that direction);
- each camera's roll about its own optical axis: a point moves by its ~0.025 rad from the image
  centre times the angle (~2.5 arc-min);
- the cameras' common outward tilt, traded against the rig's height (~1.5 arc-min): frames
  re-solved with such a rig move up or down by ~0.3 m. A rig-centre prior of POS quality (2-3 cm)
  removes this one: rx then ~0.13 arc-min, the re-solved positions as good as with the true rig.

The four best-determined combinations of the twelve deltas are known to ~0.1 arc-min.

Flying a line instead, with new markers in every frame (the simulator's flight.pattern `line`: C0
sees ~16 points a frame, a group ~1950), the bound is 0.08, 0.11 and 0.14 arc-min, the survey,
pixel and vibration terms contributing alike, and the common tilt is no longer traded against the
height: the re-solved positions are as good as with the true rig without a centre prior.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from scipy.special import chdtri

from ..blas import single_threaded_blas
from ..camera import Camera, project_unmasked
from ..dataset import factorized
from ..errors import DmaisError
from ..frames import FlightObservations
from ..geometry import Rigid3, exp_so3, left_jacobian_so3, skew
from ..rig import Rig
from ..workspace import MOUNTING_COLUMNS
from . import _group, group_normal
from .error_model import CALIBRATION_PARAMETERS, calibration_parameters
from .group_normal import GroupNormal, GroupStructure

log = logging.getLogger(__name__)

#: Test level of `significant`: with no change, this share of the (camera, group) rows is flagged.
SIGNIFICANCE = 0.01
#: Default per-axis prior sigma of delta (arc-min): generous, so that it only regularises.
PRIOR_SIGMA_ARCMIN = 30.0
RAD_PER_ARCMIN = np.pi / (180.0 * 60.0)
#: A relative focal sigma of the calibration below this holds the camera's focal length.
HELD_FOCAL_SIGMA = 1e-9
#: `_calibration_moved`'s parameter indices of the focal lengths' aspect, (fx / fx0 - fy / fy0) / 2,
#: and of the mean of the focal change's prior.
ASPECT, FOCAL_PRIOR = -1, -2
#: CALIBRATION_PARAMETERS' index of the camera centre's x (then y, z), and calibration_parameters'
#: of an opencv camera's k2 (then p1, p2, k3: Camera.parameter_names' order after k1).
CENTRE = CALIBRATION_PARAMETERS.index("vx")
LENS = len(CALIBRATION_PARAMETERS)
#: Levenberg-Marquardt: iteration limit, and converged where a step is shorter than this, in standard
#: deviations of the unknowns (in the normal matrix's metric). Near the minimum each step is ~1/50 of the
#: one before (the simulator's hovering groups): the step taken, the rig is then within ~2e-5 sigma of it,
#: where 1e-7 without taking it cost 21 iterations on two groups of 1,100 frames instead of 14.
MAX_ITERATIONS = 50
STEP_TOLERANCE = 1e-3
#: Up to this many observations (~140 bytes each), the model at the minimum is kept through the covariance's
#: solve for the calibration's share (`_rig_covariance`) rather than made again after it.
KEPT_FORWARD_OBSERVATIONS = 200_000
#: A trial cost above the current one by less than this fraction is its rounding, not an increase.
COST_ROUNDING = 1e-13
#: The mounting CSV's columns (`mounting_table`).
TABLE_COLUMNS = list(MOUNTING_COLUMNS)


@dataclass(frozen=True)
class GroupRig:
    """The group adjustment of one flight group, C cameras in the rig's order.

    cameras: (C,) names; delta_arcmin, sigma_arcmin: (C, 3) the mounting change (rotation vector in
    the camera frame, module docstring) and its 1-sigma per axis, arc-min; covariance_arcmin2:
    (C, 3, 3); chi2: (C,) delta^T cov^-1 delta; significant: (C,) chi2 beyond SIGNIFICANCE. The
    reference camera's row is 0 (not significant); a camera without observations has NaN (not
    significant). focal_ppm, sigma_focal_ppm: (C,) each camera's focal change (fx and fy scaled by
    1 + focal_ppm 1e-6) and its 1-sigma, given the calibration's covariance (NaN without it, or
    without observations). rig: the in-flight rig (the calibrated one with the deltas and focal
    changes applied); R (F, 3, 3),
    t (F, 3): the refined rig_from_world of the frames; n_frames F; iterations of LM; cost: the
    final whitened cost (module docstring) and dof its degrees of freedom, 2N - 6F (each prior adds
    as many residuals as unknowns).
    """

    cameras: tuple[str, ...]
    delta_arcmin: np.ndarray
    sigma_arcmin: np.ndarray
    covariance_arcmin2: np.ndarray
    chi2: np.ndarray
    significant: np.ndarray
    focal_ppm: np.ndarray
    sigma_focal_ppm: np.ndarray
    rig: Rig
    R: np.ndarray
    t: np.ndarray
    n_frames: int
    iterations: int
    cost: float
    dof: int


@dataclass(frozen=True)
class _Problem:
    """The checked inputs. Per observation (N): frame (N,) in [0, F); camera (N,) index into rig
    order; slot (N,) the camera's delta slot in [0, K) or -1 (reference); point (N,) in [0, P);
    uv (N, 2); weight (N,) 1 / pixel sigma. origin (3,): the surveyed points' mean, which the problem's
    world coordinates (surveyed, centroid, center) are taken from, so that their rounding is of metres,
    not of the kilometres of a map grid (it sets how closely the minimum can be told); surveyed,
    survey_sigma (P, 3); centroid (F, 3) each frame's surveyed points' mean, about which its pose turns;
    free (K,) the cameras with a delta; jitter,
    prior: sigmas in rad (jitter 0: no jitter unknowns); focal_prior (C',): the prior sigma of the
    relative focal change of each camera with a focal slot, focal_slot (C,) in [0, C') or -1 (its
    focal length held)."""

    rig: Rig
    names: list[str]
    free: list[str]
    frame: np.ndarray
    camera: np.ndarray
    slot: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    weight: np.ndarray
    origin: np.ndarray
    surveyed: np.ndarray
    survey_sigma: np.ndarray
    centroid: np.ndarray
    n_frames: int
    center: np.ndarray | None
    center_sigma: np.ndarray | None
    jitter: float
    prior: float
    focal_prior: np.ndarray
    focal_slot: np.ndarray
    structure: GroupStructure | None = None

    @property
    def local_size(self) -> int:
        """Unknowns per frame: its pose (6) and, with jitter, 3 per camera with a delta."""
        return 6 + 3 * len(self.free) * (self.jitter > 0)

    @property
    def rig_size(self) -> int:
        """The rig's unknowns: the deltas (3K), then the focal changes (C')."""
        return 3 * len(self.free) + len(self.focal_prior)

    @property
    def global_size(self) -> int:
        """The rig's unknowns, then the points (3P)."""
        return self.rig_size + self.surveyed.size


@dataclass
class _State:
    """R (F, 3, 3), t (F, 3), delta (K, 3), jitter (F, K, 3) (rad), focal (C',) the relative focal
    changes, points (P, 3)."""

    R: np.ndarray
    t: np.ndarray
    delta: np.ndarray
    jitter: np.ndarray
    focal: np.ndarray
    points: np.ndarray


# ------------------------------------------------------------------------------ the adjustment


def adjust_group_rig(rig: Rig, cameras, uv, point_ids, points, frame_index, R, t,
                     pixel_sigma_px: float | Mapping[str, float], jitter_sigma_arcmin: float, survey_sigma_m,
                     prior_sigma_arcmin: float = PRIOR_SIGMA_ARCMIN, center_prior_m=None,
                     center_sigma_m=None, calibration_covariance=None) -> GroupRig:
    """The group rig adjustment (module docstring) of the N observations of F frames of one group.

    rig: the calibrated rig; cameras (N,) names; uv (N, 2) distorted pixels; point_ids (N,);
    points (N, 3) the surveyed world points of the observations; frame_index (N,) in [0, F);
    R (F, 3, 3), t (F, 3) the frames' rig_from_world from their own solves; pixel_sigma_px: per
    axis, one value or one per camera; jitter_sigma_arcmin: per-frame vibration per axis (0: none);
    survey_sigma_m: per-axis survey sigma, a float, (3,) or (N, 3) (per observation, of its point);
    prior_sigma_arcmin: delta's prior. Optionally a prior on the rig centres -R_f^T t_f in the world,
    center_prior_m (F, 3) (e.g. the POS positions less the lever arm) with per-axis sigma
    center_sigma_m (float, (3,) or (F, 3)): not in the model above; it pins the common outward tilt
    of the cameras, which the rig's height otherwise trades against (module docstring).
    calibration_covariance (K C, K C): the calibrated rig's joint covariance of its C cameras'
    error_model.calibration_parameters (K each), camera by camera in rig order (rig.json's): each camera's
    focal change is then an unknown with its focal sigma as prior, and the covariance carries the
    share of the rest (`_calibration_share`). Raises DmaisError on inconsistent or
    degenerate input; a non-reference camera without observations gets a NaN row, with a warning.
    """
    problem = _problem(rig, cameras, uv, point_ids, points, frame_index, R, pixel_sigma_px, jitter_sigma_arcmin,
                       survey_sigma_m, prior_sigma_arcmin, center_prior_m, center_sigma_m, calibration_covariance)
    # the per-observation inputs are in `problem` now: not held through the adjustment (a line of 10,000 frames: 0.1 GB)
    del cameras, uv, point_ids, points, survey_sigma_m
    R, t = _checked_poses(R, t, problem.n_frames)
    K = len(problem.free)
    t_local = t + R @ problem.origin  # rig_from_local: x_rig = R (X - origin) + t_local
    state = _State(R.copy(), t_local, np.zeros((K, 3)), np.zeros((problem.n_frames, K, 3)),
                   np.zeros(len(problem.focal_prior)), problem.surveyed.copy())
    with single_threaded_blas():  # small matrices: threads only add hand-offs (2x slower on 2 busy cores)
        state, iterations, cost, forward = _levenberg_marquardt(problem, state)
        normal = _normal_equations(problem, state, forward if forward.J_e is not None else None)
        if forward.J_e is None or len(problem.uv) > KEPT_FORWARD_OBSERVATIONS:
            forward = None  # its Jacobians' factors are in `normal`: not held through the covariance's solve
        rig_columns, rig_inverse = (group_normal.rig_columns(normal) if calibration_covariance is not None else
                                    (None, group_normal.solve(normal, np.zeros((problem.structure.size, 0)))[1]))
        del normal  # not held through the calibration's share (0.46 GB on a line of 10,000 frames)
        covariance = _rig_covariance(problem, state, rig_columns, rig_inverse, calibration_covariance, forward)
    state = replace(state, t=state.t - state.R @ problem.origin)
    return _result(problem, state, covariance, iterations, cost)


def adjust_flight_groups(flight: FlightObservations, rig: Rig, R, t, pixel_sigma_px, jitter_sigma_arcmin: float,
                         survey_sigma_m, prior_sigma_arcmin: float = PRIOR_SIGMA_ARCMIN, center_prior_m=None,
                         center_sigma_m=None, calibration_covariance=None) -> dict[str, GroupRig]:
    """`adjust_group_rig` of every group of `flight` (frames.flight_observations_by_frame).

    R (F, 3, 3), t (F, 3): the rig_from_world of flight's F frames, NaN for a frame not solved (left
    out); survey_sigma_m: a float or (3,); center_prior_m (F, 3), center_sigma_m: as in
    `adjust_group_rig`, per frame of flight; calibration_covariance as there. Returns group ->
    GroupRig, whose R, t are of the group's solved frames in flight's order.
    """
    R, t = np.asarray(R, dtype=float).reshape(-1, 3, 3), np.asarray(t, dtype=float).reshape(-1, 3)
    if len(R) != len(flight) or len(t) != len(flight):
        raise DmaisError(f"mounting: {len(R)} rotations and {len(t)} translations for {len(flight)} frames")
    solved = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    adjusted = {}
    for group in pd.unique(flight.groups):
        frames = np.flatnonzero((flight.groups == group) & solved)
        if not len(frames):
            log.warning("mounting: group %s has no solved frame; left out", group)
            continue
        rows = np.isin(flight.frame_index, frames)
        centers = {} if center_prior_m is None else {
            "center_prior_m": np.asarray(center_prior_m, dtype=float)[frames],
            "center_sigma_m": np.broadcast_to(np.asarray(center_sigma_m, dtype=float), (len(flight), 3))[frames]}
        adjusted[str(group)] = adjust_group_rig(
            rig, flight.cameras[rows], flight.uv[rows], flight.point_ids[rows], flight.points[rows],
            np.searchsorted(frames, flight.frame_index[rows]), R[frames], t[frames], pixel_sigma_px,
            jitter_sigma_arcmin, survey_sigma_m, prior_sigma_arcmin, **centers,
            calibration_covariance=calibration_covariance)
    return adjusted


def mounting_table(adjusted: Mapping[str, GroupRig]) -> pd.DataFrame:
    """The mounting CSV (TABLE_COLUMNS): a row per group (key of `adjusted`) and camera."""
    rows = []
    for group, result in adjusted.items():
        for c, name in enumerate(result.cameras):
            rows.append({"group": group, "camera": name,
                         **dict(zip(TABLE_COLUMNS[2:5], result.delta_arcmin[c])),
                         **dict(zip(TABLE_COLUMNS[5:8], result.sigma_arcmin[c])),
                         "significant": bool(result.significant[c]),
                         "d_focal_ppm": result.focal_ppm[c], "sigma_focal_ppm": result.sigma_focal_ppm[c]})
    return pd.DataFrame(rows, columns=TABLE_COLUMNS)


# ------------------------------------------------------------------------------ the input


def _problem(rig, cameras, uv, point_ids, points, frame_index, R, pixel_sigma_px, jitter_sigma_arcmin,
             survey_sigma_m, prior_sigma_arcmin, center_prior_m, center_sigma_m, calibration_covariance) -> _Problem:
    """The checked inputs of `adjust_group_rig` as a _Problem."""
    (names, by_name), (ids, point), uv, points = _checked_observations(rig, cameras, uv, point_ids, points, frame_index)
    n_frames = len(np.asarray(R).reshape(-1, 3, 3))
    frame = _checked_frames(np.asarray(frame_index), n_frames)
    free, camera, slot = _camera_slots(rig, names, by_name)
    surveyed, survey_sigma = _points(ids, point, points, survey_sigma_m)
    origin = surveyed.mean(axis=0)
    surveyed, points = surveyed - origin, points - origin
    jitter = _non_negative(jitter_sigma_arcmin, "jitter_sigma_arcmin") * RAD_PER_ARCMIN
    prior = _non_negative(prior_sigma_arcmin, "prior_sigma_arcmin") * RAD_PER_ARCMIN
    if prior <= 0:
        raise DmaisError("mounting: prior_sigma_arcmin must be above 0")
    sums = np.column_stack([np.bincount(frame, points[:, k], minlength=n_frames) for k in range(3)])
    centroid = sums / np.bincount(frame, minlength=n_frames)[:, None]
    center, center_sigma = _centers(center_prior_m, center_sigma_m, n_frames)
    problem = _Problem(rig, rig.camera_names, free, frame, camera, slot, point, uv,
                       1.0 / _pixel_sigmas(names, by_name, pixel_sigma_px), origin, surveyed, survey_sigma, centroid,
                       n_frames, None if center is None else center - origin, center_sigma, jitter, prior,
                       *_focal_priors(rig, calibration_covariance))
    local_cols, rig_cols = _columns(problem)
    return replace(problem, structure=group_normal.group_structure(
        frame, point, local_cols, rig_cols, n_frames, problem.local_size, problem.rig_size, len(surveyed)))


def _checked_observations(rig: Rig, cameras, uv, point_ids, points, frame_index):
    """((names (D,), camera (N,)), (ids (P,), point (N,)), uv (N, 2), points (N, 3)): one camera name, point id,
    pixel and point per observation, finite, of the rig's cameras; the names and ids as str, each in its
    `_distinct` form."""
    cameras, point_ids = np.asarray(cameras), np.asarray(point_ids)
    uv, points = np.asarray(uv, dtype=float).reshape(-1, 2), np.asarray(points, dtype=float).reshape(-1, 3)
    n = len(cameras)
    if n == 0:
        raise DmaisError("mounting: a group without observations")
    if not (len(uv) == len(point_ids) == len(points) == len(frame_index) == n):
        raise DmaisError(f"mounting: {n} cameras, {len(uv)} pixels, {len(point_ids)} point ids, {len(points)} points "
                         f"and {len(frame_index)} frame indices: one of each per observation")
    if not (np.isfinite(uv).all() and np.isfinite(points).all()):
        raise DmaisError("mounting: non-finite pixels or points")
    names, camera = _distinct(cameras)
    unknown = sorted(set(names) - set(rig.cameras))
    if unknown:
        raise DmaisError(f"mounting: camera(s) {', '.join(unknown)} not in the rig ({', '.join(rig.cameras)})")
    return (names, camera), _distinct(point_ids), uv, points


def _distinct(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(values.astype(str), return_inverse=True) of values (N,): the distinct strings (D,) sorted and
    each value's place among them (N,). Values that are str objects (a table's column) are hashed first and
    only their distinct ones converted and sorted: numpy's sort of N fixed-width copies was most of a group's
    set-up."""
    if values.dtype == object and values.ndim == 1 and pd.api.types.infer_dtype(values, skipna=False) == "string":
        codes, uniques = factorized(values)
        distinct, inverse = np.unique(np.asarray(uniques, dtype=object).astype(str), return_inverse=True)
        return distinct, inverse[codes]
    return np.unique(values.astype(str), return_inverse=True)


def _camera_slots(rig: Rig, distinct: np.ndarray, camera: np.ndarray) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The non-reference cameras observed (K, in rig order), each observation's camera (N,) index in
    rig order and its delta slot (N,) in [0, K) (-1: the reference), from the observed cameras' names
    `distinct` (D,) and each observation's among them (N,); a warning names the others."""
    names = rig.camera_names
    seen = set(distinct)
    free = [c for c in names if c != rig.reference_camera and c in seen]
    missing = [c for c in names if c != rig.reference_camera and c not in seen]
    if missing:
        log.warning("mounting: camera(s) %s have no observation in the group: no estimate (NaN)", ", ".join(missing))
    in_rig = np.array([names.index(c) for c in distinct], dtype=np.int64)
    slot = np.array([free.index(c) if c in free else -1 for c in distinct], dtype=np.int64)
    return free, in_rig[camera], slot[camera]


def _checked_frames(frame_index: np.ndarray, n_frames: int) -> np.ndarray:
    """frame_index (N,) as ints, each in [0, n_frames) and every frame with at least 3 observations."""
    if not np.issubdtype(frame_index.dtype, np.integer):
        raise DmaisError(f"mounting: frame indices must be integers, got {frame_index.dtype}")
    if frame_index.min() < 0 or frame_index.max() >= n_frames:
        raise DmaisError(f"mounting: frame indices must be in [0, {n_frames}) for {n_frames} poses")
    counts = np.bincount(frame_index, minlength=n_frames)
    few = np.flatnonzero(counts < 3)
    if len(few):
        raise DmaisError(f"mounting: frame(s) {', '.join(map(str, few[:5]))} have fewer than 3 observations; "
                         "a frame's pose needs at least 3")
    return frame_index.astype(int)


def _checked_poses(R, t, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    R, t = np.asarray(R, dtype=float).reshape(-1, 3, 3), np.asarray(t, dtype=float).reshape(-1, 3)
    if len(t) != n_frames:
        raise DmaisError(f"mounting: {n_frames} rotations and {len(t)} translations")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise DmaisError("mounting: a frame's starting pose is not finite (leave unsolved frames out)")
    return R, t


def _points(ids: np.ndarray, point: np.ndarray, points: np.ndarray, survey_sigma_m) -> tuple[np.ndarray, np.ndarray]:
    """Surveyed coordinates and per-axis sigmas (P, 3) of the P distinct points, from the per-observation
    points (N, 3) and sigmas (float, (3,) or (N, 3)); point (N,) each observation's point."""
    try:
        sigma = np.broadcast_to(np.asarray(survey_sigma_m, dtype=float), points.shape)
    except ValueError:
        raise DmaisError(f"mounting: survey_sigma_m must be a float, (3,) or (N, 3), got {np.shape(survey_sigma_m)}"
                         ) from None
    if not (np.isfinite(sigma).all() and (sigma > 0).all()):
        raise DmaisError("mounting: every survey sigma must be finite and above 0")
    first = np.zeros(len(ids), int)
    first[point[::-1]] = np.arange(len(point))[::-1]
    surveyed = points[first]
    if not (_close(points, surveyed[point], 1e-9) and _close(sigma, sigma[first][point], 1e-12)):
        raise DmaisError("mounting: one point id with different coordinates or survey sigmas")
    return surveyed, sigma[first].copy()


def _close(a: np.ndarray, b: np.ndarray, atol: float) -> bool:
    """np.allclose(a, b, rtol=0, atol=atol), at once where they are equal (one table's lookups)."""
    return bool(np.array_equal(a, b) or np.allclose(a, b, rtol=0, atol=atol))


def _centers(center_prior_m, center_sigma_m, n_frames: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The rig centres' prior (F, 3) and its per-axis sigma (F, 3), or (None, None) without one."""
    if center_prior_m is None:
        return None, None
    center = np.asarray(center_prior_m, dtype=float)
    try:
        sigma = np.broadcast_to(np.asarray(center_sigma_m, dtype=float), (n_frames, 3)).copy()
    except ValueError:
        raise DmaisError(f"mounting: center_sigma_m must be a float, (3,) or (F, 3), got {np.shape(center_sigma_m)}"
                         ) from None
    if center.shape != (n_frames, 3) or not np.isfinite(center).all():
        raise DmaisError(f"mounting: center_prior_m must be finite, (F, 3) = ({n_frames}, 3), got {center.shape}")
    if not (np.isfinite(sigma).all() and (sigma > 0).all()):
        raise DmaisError("mounting: every center sigma must be finite and above 0")
    return center, sigma


def _focal_priors(rig: Rig, calibration_covariance) -> tuple[np.ndarray, np.ndarray]:
    """The relative focal sigma (C',) of each camera the calibration's covariance (K C, K C)
    (`adjust_group_rig`) gives one (that of the mean of fx / fx0 and fy / fy0), and each camera's
    slot (C,) among them (-1: none, its focal length held); none without a covariance."""
    C = len(rig.camera_names)
    if calibration_covariance is None:
        return np.zeros(0), np.full(C, -1)
    n_all = len(calibration_parameters(rig))
    covariance = np.asarray(calibration_covariance, dtype=float)
    if covariance.shape != (n_all * C, n_all * C) or not np.isfinite(covariance).all():
        raise DmaisError(f"mounting: the calibration covariance must be finite, ({n_all * C}, {n_all * C}) for "
                         f"{C} cameras, got {covariance.shape}")
    sigma = np.empty(C)
    for c, name in enumerate(rig.camera_names):
        scale = np.zeros(n_all * C)
        scale[n_all * c:n_all * c + 2] = 0.5 / np.array([rig.cameras[name].fx, rig.cameras[name].fy])
        sigma[c] = np.sqrt(max(scale @ covariance @ scale, 0.0))
    held = sigma < HELD_FOCAL_SIGMA
    return sigma[~held], np.where(held, -1, np.cumsum(~held) - 1)


def _pixel_sigmas(names: np.ndarray, camera: np.ndarray, pixel_sigma_px) -> np.ndarray:
    """(N,) per-axis pixel sigma of each observation, of camera (N,) among `names` (D,), from one value or a
    per-camera mapping."""
    if isinstance(pixel_sigma_px, Mapping):
        absent = sorted(set(names) - set(pixel_sigma_px))
        if absent:
            raise DmaisError(f"mounting: no pixel sigma for camera(s) {', '.join(absent)}")
        sigma = np.array([float(pixel_sigma_px[c]) for c in names])[camera]
    else:
        sigma = np.full(len(camera), float(pixel_sigma_px))
    if not (np.isfinite(sigma).all() and (sigma > 0).all()):
        raise DmaisError("mounting: pixel sigmas must be finite and above 0")
    return sigma


def _non_negative(value, name: str) -> float:
    value = float(value)
    if not (np.isfinite(value) and value >= 0):
        raise DmaisError(f"mounting: {name} must be finite and at least 0, got {value}")
    return value


# ------------------------------------------------------------------------------ residuals and Jacobians


@dataclass(frozen=True)
class _Forward:
    """The model at a state, per observation: e (N, 2) whitened pixel residuals; with the Jacobians'
    factors: J_e (N, 2, 3) d e / d x; J_focal (N, 2) d e / d (the camera's relative focal change); x
    (N, 3) the point in the (jittered) camera frame; q (N, 3) the point less its frame's centroid,
    turned into the rig frame; image (N,) its image, frame F x C + camera (rig order); per image (F C,
    3, 3): cam_from_rig the rotation exp([j]) exp([delta]) C_c, delta_turn exp([j]) J_l(delta) and
    jitter_turn J_l(j) (identities for the reference camera, whose delta and jitter are 0)."""

    e: np.ndarray
    J_e: np.ndarray | None = None
    J_focal: np.ndarray | None = None
    x: np.ndarray | None = None
    q: np.ndarray | None = None
    image: np.ndarray | None = None
    cam_from_rig: np.ndarray | None = None
    delta_turn: np.ndarray | None = None
    jitter_turn: np.ndarray | None = None


def _forward(problem: _Problem, state: _State, jacobians: bool = True) -> _Forward:
    """The model at `state` (_Forward); without `jacobians`, its residuals alone."""
    p, rig = problem, problem.rig
    C = len(p.names)
    per_camera = np.array([p.names.index(name) for name in p.free], dtype=int)  # the slots' cameras
    deltas, jitters = np.zeros((C, 3)), np.zeros((p.n_frames, C, 3))
    deltas[per_camera] = state.delta
    if p.local_size > 6:
        jitters[:, per_camera] = state.jitter
    cal_R = np.array([rig.cam_from_rig[c].R for c in p.names])
    cal_t = np.array([rig.cam_from_rig[c].t for c in p.names])
    D, Jm = exp_so3(deltas), exp_so3(jitters.reshape(-1, 3)).reshape(p.n_frames, C, 3, 3)
    turn = Jm @ D  # (F, C, 3, 3) exp(j) exp(delta)
    cam_from_rig = (turn @ cal_R).reshape(-1, 3, 3)
    cam_t = (turn @ cal_t[:, :, None])[..., 0].reshape(-1, 3)
    image = p.frame * C + p.camera
    x_rig, x = np.empty((len(image), 3)), np.empty((len(image), 3))
    centre = q = None
    if jacobians:  # q = x_rig - (R m + t), the point less its frame's centroid in the rig, made in the same loop
        centre, q = np.einsum("fij,fj->fi", state.R, p.centroid) + state.t, np.empty_like(x)
    _group.mounting_points_in_cameras(p.frame, p.point, image, *map(np.ascontiguousarray, (
        state.R, state.t, state.points, cam_from_rig, cam_t)), x_rig, x, centre, q)
    if all(rig.cameras[name].model == "radial1" for name in p.names):
        e, J_e, J_focal = _radial1_residuals(p, state, x, jacobians)
    else:
        e, J_e, J_focal = _projected_residuals(p, state, x, jacobians)
    if not jacobians:
        return _Forward(e)
    delta_turn = (Jm @ left_jacobian_so3(deltas)).reshape(-1, 3, 3)
    return _Forward(e, J_e, J_focal, x, q, image, cam_from_rig, delta_turn,
                    left_jacobian_so3(jitters).reshape(-1, 3, 3))


def _radial1_residuals(problem: _Problem, state: _State, x: np.ndarray, jacobians: bool):
    """`_projected_residuals` of radial1 cameras, by one compiled loop over the observations (_group)."""
    p = problem
    lens = np.empty((len(p.names), 7))  # per camera fx, fy with its focal change, cx, cy, d, fx, fy without
    for c, name in enumerate(p.names):
        calibrated = p.rig.cameras[name]
        changed = _focal_changed(calibrated, _focal(p, state, c))
        lens[c] = changed.fx, changed.fy, calibrated.cx, calibrated.cy, calibrated.d, calibrated.fx, calibrated.fy
    n = len(x)
    m = n if jacobians else 0
    e, J_e, J_focal = np.empty((n, 2)), np.empty((m, 2, 3)), np.empty((m, 2))
    _group.radial1_residuals(x, p.camera, lens, np.ascontiguousarray(p.uv), p.weight, e, J_e, J_focal, jacobians)
    return (e, J_e, J_focal) if jacobians else (e, None, None)


def _projected_residuals(problem: _Problem, state: _State, x: np.ndarray, jacobians: bool):
    """The whitened residuals e (N, 2) of points x (N, 3) in their cameras (camera.project_unmasked with each
    camera's focal change), and with `jacobians` d e / d x (N, 2, 3) and d e / d (the relative focal change)
    (N, 2); None for them without."""
    p, rig = problem, problem.rig
    predicted = np.empty((len(x), 2))
    J_pixel, J_focal = (np.empty((len(x), 2, 3)), np.empty((len(x), 2))) if jacobians else (None, None)
    for c in np.unique(p.camera):
        rows = p.camera == c
        cam = _focal_changed(rig.cameras[p.names[c]], _focal(p, state, c))
        projected = project_unmasked(x[rows], cam, jacobians)
        if not jacobians:
            predicted[rows] = projected
            continue
        predicted[rows], J_pixel[rows], by_intrinsic = projected
        unscaled = rig.cameras[p.names[c]]
        J_focal[rows] = by_intrinsic[:, :, 0] * unscaled.fx + by_intrinsic[:, :, 1] * unscaled.fy
    w = p.weight[:, None]
    e = (predicted - p.uv) * w
    if not jacobians:
        return e, None, None
    return e, J_pixel * w[:, :, None], J_focal * w


def _focal(problem: _Problem, state: _State, camera: int) -> float:
    """The relative focal change of the camera (index in rig order): 0 where it is held."""
    slot = problem.focal_slot[camera]
    return float(state.focal[slot]) if slot >= 0 else 0.0


def _focal_changed(camera: Camera, focal: float) -> Camera:
    """`camera` with fx and fy scaled by 1 + focal."""
    return replace(camera, fx=camera.fx * (1.0 + focal), fy=camera.fy * (1.0 + focal)) if focal else camera


def _columns(problem: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """Each observation's columns (C ints, group_normal.GroupStructure's): local (N, l) in its frame's block (the pose 0:6, then its camera's
    jitter) and rig (N, r) in the rig's unknowns (its camera's delta, then its focal change, where the
    problem has focal changes); an observation of the reference camera, or of a camera whose focal
    length is held, takes slot 0's, with zeros in its Jacobian (`_jacobians`)."""
    p, K = problem, len(problem.free)
    slot = np.array([p.free.index(name) if name in p.free else 0 for name in p.names])[:, None]  # per camera
    local = np.broadcast_to(np.arange(6), (len(p.names), 6))
    if p.local_size > 6:
        local = np.concatenate([local, 6 + 3 * slot + np.arange(3)], axis=1)
    rig = 3 * slot + np.arange(3)
    if len(p.focal_prior):
        rig = np.concatenate([rig, 3 * K + np.maximum(p.focal_slot, 0)[:, None]], axis=1)
    return local.astype(np.intc)[p.camera], rig.astype(np.intc)[p.camera]  # each observation's its camera's, C ints


def _jacobians(problem: _Problem, state: _State, f: _Forward):
    """`_jacobians_numpy`'s Jacobians and columns, by one compiled loop over the observations (_group)."""
    p = problem
    n, g = len(p.uv), 7 if len(p.focal_prior) else 6
    local_J, global_J = np.empty((n, 2, p.structure.local_cols.shape[1])), np.empty((n, 2, g))
    global_cols = np.concatenate([p.structure.rig_cols, p.rig_size + 3 * p.point[:, None] + np.arange(3)], axis=1)
    _group.mounting_jacobians(p.frame, f.image, p.slot, p.focal_slot[p.camera], f.J_e, f.J_focal, f.x, f.q,
                              f.cam_from_rig, f.delta_turn, f.jitter_turn, state.R, local_J, global_J)
    return local_J, p.structure.local_cols, global_J, global_cols


def _jacobians_numpy(problem: _Problem, state: _State, f: _Forward):
    """The compact Jacobians of e: local (N, 2, l) with its columns (N, l) in the frame's block and
    global (N, 2, g) with its columns (N, g) in the vector of the rig's unknowns and the points
    (`_columns`; g = 6, 7 with the focal changes, the point's 3 last); an observation of the reference
    camera has zeros for delta and jitter. With a^T [v]x = (a x v)^T: d x / d omega = -[x_rig - s]x
    through the pose turned about its centroid, and exp([j]) [z]x = [x]x exp([j])."""
    p = problem
    has = (problem.slot >= 0)[:, None, None]
    local_cols, rig_cols = p.structure.local_cols, p.structure.rig_cols
    d_rig = f.J_e @ f.cam_from_rig[f.image]  # d e / d x_rig
    pose = np.concatenate([np.cross(f.q[:, None, :], d_rig), d_rig], axis=2)
    e_cross_x = np.cross(f.J_e, f.x[:, None, :])  # J_e [x]x
    d_delta = np.where(has, -e_cross_x @ f.delta_turn[f.image], 0.0)
    focal = [np.where(p.focal_slot[p.camera][:, None] >= 0, f.J_focal, 0.0)[:, :, None]] if len(p.focal_prior) else []
    global_J = np.concatenate([d_delta, *focal, d_rig @ state.R[p.frame]], axis=2)
    global_cols = np.concatenate([rig_cols, p.rig_size + 3 * p.point[:, None] + np.arange(3)], axis=1)
    if p.local_size == 6:
        return pose, local_cols, global_J, global_cols
    d_jitter = np.where(has, -e_cross_x @ f.jitter_turn[f.image], 0.0)
    return np.concatenate([pose, d_jitter], axis=2), local_cols, global_J, global_cols


def _center_residuals(problem: _Problem, state: _State) -> tuple[np.ndarray, np.ndarray]:
    """The whitened rig-centre prior's residuals (F, 3) and their Jacobian (F, 3, 6) in a frame's
    (omega, dt): c = -R^T t = m - R^T s with s = R m + t, so dc = -R^T [s]x omega - R^T dt."""
    p = problem
    Rt = np.swapaxes(state.R, 1, 2)
    s = np.einsum("fij,fj->fi", state.R, p.centroid) + state.t
    residuals = (p.centroid - np.einsum("fij,fj->fi", Rt, s) - p.center) / p.center_sigma
    J = -np.concatenate([Rt @ skew(s), Rt], axis=2) / p.center_sigma[:, :, None]
    return residuals, J


def _cost(problem: _Problem, state: _State, forward: _Forward | None = None) -> float:
    """The whitened cost (module docstring); forward: the model at `state`, if made already."""
    p = problem
    e = (forward or _forward(p, state, jacobians=False)).e
    priors = [((state.points - p.surveyed) / p.survey_sigma).ravel(), state.delta.ravel() / p.prior,
              state.focal / p.focal_prior]
    if p.jitter > 0:
        priors.append(state.jitter.ravel() / p.jitter)
    if p.center is not None:
        priors.append(_center_residuals(p, state)[0])
    return float(np.sum(e**2) + sum(np.sum(r**2) for r in priors))


# ------------------------------------------------------------------------------ normal equations


def _normal_equations(problem: _Problem, state: _State, forward: _Forward | None = None) -> GroupNormal:
    """J^T J and J^T e of the pixel residuals in blocks (pose.group_normal), then the priors'; forward: the
    model at `state` with its Jacobians' factors, if made already. Each observation's Jacobian (`_jacobians`)
    is formed and added in one compiled loop (_group.mounting_assemble)."""
    p, s = problem, problem.structure
    f = forward or _forward(p, state)
    normal = group_normal.zero_normal(s)
    _group.mounting_assemble(p.frame, f.image, p.slot, p.focal_slot[p.camera], f.J_e, f.J_focal, f.x, f.q,
                             f.cam_from_rig, f.delta_turn, f.jitter_turn, state.R, s.point, s.local_cols, s.rig_cols,
                             f.e, *normal.blocks())
    _add_priors(p, state, normal)
    return normal


def _add_priors(problem: _Problem, state: _State, normal: GroupNormal) -> None:
    """Add the priors' terms to the normal equations' blocks in place: the deltas' and focal changes'
    to Hrr and b_rig, the points' to Hpp and b_point, the jitters' and rig centres' to A and b_local."""
    p, K = problem, len(problem.free)
    rig_weights = np.concatenate([np.full(3 * K, p.prior**-2), p.focal_prior**-2])
    normal.Hrr[np.diag_indices(len(rig_weights))] += rig_weights
    normal.b_rig[:] += rig_weights * np.concatenate([state.delta.ravel(), state.focal])
    point_weights = p.survey_sigma**-2
    normal.Hpp[:, np.arange(3), np.arange(3)] += point_weights
    normal.b_point[:] += point_weights * (state.points - p.surveyed)
    A, b_local = normal.A, normal.b_local
    if p.center is not None:
        residuals, J = _center_residuals(p, state)
        A[:, :6, :6] += np.swapaxes(J, 1, 2) @ J
        b_local[:, :6] += (np.swapaxes(J, 1, 2) @ residuals[:, :, None])[..., 0]
    if p.local_size > 6:
        jitter = np.arange(6, p.local_size)
        A[:, jitter, jitter] += p.jitter**-2
        b_local[:, 6:] += state.jitter.reshape(p.n_frames, -1) / p.jitter**2


def _step(problem: _Problem, normal: GroupNormal, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """The (damped) Gauss-Newton step: local (F, L), global (G,)."""
    F, L = problem.n_frames, problem.local_size
    with normal.damped(damping) as damped:
        step = group_normal.solve(damped, -normal.gradient[:, None])[0][:, 0]
    return step[:F * L].reshape(F, L), step[F * L:]


def _moved(problem: _Problem, state: _State, d_local: np.ndarray, d_global: np.ndarray) -> _State:
    """`state` moved by a step: R <- exp(omega) R about the frame's centroid m (R m + t moves by dt)."""
    K, m, n_rig = len(problem.free), problem.centroid, problem.rig_size
    R = exp_so3(d_local[:, :3]) @ state.R
    t = np.einsum("fij,fj->fi", state.R - R, m) + state.t + d_local[:, 3:6]
    jitter = state.jitter + d_local[:, 6:].reshape(problem.n_frames, -1, 3) if problem.local_size > 6 else state.jitter
    return _State(R, t, state.delta + d_global[:3 * K].reshape(K, 3), jitter, state.focal + d_global[3 * K:n_rig],
                  state.points + d_global[n_rig:].reshape(-1, 3))


def _levenberg_marquardt(problem: _Problem, state: _State) -> tuple[_State, int, float, _Forward]:
    """The minimum of the cost from `state`: (state, iterations, cost, the model there, with its
    Jacobians' factors where the last step was taken). Converged where a step is shorter than
    STEP_TOLERANCE in standard deviations (its length, -gradient . step, is computed from the gradient,
    exact where the difference of two costs is lost in their rounding): that step is taken, unless it
    raises the cost, and the iteration ends there, off the minimum by about the step times the rate of
    convergence."""
    forward = _forward(problem, state)
    cost, damping = _cost(problem, state, forward), 1e-6
    for iteration in range(1, MAX_ITERATIONS + 1):
        normal = _normal_equations(problem, state, forward)
        forward = _Forward(forward.e)  # its Jacobians' factors are in `normal`: not held through the solves
        while True:
            d_local, d_global = _step(problem, normal, damping)
            short = -normal.gradient @ np.concatenate([d_local.ravel(), d_global]) <= STEP_TOLERANCE**2
            trial = _moved(problem, state, d_local, d_global)
            trial_forward = _forward(problem, trial)  # with the Jacobians: most steps are taken
            trial_cost = _cost(problem, trial, trial_forward)
            if np.isfinite(trial_cost) and trial_cost <= cost * (1.0 + COST_ROUNDING):
                break
            damping *= 10.0
            if short or damping > 1e8:
                return state, iteration, cost, forward
        del normal  # freed before the next iteration's are made (a line of 10,000 frames: 0.46 GB of blocks)
        state, cost, forward = trial, trial_cost, trial_forward
        del trial_forward  # held by `forward` alone, whose factors go once the next normal equations are made
        if short:
            return state, iteration, cost, forward
        damping = max(damping / 10.0, 1e-9)
    log.warning("mounting: the group adjustment stopped at %d iterations before converging", MAX_ITERATIONS)
    return state, MAX_ITERATIONS, cost, forward


# ------------------------------------------------------------------------------ the result


def _rig_covariance(problem: _Problem, state: _State, rig_columns: np.ndarray | None, covariance: np.ndarray,
                    calibration_covariance=None, forward: _Forward | None = None) -> np.ndarray:
    """(3K + C', 3K + C') covariance of the rig's unknowns (the deltas, rad^2, then C' focal changes):
    their block of the inverse normal matrix (`covariance`; of the normal equations at `state`), plus, given
    the calibration's covariance (`adjust_group_rig`), its share (`_calibration_share`), from the inverse's
    rig columns (F L + G, 3K + C') (group_normal.rig_columns) and the model at `state` with its Jacobians'
    factors: `forward` where kept, else made again after the solve (a line's group of 10,000 frames has 1.4
    million observations: KEPT_FORWARD_OBSERVATIONS)."""
    if calibration_covariance is None:
        return covariance
    moved, columns = _calibration_moved(problem, state, forward or _forward(problem, state), rig_columns, covariance)
    return covariance + _calibration_share(problem, moved, columns, np.asarray(calibration_covariance, float))


def _calibration_share(problem: _Problem, moved: np.ndarray, columns: list[tuple[int, int]],
                       calibration_covariance: np.ndarray) -> np.ndarray:
    """(3K + C', 3K + C') the rig's unknowns' covariance from the calibration's error: A Sigma A^T,
    Sigma (K C, K C) as `adjust_group_rig`'s; moved (3K + C', n): their change per unit change of
    each parameter of `columns` (`_calibration_moved`). A: how a calibration error moves the
    estimates. Where the flight resolves the rig better than the calibration (a line of frames),
    this share is what keeps a calibration error from being flagged as a change.

    - An intrinsics error x moves the adjusted unknowns by -N^-1 J^T (d e / d x) x (the minimum's
      implicit derivative, N the normal matrix; d e / d x the projection's,
      camera.project_unmasked); much of it is a rotation the calibrated rig took up too (a
      principal point off by d px looks like a turn of d / f), so it cancels.
    - A camera whose focal change s is an unknown (prior N(0, sigma_s^2), sigma_s the calibration's
      sigma of s = (dfx / fx + dfy / fy) / 2): fx's and fy's error enters by its aspect a = (dfx /
      fx - dfy / fy) / 2, as above, and by s through the prior, whose mean is off by s: the
      unknowns move by N^-1 e_s / sigma_s^2 per unit s. The inverse normal matrix holds that term's
      variance already (the prior's own), so it is taken off again: what is left is its
      correlation with the other parameters' errors.
    - An error w of the calibrated rotation itself (about the rig's axes: rig_from_cam became
      exp(w) rig_from_cam) moves the delta, in the camera's frame, by C w (C the camera's
      cam_from_rig rotation).
    - An error of its centre in the rig enters as the intrinsics do. It matters: a rooftop
      calibration of 5 deg cameras places the centres to 2-5 cm along the rig's z axis, and 5 cm
      seen sideways from 500 m is 0.2-0.3 arc-min of a tilted camera's rx."""
    p = problem
    n_all, n_intrinsics = len(calibration_parameters(p.rig)), 5  # fx, fy, cx, cy, d first
    A = np.zeros((p.rig_size, n_all * len(p.names)))
    counted = np.zeros((p.rig_size, p.rig_size))  # the focal priors' own share, already in N^-1
    for j, (c, k) in enumerate(columns):
        camera = p.rig.cameras[p.names[c]]
        if k in (ASPECT, FOCAL_PRIOR):
            sign = -1.0 if k == ASPECT else 1.0
            A[:, n_all * c] += moved[:, j] / (2.0 * camera.fx)
            A[:, n_all * c + 1] += sign * moved[:, j] / (2.0 * camera.fy)
        else:
            A[:, n_all * c + k] = moved[:, j]
        if k == FOCAL_PRIOR:
            counted += np.outer(moved[:, j], moved[:, j]) * p.focal_prior[p.focal_slot[c]]**2
    for slot, name in enumerate(p.free):
        c = p.names.index(name)
        A[3 * slot:3 * slot + 3, n_all * c + n_intrinsics:n_all * c + n_intrinsics + 3] = p.rig.cam_from_rig[name].R
    return A @ calibration_covariance @ A.T - counted


def _calibration_moved(problem: _Problem, state: _State, f: _Forward, rig_columns: np.ndarray,
                       rig_inverse: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """(3K + C', n) how the rig's unknowns move per unit change of each calibration parameter of `columns`
    (n pairs (c, k)): per observed camera c, that camera's CALIBRATION_PARAMETERS[k], the intrinsics (k <
    5) and the centre (k = CENTRE + axis, m in the rig frame); of a camera whose focal change is an
    unknown, in place of fx and fy its aspect (k = ASPECT: fx and fy scaled by 1 + a and 1 - a) and
    its prior's mean (k = FOCAL_PRIOR). f: the model at `state` with its Jacobians' factors;
    rig_columns (F L + G, 3K + C'): the inverse normal matrix's columns of the rig's unknowns,
    rig_inverse their rows of them.

    A change x moving the whitened residuals by E x (E = d e / d x) moves the minimum by -N^-1 J^T E x,
    the rig's part of which is -rig_columns^T (J^T E) x: J^T E is summed over the camera's observations
    by one compiled loop forming their Jacobians (_group.mounting_transposed_products), never stored."""
    p, s = problem, problem.structure
    moved, columns = [], []
    for c in np.unique(p.camera):
        rows = np.flatnonzero(p.camera == c)
        camera = _focal_changed(p.rig.cameras[p.names[c]], _focal(p, state, c))
        intrinsic = project_unmasked(f.x[rows], camera, True)[2]  # the model's, fx, fy, cx, cy, d first
        parameters = [0, 1, 2, 3, 4] + [LENS + k for k in range(intrinsic.shape[2] - 5)]
        aspect = int(p.focal_slot[c] >= 0)
        by_parameter = np.empty((len(rows), 2, intrinsic.shape[2] - aspect + 3))  # whitened, then the centre's 3
        weight = p.weight[rows, None]
        if aspect:
            by_parameter[:, :, 0] = intrinsic[:, :, 0] * weight * camera.fx - intrinsic[:, :, 1] * weight * camera.fy
            parameters = [ASPECT] + parameters[2:]
        np.multiply(intrinsic[:, :, 2 * aspect:], weight[:, :, None], out=by_parameter[:, :, aspect:-3])
        # d e / d x_rig is the pose's translation columns; x_cam = C (x_rig - centre): d e / d centre = -d_rig
        np.negative(f.J_e[rows] @ f.cam_from_rig[f.image[rows]], out=by_parameter[:, :, -3:])
        effect = np.zeros((s.size, by_parameter.shape[2]))  # J^T E
        _group.mounting_transposed_products(rows, p.frame, f.image, p.slot, p.focal_slot[p.camera], f.J_e,
                                            f.J_focal, f.x, f.q, f.cam_from_rig, f.delta_turn, f.jitter_turn,
                                            state.R, s.point, s.local_cols, s.rig_cols, p.local_size, p.rig_size,
                                            by_parameter, effect)
        moved.append(-(rig_columns.T @ effect))
        columns += [(int(c), parameter) for parameter in parameters + [CENTRE, CENTRE + 1, CENTRE + 2]]
        if p.focal_slot[c] >= 0:  # the prior's residual (s - m) / sigma_s: the gradient moves by -e_s / sigma_s^2 per m
            slot = 3 * len(p.free) + p.focal_slot[c]
            moved.append(rig_inverse[:, slot:slot + 1] * p.focal_prior[p.focal_slot[c]]**-2)
            columns.append((int(c), FOCAL_PRIOR))
    return np.hstack(moved), columns


def _result(problem: _Problem, state: _State, covariance: np.ndarray, iterations: int, cost: float) -> GroupRig:
    """The GroupRig of the minimum: rows in rig order, the reference's 0, unobserved cameras' NaN;
    covariance (3K + C', 3K + C') the rig's unknowns' (`_rig_covariance`)."""
    rig, names = problem.rig, problem.names
    C = len(names)
    delta, cov, chi2 = np.full((C, 3), np.nan), np.full((C, 3, 3), np.nan), np.full(C, np.nan)
    reference = names.index(rig.reference_camera)
    delta[reference], cov[reference], chi2[reference] = 0.0, 0.0, 0.0
    cam_from_rig = dict(rig.cam_from_rig)
    for k, name in enumerate(problem.free):
        c = names.index(name)
        delta[c], cov[c] = state.delta[k], covariance[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        chi2[c] = state.delta[k] @ np.linalg.solve(cov[c], state.delta[k])
        cam_from_rig[name] = Rigid3(exp_so3(state.delta[k]), np.zeros(3)) * rig.cam_from_rig[name]
    focal, sigma_focal, cameras = _focal_changes(problem, state, covariance)
    # chi-square's upper quantile by scipy.special: scipy.stats took 0.35-0.7 s of a pose job's start
    significant = np.nan_to_num(chi2, nan=0.0) > chdtri(3, SIGNIFICANCE)
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)) / RAD_PER_ARCMIN
    return GroupRig(tuple(names), delta / RAD_PER_ARCMIN, sigma, cov / RAD_PER_ARCMIN**2, chi2, significant,
                    focal, sigma_focal, Rig(cameras, cam_from_rig, rig.reference_camera), state.R, state.t,
                    problem.n_frames, iterations, cost, 2 * len(problem.uv) - 6 * problem.n_frames)


def _focal_changes(problem: _Problem, state: _State, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """(C,) the focal changes and their sigmas in ppm (NaN where not estimated or not observed), and
    the cameras with them applied."""
    names, C, K = problem.names, len(problem.names), len(problem.free)
    cameras = dict(problem.rig.cameras)
    focal, sigma = np.full(C, np.nan), np.full(C, np.nan)
    for c in np.unique(problem.camera):
        slot = problem.focal_slot[c]
        if slot >= 0:
            focal[c], sigma[c] = state.focal[slot] * 1e6, np.sqrt(covariance[3 * K + slot, 3 * K + slot]) * 1e6
            cameras[names[c]] = _focal_changed(cameras[names[c]], state.focal[slot])
    return focal, sigma, cameras
