"""The error model behind poses.csv's 1-sigma: variance components of the observations, estimated
from the residuals of the frames solved together, and propagated to every frame's pose.

Observation i (frame f, camera c, ground point p, flight group g) has the angular residual r_i
(2,) of refine.py: the tangent-plane error, in the basis B_i (2, 3) of its observed unit ray f_i
(rig frame), between f_i and the direction to its point. Its error at the true pose is the sum of
independent zero-mean terms (F_i the camera's focal length in px, a_c its optical axis in the rig
frame, R the frame's rig_from_world):

    component    effect on r_i                         random variable                  one draw per
    pixel        n_i / F_i                             n_i ~ N(0, s_px^2 I2) px         observation
    survey       D_i dM_p, D_i = dr_i/dp R  (2, 3)     dM_p ~ N(0, diag(s_h^2, s_h^2,   ground point
                                                        s_v^2)) m
    jitter       G_i w, G_i = B_i [f_i]x  (2, 3)       w ~ N(0, s_j^2 I3) rad           frame, non-reference camera
    mounting     G_i m                                 m ~ N(0, s_m^2 I3) rad           group, non-reference camera
    focal        h_i k, h_i = -(f_i . a_c) B_i a_c     k ~ N(0, s_k^2) (relative)       group, camera
    calibration  C_i x  (2, 11)                        x ~ N(0, Sigma_c) (fx fy cx cy   whole flight
                                                        d, rotation, centre) of all cameras

The survey error's horizontal (world x, y: component `survey`) and vertical (z:
`survey_vertical`) sigmas are two components, as RTK reports give them (its height is worse);
unless the vertical is given (a setting, or ground_points.csv's `sigma_z_m`) the two are one
sigma, estimated for all three axes: estimated apart from one group's points (40 on the
paper-scale run) the split was too uncertain to use (horizontal 0.87-1.71 cm where the groups'
points had 1.20-1.60).

Jitter is the camera's vibration within a frame (every point of that camera moves together),
mounting its rotation against the calibrated rig during a group, focal its focal-length change
(a thermal focus change, or the calibration's own focal error: both scale the image about the
axis). The reference camera has no jitter or mounting term: the rig frame is its frame, so its
rotation is the platform's attitude. The calibration term is fixed: the calibration's joint
covariance of every camera's parameters (rig.json's calibration_covariance: cameras calibrated on
the same control points share their survey errors, and the rig is fitted with the intrinsics as
they are, so their errors are correlated); the survey terms are fixed per point where
ground_points.csv gives `sigma_m` (and `sigma_z_m`), and any other component where the user sets it.

Estimation (variance-component estimation, method of moments as Helmert's: quadratic forms of the
residuals equated to their expectations), per flight group, on at most ESTIMATION_FRAMES of its
frames. A frame's solve is linear in the errors e about the truth: its residuals are
r = e - J A^-1 sum_i w_i J_i^T e_i per frame (J, w, A as uncertainty.py), so each statistic T_m of
`Statistics`, a quadratic form in r, has expectation E T_m = sum_k s_k^2 D_mk. The D_mk are
estimated by Monte Carlo trace estimation (Rademacher draws of each component through the same
linear solve, Koch & Kusche 2002, J. Geodesy 76: 641-652), the calibration's exactly (its few
parameters one at a time). The statistics separate the components by their structure: pixel
noise is what no structure explains; survey what repeats per point; jitter what moves a camera's
points together in one frame only; mounting and focal what does so in every frame of the group.

The system is solved for the free components by non-negative least squares, each statistic
weighted by its spread under a first fit (drawn, `_spread`). A component that the solves absorb
(a rotation of a camera solved alone) is not estimable; one estimated below SIGNIFICANCE of its
standard errors were it absent (`_null_error`: under the fit with it, a group's 2' mounting
change was never significant, its own draws making its statistic's spread as large as its value)
is not significant (the least significant is dropped and the rest estimated again); both are 0
for the others' estimation, and in the sigmas their prior where one is given
(`estimate`'s priors; for a not significant one at most its estimate plus SIGNIFICANCE standard
errors), else 0. Jitter and
mounting act alike on one frame, so their sum is far better determined than their split; the
sigmas use the sum. A mounting change hardly shows in one group's residuals (the pose and the
same points' survey errors absorb it) yet moves the whole rig's position: 0.45' of it moved a
simulated group by 14 cm, unseen. It needs a prior (the pose stage's error_priors, mounting 0.15'
by default, the simulator's rooftop-to-flight change).

Propagation: cov(omega, delta_t) of frame f = A^-1 (sum_k B_k) A^-1, B_k = the k-th component's
covariance of sum_i w_i J_i^T e_i (correlated within a camera for jitter, mounting, focal and
calibration, per point for survey). Correlations between frames (a point's survey error, a group's
mounting) do not enter one frame's covariance; they make the frames' errors alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import nnls

from ..camera import LENS_FIELDS, project_unmasked
from ..rig import Rig
from ._error import block_outer_sums, calibration_columns, covariance_sums, linearised_rows, row_products
from .refine import inverse_normal_matrices

ARCMIN = np.radians(1.0 / 60.0)
#: The components, in the order of every array here.
COMPONENTS = ("pixel", "survey", "survey_vertical", "jitter", "mounting", "focal", "calibration")
#: The components drawn at random per observation, point, frame or group (all but the calibration).
RANDOM = COMPONENTS[:-1]
#: Units of ErrorModel.sigma per component (calibration: a factor on rig.json's covariance).
UNITS = {"pixel": "px", "survey": "m", "survey_vertical": "m", "jitter": "arcmin", "mounting": "arcmin",
         "focal": "ppm", "calibration": "x"}
_TO_SI = {"pixel": 1.0, "survey": 1.0, "survey_vertical": 1.0, "jitter": ARCMIN, "mounting": ARCMIN, "focal": 1e-6,
          "calibration": 1.0}
#: Which world axes (x, y, z) each survey component moves.
SURVEY_AXES = {"survey": np.array([1.0, 1.0, 0.0]), "survey_vertical": np.array([0.0, 0.0, 1.0])}
#: Fewest residual degrees of freedom (2n - 6 per frame, summed) to estimate any component.
MIN_DEGREES_OF_FREEDOM = 4
#: Monte Carlo draws of each component for the expectations, and of the fitted model for the
#: statistics' spread: their precision depends on the draws, not on the number of observations.
DRAWS = 16
#: The most frames of a group the estimation uses, evenly spread over it (`estimation_frames`): the
#: components belong to the group, and 64 frames of 40 observations give them to a few percent.
ESTIMATION_FRAMES = 64
#: A component is not estimable where the frames' solves absorb all but this share of its effect
#: (E ||residual||^2 / E ||error||^2), as a single camera's solve absorbs a rotation of it.
MIN_VISIBLE = 0.02
#: A component estimated below this many of its standard errors is taken as absent (not significant).
SIGNIFICANCE = 2.0
#: Floor of a statistic in the estimation's relative weights, as a share of their total.
MIN_EFFECT = 1e-6
#: The calibration parameters of one camera, in the order of the columns of C_i ("d": the first
#: radial coefficient, an opencv camera's k1)...
CALIBRATION_PARAMETERS = ("fx", "fy", "cx", "cy", "d", "rx", "ry", "rz", "vx", "vy", "vz")
#: ... then, where the rig has an opencv camera, its further lens parameters.
LENS_PARAMETERS = LENS_FIELDS


def calibration_parameters(rig: Rig) -> tuple[str, ...]:
    """The calibration parameters per camera of `rig` (the columns of C_i): CALIBRATION_PARAMETERS,
    and LENS_PARAMETERS after them when a camera of the rig has the opencv model."""
    richer = any(camera.model != "radial1" for camera in rig.cameras.values())
    return CALIBRATION_PARAMETERS + (LENS_PARAMETERS if richer else ())


@dataclass(frozen=True)
class ErrorModel:
    """One standard deviation per component (COMPONENTS, in UNITS), and how each was obtained:
    `source` 'estimated', 'set' (given by the user, or the calibration's factor 1), 'calibration'
    (the pixel noise of the calibration, where the frames have too few observations), 'prior' (the
    residuals could not tell it: the user's prior), 'not estimable' (no effect on the residuals) or
    'not significant' (both 0). dof: the
    residual degrees of freedom the estimate used."""

    sigma: dict[str, float]
    source: dict[str, str]
    dof: int = 0

    def si(self, name: str) -> float:
        """The component's sigma in SI units (px, m, rad, relative, factor)."""
        return self.sigma[name] * _TO_SI[name]


@dataclass
class Geometry:
    """The linearised solve of F frames from N observations (see the module docstring).

    J (N, 2, 6), weight (N,): refine.py's Jacobian about each frame's point centroid and the
    solve's weights; A_inverse (F, 6, 6); residual (N, 2) rad; focal (N,) px; frame (N,) ascending,
    starts (F,) its first rows; camera (N,) int; reference (N,) bool; group (N,) int; point (N,)
    int; survey (N, 2, 3) D_i; rotation (N, 2, 3) G_i; focal_effect (N, 2) h_i; calibration
    (N, 2, K) C_i (per calibration_parameters, K of them, zero where the calibration gives no variance);
    calibration_covariance (K C, K C) of the C rig cameras' calibration_parameters, camera by
    camera in the rig's order; point_sigma (N, 3) m along x, y, z, NaN where not given; t_centred
    (F, 3) the translations about each frame's point centroid (t + R m), R (F, 3, 3) the solved rotations,
    origins (N, 3) the rays' origins and points_centred (N, 3) the points less their frame's
    centroid (for re-solving the frames, `nonlinear.py`)."""

    J: np.ndarray
    weight: np.ndarray
    A_inverse: np.ndarray
    residual: np.ndarray
    focal: np.ndarray
    frame: np.ndarray
    starts: np.ndarray
    camera: np.ndarray
    reference: np.ndarray
    group: np.ndarray
    point: np.ndarray
    survey: np.ndarray
    rotation: np.ndarray
    focal_effect: np.ndarray
    calibration: np.ndarray
    calibration_covariance: np.ndarray
    point_sigma: np.ndarray
    t_centred: np.ndarray = field(repr=False, default=None)
    R: np.ndarray = field(repr=False, default=None)
    origins: np.ndarray = field(repr=False, default=None)
    points_centred: np.ndarray = field(repr=False, default=None)

    @property
    def n_frames(self) -> int:
        return len(self.starts)

    @property
    def dof(self) -> int:
        return int(2 * len(self.frame) - 6 * self.n_frames)


def linearised_solve(rig: Rig, cameras: np.ndarray, uv: np.ndarray, origins, directions, points,
                     frame_index, R, t, groups, point_ids, object_space: bool,
                     point_sigma_m=None, calibration_covariance: np.ndarray | None = None) -> Geometry:
    """The Geometry of F solved frames (module docstring).

    cameras (N,) names, uv (N, 2) px, origins, directions (N, 3) rig frame, points (N, 3) world,
    frame_index (N,) ascending with every frame present, R (F, 3, 3), t (F, 3) rig_from_world,
    groups (F,) the frames' groups, point_ids (N,), object_space: the poses minimise the paper's
    eq. objfun (True) or the angular residuals (False); point_sigma_m (N, 3) or (N,) (all axes) the
    survey sigma of each observation's point along x, y, z (NaN where not given);
    calibration_covariance (K C, K C) of the rig cameras' calibration_parameters (Geometry;
    rotations rx, ry, rz in rad about the rig's axes, the camera centre vx, vy, vz in the rig, m),
    None: 0.
    """
    n_frames = len(R)
    frame_index = np.asarray(frame_index)
    counts = np.bincount(frame_index, minlength=n_frames)
    centroid = np.stack([np.bincount(frame_index, points[:, k], minlength=n_frames) for k in range(3)], axis=1)
    centroid = centroid / np.maximum(counts, 1)[:, None]
    t_centred = t + np.einsum("fij,fj->fi", R, centroid)
    names = list(rig.cameras)
    camera_names = np.asarray(cameras)
    camera = np.full(len(cameras), -1)
    for c, name in enumerate(names):
        camera[camera_names == name] = c
    axes = np.array([rig.cam_from_rig[name].R[2] for name in names])
    # one compiled pass for the rows (numpy's expressions, tests/test_error_model_rows.py): the rays' unit
    # vectors and tangent bases, refine._jacobian about the centroids, |p|^2 of the uncentred points and the
    # survey's dr/dp, B [f]x and the focal effect -(f . a) B a
    unit, bases, residual, J, squares, dr_dp, rotation, focal_effect, points_centred = linearised_rows(
        origins, directions, points, centroid, R, t, t_centred, frame_index, axes, camera)
    if object_space:
        weight = squares / (np.bincount(frame_index, squares, minlength=n_frames)[frame_index] / counts[frame_index])
    else:
        weight = np.ones(len(points))
    A = row_products(J, J, frame_index, n_frames, weight)  # sum of (w J)^T J
    group_codes = pd.factorize(np.asarray(groups).astype(str), sort=True)[0]  # np.unique's codes, by hashing
    point_codes = pd.factorize(np.asarray(point_ids).astype(str), sort=True)[0]
    n_parameters = len(calibration_parameters(rig)) * len(names)
    calibration_covariance = np.zeros((n_parameters, n_parameters)) if calibration_covariance is None \
        else np.asarray(calibration_covariance, dtype=float)
    calibration = _calibration_effects(rig, names, camera, uv, bases, rotation, dr_dp, np.diag(calibration_covariance))
    point_sigma = np.full((len(points), 3), np.nan) if point_sigma_m is None else \
        np.broadcast_to(np.asarray(point_sigma_m, float).reshape(len(points), -1), (len(points), 3)).copy()
    R_rows = R[frame_index]
    return Geometry(J=J, weight=weight, A_inverse=inverse_normal_matrices(A), residual=residual,
                    focal=np.array([rig.cameras[n].fx for n in names])[camera], frame=np.asarray(frame_index),
                    starts=np.searchsorted(frame_index, np.arange(n_frames)), camera=camera,
                    reference=camera == names.index(rig.reference_camera), group=group_codes[frame_index],
                    point=point_codes, survey=dr_dp @ R_rows, rotation=rotation, focal_effect=focal_effect,
                    calibration=calibration, calibration_covariance=calibration_covariance, point_sigma=point_sigma,
                    t_centred=t_centred, R=R, origins=origins, points_centred=points_centred)


def _calibration_effects(rig: Rig, names: list[str], camera_of, uv, bases, rotation, dr_dp, variances) -> np.ndarray:
    """C_i (N, 2, K): the change of r_i (of camera names[camera_of[i]]) per unit change of each of its camera's
    calibration_parameters (intrinsics as its ray moves, `_ray_changes`; a rotation w of the camera
    about the rig's axes rotates its rays by w; a move of its centre moves their origin), where its
    variance (variances (K C,)) is not 0; bases (N, 2, 3) B_i, rotation (N, 2, 3) G_i = B_i [f_i]x,
    dr_dp (N, 2, 3) the residuals' change with the ray-to-point vector."""
    parameters = calibration_parameters(rig)
    k_all = len(parameters)
    effects = np.zeros((len(uv), 2, k_all))
    for c, name in enumerate(names):
        rows = np.flatnonzero(camera_of == c)
        sigma = np.sqrt(np.clip(variances[k_all * c:k_all * (c + 1)], 0.0, None))
        if not len(rows) or not sigma.any():
            continue
        camera = rig.cameras[name]
        # the camera's own parameters: fx fy cx cy and d (k1), then LENS_PARAMETERS by name
        own = {k: k if k < 5 else camera.parameter_names.index(parameters[k]) for k in range(k_all)
               if (k < 5 or parameters[k] in LENS_PARAMETERS) and sigma[k] > 0}
        w, dw = _pixel_changes(camera, uv[rows]) if own else (np.zeros((0, 3)), np.zeros((0, 2, 0)))
        # d f / d w = -[f]x: r changes by -B df = B [f]x w; the origin by dv: p by -dv
        calibration_columns(w, dw, rig.cam_from_rig[name].R.T, bases, rotation, dr_dp, rows, list(own),
                            list(own.values()), effects)
    return effects


def _pixel_changes(camera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """w (n, 3) = (x, y, 1), the undistorted points of pixels (n, 2), and the change of (x, y) (n, 2, P) per unit
    change of each of the camera's parameter_names (P): at a fixed pixel it moves by -J_xy^-1 J_p (the
    projection's Jacobians there). NaN where the pixel does not undistort."""
    xy = camera.undistort_normalized(pixels)
    w = np.column_stack([xy, np.ones(len(xy))])
    _, J_point, J_parameters = project_unmasked(w, camera, jacobian=True)
    J = J_point[:, :, :2]  # at depth 1, d pixels / d (x, y)
    inverse = np.empty((len(xy), 2, 2))
    inverse[:, 0, 0], inverse[:, 0, 1] = J[:, 1, 1], -J[:, 0, 1]
    inverse[:, 1, 0], inverse[:, 1, 1] = -J[:, 1, 0], J[:, 0, 0]
    inverse /= (J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])[:, None, None]
    return w, -inverse @ J_parameters


def _ray_changes(camera, rig_from_cam: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(n, 3, P) the change of the unit rays (rig frame) of pixels (n, 2) per unit change of each of the
    camera's parameter_names (P): the ray w / |w| of `_pixel_changes`' w moves by (I - f f^T) dw / |w|, dw its
    change (of x, y; not of 1). NaN where the pixel does not undistort. (Central differences of the rays did the
    same, 10 undistortions a camera.) The numpy of what `_calibration_effects` computes compiled
    (`_error.calibration_columns`)."""
    w, moved = _pixel_changes(camera, pixels)
    dw = np.zeros((len(w), 3, moved.shape[2]))
    dw[:, :2] = moved
    norm = np.linalg.norm(w, axis=1)
    f = w / norm[:, None]
    change = (dw - f[:, :, None] * np.einsum("ni,nip->np", f, dw)[:, None, :]) / norm[:, None, None]
    return np.einsum("ij,njp->nip", rig_from_cam, change)


def _sum_by(values: np.ndarray, key: np.ndarray, n_keys: int) -> np.ndarray:
    """Sums (n_keys, ...) of values (N, ...) per key (N,) in [0, n_keys) (rows with key < 0 ignored).
    One bincount over (key, entry) slots: each sum adds its rows in their order, as one bincount
    per entry did."""
    width = int(np.prod(values.shape[1:]))
    if len(key) and key.min() < 0:
        keep = key >= 0
        values, key = values[keep], key[keep]
    flat = values.reshape(len(key), width)
    slots = (key[:, None] * width + np.arange(width)).ravel()
    return np.bincount(slots, flat.ravel(), minlength=n_keys * width).reshape(n_keys, *values.shape[1:])


def solve_response(geometry: Geometry, errors: np.ndarray) -> np.ndarray:
    """Residuals (..., N, 2) of the frames' solves for observation errors (..., N, 2) (rad): e - J dtheta."""
    g = geometry
    right = np.einsum("nkj,...nk->...nj", g.J * g.weight[:, None, None], errors)
    sums = np.add.reduceat(right, g.starts, axis=-2) if g.n_frames else right[..., :0, :]
    step = np.einsum("fij,...fj->...fi", g.A_inverse, sums)
    return errors - np.einsum("nkj,...nj->...nk", g.J, step[..., g.frame, :])


def _dense(key: np.ndarray) -> np.ndarray:
    """key (N,) renumbered 0, 1, ... in order of value, -1 kept: np.unique's codes, by counting the
    values present where they are fewer than about 8 N."""
    out = np.full(len(key), -1)
    keep = key >= 0
    kept = key[keep]
    if len(kept) and kept.max() < 8 * len(kept) + 1024:
        present = np.zeros(int(kept.max()) + 1, bool)
        present[kept] = True
        out[keep] = (np.cumsum(present) - 1)[kept]
    else:
        out[keep] = np.unique(kept, return_inverse=True)[1]
    return out


class Statistics:
    """The quadratic forms of residuals that the estimation equates to their expectations, in
    pixels (s_i = F_i r_i), for one Geometry:

        T_rotation  the part of each frame's residuals that its pose and one rotation per
                    non-reference camera explain (least squares, frame by frame; jitter, mounting);
        T_pixel     what remains (q), less T_point (pixel noise);
        T_point     the part of q that a constant per (group, point) explains, points seen in 2
                    frames or more (survey);
        T_group     per group, the part that one rotation per non-reference camera for all its
                    frames explains beyond each frame's pose (mounting);
        T_focal     the part of q that one focal change per (group, camera) explains (focal).

    Refitting the pose with the rotations keeps jitter out of q, so that the small pixel term is not
    swamped by the sampling noise of the large ones.
    """

    NAMES = ("rotation", "pixel", "point", "group", "focal")

    def __init__(self, geometry: Geometry):
        g = self.geometry = geometry
        cameras = int(g.camera.max()) + 1 if len(g.camera) else 1
        moving = np.unique(g.camera[~g.reference])
        self.slot = np.where(g.reference, -1, np.searchsorted(moving, g.camera))  # (N,) rotation block of a row
        self.width = 6 + 3 * len(moving)
        scale = g.focal[:, None, None]
        self.pose_rows = g.J * scale  # (N, 2, 6)
        self.rotation_rows = g.rotation * scale  # (N, 2, 3)
        self.focal_rows = g.focal_effect * g.focal[:, None]  # (N, 2)
        normal = self._normal()
        self.inverse = np.linalg.pinv(normal, rcond=1e-10, hermitian=True)
        # per frame, the rotations' normal matrix with the pose eliminated, for T_group
        self.pose_inverse = np.linalg.pinv(normal[:, :6, :6], rcond=1e-12, hermitian=True)
        self.cross = normal[:, :6, 6:]
        schur = normal[:, 6:, 6:] - np.swapaxes(self.cross, 1, 2) @ self.pose_inverse @ self.cross
        self.frame_group = np.zeros(g.n_frames, int)
        self.frame_group[g.frame] = g.group
        n_groups = int(self.frame_group.max()) + 1 if g.n_frames else 0
        self.group_inverse = np.linalg.pinv(_sum_by(schur, self.frame_group, n_groups), rcond=1e-10, hermitian=True)
        group_point = _dense(g.group * (int(g.point.max()) + 1 if len(g.point) else 1) + g.point)
        repeated = np.bincount(group_point)[group_point] >= 2 if len(g.point) else np.zeros(0, bool)
        self.point = np.where(repeated, group_point, -1)  # points seen in 2 frames or more
        self.group_camera = _dense(g.group * cameras + g.camera)

    def _columns(self, rows: np.ndarray) -> np.ndarray:
        """The frame-projection's right-hand sides (F, width) of per-row products (N, 6 + 3)."""
        g = self.geometry
        out = np.zeros((g.n_frames, self.width))
        out[:, :6] = _sum_by(rows[:, :6], g.frame, g.n_frames)
        moving = self.slot >= 0
        for slot in np.unique(self.slot[moving]):
            mask = self.slot == slot
            out[:, 6 + 3 * slot:9 + 3 * slot] = _sum_by(rows[mask, 6:], g.frame[mask], g.n_frames)
        return out

    def _normal(self) -> np.ndarray:
        """(F, width, width) per frame, X^T X of the pose and rotation columns."""
        g = self.geometry
        pose, rotation = self.pose_rows, self.rotation_rows
        normal = np.zeros((g.n_frames, self.width, self.width))
        normal[:, :6, :6] = _sum_by(np.einsum("nki,nkj->nij", pose, pose), g.frame, g.n_frames)
        for slot in np.unique(self.slot[self.slot >= 0]):
            mask = self.slot == slot
            cols = slice(6 + 3 * slot, 9 + 3 * slot)
            cross = _sum_by(np.einsum("nki,nkj->nij", pose[mask], rotation[mask]), g.frame[mask], g.n_frames)
            normal[:, :6, cols], normal[:, cols, :6] = cross, np.swapaxes(cross, 1, 2)
            normal[:, cols, cols] = _sum_by(np.einsum("nki,nkj->nij", rotation[mask], rotation[mask]),
                                            g.frame[mask], g.n_frames)
        return normal

    def __call__(self, residuals: np.ndarray) -> np.ndarray:
        """(5,) the statistics (NAMES) of residuals (N, 2) rad."""
        g = self.geometry
        s = residuals * g.focal[:, None]
        products = np.concatenate([np.einsum("nki,nk->ni", self.pose_rows, s),
                                   np.einsum("nki,nk->ni", self.rotation_rows, s)], axis=1)
        columns = self._columns(products)
        coefficients = np.einsum("fij,fj->fi", self.inverse, columns)  # (F, width)
        own = np.zeros((len(s), 3))
        moving = self.slot >= 0
        for slot in np.unique(self.slot[moving]):
            mask = self.slot == slot
            own[mask] = coefficients[g.frame[mask], 6 + 3 * slot:9 + 3 * slot]
        fitted = np.einsum("nki,ni->nk", self.pose_rows, coefficients[g.frame, :6]) + \
            np.einsum("nki,ni->nk", self.rotation_rows, own)
        rest = s - fitted
        point = _constant_explained(rest, self.point)
        within = float(np.sum(rest * rest))
        return np.array([float(np.sum(s * s)) - within, within - point, point, self._group(columns),
                         _focal_explained(rest, self.focal_rows, self.group_camera)])

    def _group(self, columns: np.ndarray) -> float:
        """T_group from the frames' right-hand sides (F, width): per group, the pixels that one
        rotation per non-reference camera for all its frames explains beyond each frame's pose
        (least squares with the poses eliminated: Schur complements summed over the frames)."""
        if self.width == 6:
            return 0.0
        pose_part = np.einsum("fij,fj->fi", self.pose_inverse, columns[:, :6])
        reduced = columns[:, 6:] - np.einsum("fji,fj->fi", self.cross, pose_part)
        right = _sum_by(reduced, self.frame_group, len(self.group_inverse))
        return float(np.einsum("gi,gij,gj->", right, self.group_inverse, right))


def _constant_explained(values: np.ndarray, key: np.ndarray) -> float:
    """sum over blocks of ||sum of the block's values||^2 / its rows: the part of values (N, k) that a
    constant per block (key (N,), -1: none) explains."""
    keep = key >= 0
    if not keep.any():
        return 0.0
    sums = _sum_by(values[keep], key[keep], int(key.max()) + 1)
    return float(np.sum(np.sum(sums * sums, axis=1) / np.maximum(np.bincount(key[keep]), 1)))


def _focal_explained(values: np.ndarray, rows: np.ndarray, key: np.ndarray) -> float:
    """The part of values (N, 2) that one multiple of rows (N, 2) per block (key (N,)) explains."""
    n_keys = int(key.max()) + 1 if len(key) else 0
    across = np.bincount(key, np.sum(rows * values, axis=1), minlength=n_keys)
    norm = np.bincount(key, np.sum(rows * rows, axis=1), minlength=n_keys)
    return float(np.sum(np.where(norm > 0, across**2 / np.where(norm > 0, norm, 1.0), 0.0)))


# ------------------------------------------------------------------------------ estimation

def estimation_frames(n_frames: int) -> np.ndarray:
    """Indexes (k,) of the frames, of n_frames, that the estimation uses: all, or ESTIMATION_FRAMES
    evenly spread."""
    if n_frames <= ESTIMATION_FRAMES:
        return np.arange(n_frames)
    return np.unique(np.linspace(0, n_frames - 1, ESTIMATION_FRAMES).round().astype(int))


def unit_draw(geometry: Geometry, name: str, rng: np.random.Generator, gaussian: bool = False) -> np.ndarray:
    """Errors (N, 2) rad of one draw of component `name` with unit variance (1 px, 1 m, 1 rad, 1
    relative focal change), Rademacher (the least-variance trace estimate) or Gaussian; the survey
    components along their SURVEY_AXES where the point's sigma is not given."""
    g = geometry
    signs = (lambda *shape: rng.normal(size=shape)) if gaussian else \
        (lambda *shape: rng.integers(0, 2, shape) * 2.0 - 1.0)
    n = len(g.frame)
    if name == "pixel":
        return signs(n, 2) / g.focal[:, None]
    if name in SURVEY_AXES:
        return _survey_draw(g, signs, np.isnan(g.point_sigma) * SURVEY_AXES[name])
    n_cameras = int(g.camera.max()) + 1 if n else 1
    if name in ("jitter", "mounting"):
        key = _dense(np.where(g.reference, -1, (g.frame if name == "jitter" else g.group) * n_cameras + g.camera))
        moves = np.vstack([signs(int(key.max()) + 1, 3), np.zeros((1, 3))])[key]  # key -1: the last, zero row
        return np.einsum("nkj,nj->nk", g.rotation, moves)
    if name == "focal":
        key = _dense(g.group * n_cameras + g.camera)
        return g.focal_effect * signs(int(key.max()) + 1)[key][:, None]
    raise ValueError(f"no random draw for component {name!r}")


def fixed_survey_draw(geometry: Geometry, rng: np.random.Generator) -> np.ndarray:
    """Errors (N, 2) of one Rademacher draw of the survey errors of the points whose sigma is given."""
    return _survey_draw(geometry, lambda *shape: rng.integers(0, 2, shape) * 2.0 - 1.0,
                        np.nan_to_num(geometry.point_sigma))


def _survey_draw(g: Geometry, signs, scale: np.ndarray) -> np.ndarray:
    """Errors (N, 2) of one draw `signs(P, 3)` of the points' moves, scaled per row and axis by scale (N, 3)."""
    moves = signs(int(g.point.max()) + 1 if len(g.point) else 0, 3)[g.point] * scale
    return np.einsum("nkj,nj->nk", g.survey, moves)


def survey_sigma(point_sigma: np.ndarray, model: ErrorModel) -> np.ndarray:
    """(N, 3) m: each observation's survey sigma along x, y, z, its point's own (point_sigma (N, 3),
    NaN where not given) or else the model's survey terms (horizontal, vertical)."""
    model_sigma = np.array([model.si("survey"), model.si("survey"), model.si("survey_vertical")])
    return np.where(np.isnan(point_sigma), model_sigma, np.nan_to_num(point_sigma))


def model_draw(geometry: Geometry, model: ErrorModel, rng: np.random.Generator,
               calibration: list[np.ndarray] | None = None) -> np.ndarray:
    """Errors (N, 2) rad of one Gaussian draw of every component of `model`, as `frame_covariances`
    propagates them: per (frame, camera) one rotation of sigma hypot(jitter, mounting), a point's
    survey error at its `sigma_m` where given; calibration: `calibration_errors(geometry)`, if
    already computed."""
    g = geometry
    errors = unit_draw(g, "pixel", rng, gaussian=True) * model.si("pixel")
    errors += unit_draw(g, "jitter", rng, gaussian=True) * np.hypot(model.si("jitter"), model.si("mounting"))
    errors += unit_draw(g, "focal", rng, gaussian=True) * model.si("focal")
    errors += _survey_draw(g, lambda *shape: rng.normal(size=shape), survey_sigma(g.point_sigma, model))
    axes = calibration_errors(g) if calibration is None else calibration
    for axis in axes:
        errors += axis * rng.normal() * model.si("calibration")
    return errors


def calibration_errors(geometry: Geometry) -> list[np.ndarray]:
    """Errors (N, 2) rad of the calibration along each principal axis of its covariance, scaled by its
    standard deviation: their statistics sum to the term's expectation (the axes are independent)."""
    g = geometry
    k_all = g.calibration.shape[2]
    values, vectors = np.linalg.eigh(g.calibration_covariance)
    out = []
    for value, vector in zip(values, vectors.T):
        if value > 1e-12 * max(values.max(), 0.0) and value > 0:
            per_camera = (vector * np.sqrt(value)).reshape(-1, k_all)  # (C, K)
            out.append(np.einsum("nkj,nj->nk", g.calibration, per_camera[g.camera]))
    return out


def estimate(geometry: Geometry, settings: dict[str, float] | None = None, fallback_pixel_px: float = np.nan,
             seed: int = 0, priors: dict[str, float] | None = None) -> ErrorModel:
    """The ErrorModel of these frames' residuals (module docstring). settings: {component: sigma}
    in UNITS fixing those components (None or NaN entries are estimated); the calibration factor
    is 1 unless set. priors: {component: sigma} in UNITS for the free components the residuals
    cannot tell (not estimable, not significant): that sigma (at most the data's bound) instead of
    0 in the model, source 'prior'. With
    fewer than MIN_DEGREES_OF_FREEDOM the free components are not estimable: their prior or 0, the
    pixel noise fallback_pixel_px where finite (the calibration's). That is also the free pixel
    noise's floor: an estimate below it (0 where the camera rotations take all of a few frames'
    residuals) gives way to it, source 'calibration', the others kept as estimated (estimated
    again with it, an 8-frame group's rotations fell below significance)."""
    g = geometry
    settings = {k: v for k, v in (settings or {}).items() if v is not None and np.isfinite(v)}
    settings.setdefault("calibration", 1.0)
    priors = {k: float(v) for k, v in (priors or {}).items() if k not in settings}
    if "survey" in settings:  # a survey sigma set alone is that of every axis
        settings.setdefault("survey_vertical", settings["survey"])
    tied = "survey_vertical" not in settings  # one survey sigma for all three axes (module docstring)
    modelled = [name for name in RANDOM if not (tied and name == "survey_vertical")]
    free = [name for name in modelled if name not in settings]
    source = {name: "set" for name in settings}
    sigma = {name: float(settings.get(name, 0.0)) for name in COMPONENTS}
    if g.dof < MIN_DEGREES_OF_FREEDOM:
        for name in free:
            sigma[name], source[name] = (priors[name], "prior") if name in priors else (0.0, "not estimable")
        if "pixel" in free and np.isfinite(fallback_pixel_px):
            sigma["pixel"], source["pixel"] = float(fallback_pixel_px), "calibration"
        return _tied(ErrorModel(sigma, source, g.dof), tied)
    statistics = Statistics(g)
    rng = np.random.default_rng(seed)
    expected, visible = {}, {}
    for name in modelled:
        errors = [_component_draw(g, name, rng, tied) for _ in range(DRAWS)]
        expected[name] = np.mean([statistics(solve_response(g, e)) for e in errors], axis=0)
        raw = np.mean([np.sum((e * g.focal[:, None]) ** 2) for e in errors])
        visible[name] = expected[name].sum() / raw if raw > 0 else 0.0
    axes = calibration_errors(g)
    known = sum((statistics(solve_response(g, e)) for e in axes), np.zeros(len(Statistics.NAMES))) \
        * settings["calibration"] ** 2
    if np.isfinite(g.point_sigma).any():
        known += np.mean([statistics(solve_response(g, fixed_survey_draw(g, rng)))
                          for _ in range(DRAWS)], axis=0)
    for name in modelled:
        if name in settings:
            known += expected[name] * (settings[name] * _TO_SI[name]) ** 2
    observed = statistics(g.residual)
    total = observed.sum()
    estimable = [name for name in free if visible[name] > MIN_VISIBLE]

    def untold(name: str, why: str, upper: float = np.inf) -> None:
        """0 for the estimation; its prior, at most the data's bound `upper` (UNITS), for the sigmas."""
        sigma[name], source[name] = (min(priors[name], upper), "prior") if name in priors else (0.0, why)

    for name in free:
        if name not in estimable:
            untold(name, "not estimable")
    variances, weight, null_spreads = [], None, {}
    calibration = [a * settings["calibration"] for a in axes]
    while estimable:
        design = np.column_stack([expected[name] for name in estimable])
        if weight is None:  # each statistic weighted by its spread under the first fit of every component
            scale = 1.0 / np.maximum(observed, MIN_EFFECT * total)
            first = nnls(design * scale[:, None], (observed - known) * scale)[0]
            fitted = {**dict(zip(estimable, first)), **{name: (settings[name] * _TO_SI[name]) ** 2
                                                         for name in modelled if name in settings}}
            weight = 1.0 / np.maximum(_spread(g, statistics, fitted, rng, tied, calibration), MIN_EFFECT * total)
        variances = nnls(design * weight[:, None], (observed - known) * weight)[0]
        information = (design * weight[:, None]).T @ (design * weight[:, None])
        fitted_errors = np.sqrt(np.clip(np.diag(np.linalg.pinv(information)), 0.0, None))

        def null_error(k: int) -> float:
            """The standard error of estimable[k]'s variance were it absent (`_null_error`)."""
            name = estimable[k]
            if name not in null_spreads:
                null_spreads[name] = _spread(g, statistics, {**fitted, name: 0.0}, rng, tied, calibration)
            return _null_error(design, weight, np.maximum(null_spreads[name], MIN_EFFECT * total), k)

        # significant under the fit with it is significant (its own draws only widen the spread);
        # the others are tested against their absence
        errors = {k: null_error(k) for k, name in enumerate(estimable)
                  if name != "pixel" and variances[k] < SIGNIFICANCE * fitted_errors[k]}
        weak = [k for k, e in errors.items() if variances[k] < SIGNIFICANCE * e]
        if not weak:
            break
        # the least significant one is taken as absent, the others estimated again without it
        k = min(weak, key=lambda k: variances[k] / errors[k])
        name = estimable.pop(k)  # its data bound: the estimate plus SIGNIFICANCE standard errors
        untold(name, "not significant", np.sqrt(variances[k] + SIGNIFICANCE * errors[k]) / _TO_SI[name])
    for name, variance in zip(estimable, variances if estimable else []):
        sigma[name], source[name] = float(np.sqrt(variance)) / _TO_SI[name], "estimated"
    if "pixel" in free and sigma["pixel"] < fallback_pixel_px:
        sigma["pixel"], source["pixel"] = float(fallback_pixel_px), "calibration"
    return _tied(ErrorModel(sigma, source, g.dof), tied)


def _null_error(design: np.ndarray, weight: np.ndarray, null_spread: np.ndarray, k: int) -> float:
    """The standard error of the k-th variance of the weighted fit (design (S, m) of the S
    statistics' expectations per unit variance, weight (S,)) were its component absent: the
    sandwich M diag((weight null_spread)^2) M^T, M the fit's map from weighted statistics to
    variances, null_spread (S,) the statistics' spread under the first fit without the component.
    The test of a component is against its absence: under the first fit with it, a large
    component's own draws make its statistic's spread as large as its value (one group's mounting is
    a chi-square of 3 (K - 1) degrees of freedom), so that a 2' change was never significant."""
    weighted = design * weight[:, None]
    M = np.linalg.pinv(weighted.T @ weighted) @ weighted.T
    return float(np.sqrt(max(M[k] ** 2 @ (weight * null_spread) ** 2, 0.0)))


def _component_draw(g: Geometry, name: str, rng: np.random.Generator, tied: bool,
                    gaussian: bool = False) -> np.ndarray:
    """unit_draw of component `name`; with `tied` the survey's moves all three axes."""
    errors = unit_draw(g, name, rng, gaussian)
    if tied and name == "survey":
        errors = errors + unit_draw(g, "survey_vertical", rng, gaussian)
    return errors


def _tied(model: ErrorModel, tied: bool) -> ErrorModel:
    """model with, if tied, the vertical survey term the horizontal one, from the same source."""
    if not tied:
        return model
    name = "survey_vertical"
    return ErrorModel({**model.sigma, name: model.sigma["survey"]}, {**model.source, name: model.source["survey"]},
                      model.dof)


def _spread(g: Geometry, statistics: Statistics, variances: dict[str, float], rng, tied: bool,
            calibration: list[np.ndarray]) -> np.ndarray:
    """(5,) the standard deviations of the statistics under the model `variances` (SI) with the
    known terms (calibration: its error (N, 2) along each axis, `calibration_errors`; the points'
    given survey sigmas), by drawing all together DRAWS times (Gaussian, as the errors are taken to
    be). The known terms' draws count: the calibration is one draw for the whole flight, and its
    camera rotations look like a group's mounting, so its spread is that estimate's uncertainty."""
    samples = []
    for _ in range(DRAWS):
        errors = sum(_component_draw(g, name, rng, tied, gaussian=True) * np.sqrt(v) for name, v in variances.items())
        errors = errors + sum(axis * rng.normal() for axis in calibration) + \
            _survey_draw(g, lambda *shape: rng.normal(size=shape), np.nan_to_num(g.point_sigma))
        samples.append(statistics(solve_response(g, errors)))
    return np.std(samples, axis=0, ddof=1)


# ------------------------------------------------------------------------------ propagation

def frame_covariances(geometry: Geometry, model: ErrorModel) -> dict[str, np.ndarray]:
    """{component: (F, 6, 6)} each component's covariance of a frame's (omega, delta_t) (the
    parametrisation of uncertainty.py, about the frame's point centroid)."""
    g = geometry
    n_frames = g.n_frames
    n_cameras = int(g.camera.max()) + 1 if len(g.camera) else 1
    frame_camera = _dense(g.frame * n_cameras + g.camera)
    block_frame = np.zeros(int(frame_camera.max()) + 1 if len(frame_camera) else 0, int)
    block_frame[frame_camera] = g.frame
    point_sigma = survey_sigma(g.point_sigma, model)
    # one compiled pass over the rows w_i J_i: the per-observation terms' sums per frame, the rotation's
    # and focal change's per (frame, camera) block, the calibration's per frame in its camera's columns
    pixel, survey, vertical, rotation_blocks, focal_blocks, L = covariance_sums(
        g.J, g.weight, g.focal, g.survey, point_sigma, g.rotation, g.focal_effect, g.calibration, g.frame,
        frame_camera, g.camera, n_frames, len(block_frame), g.calibration_covariance.shape[0] // g.calibration.shape[2],
        model.si("pixel") ** 2)

    def per_block(blocks, sigma):  # sum over blocks of L L^T, L = sum over the block's rows of w J^T E_i sigma
        return block_outer_sums(blocks, sigma, block_frame, n_frames)

    rotation_sigma = np.hypot(model.si("jitter"), model.si("mounting"))
    moving = np.where(np.bincount(frame_camera, g.reference, minlength=len(block_frame)) > 0, 0.0, rotation_sigma)
    covariances = {
        "pixel": pixel,
        "survey": survey,
        "survey_vertical": vertical,
        "rotation": per_block(rotation_blocks, np.repeat(moving[:, None], 3, axis=1)),
        "focal": per_block(focal_blocks, np.full((len(block_frame), 1), model.si("focal"))),
        # L K L^T, L (F, 6, K C) the frame's sums of w J^T C_i in its camera's columns
        "calibration": L @ g.calibration_covariance @ np.swapaxes(L, 1, 2) * model.si("calibration") ** 2,
    }
    rotation = covariances.pop("rotation")
    share = model.si("jitter") ** 2 / rotation_sigma**2 if rotation_sigma > 0 else 0.0
    covariances["jitter"], covariances["mounting"] = rotation * share, rotation * (1.0 - share)
    return {name: g.A_inverse @ covariances[name] @ g.A_inverse for name in COMPONENTS}
