"""Intrinsic calibration from a 3D (or planar) calibration field: the paper's procedure and baselines.

Paper, section "Intrinsic Calibration" (eq. 2-3 model, eq. `refine`):

1. priors d = 0, fx = fy = f, principal point at the image centre, ((W - 1) / 2, (H - 1) / 2) with
   the centre of the top-left pixel at (0, 0) (the paper's W/2, H/2 counts from the pixel corner);
2. PnPf per calibration image (pose + f; `calib.pnpf.solve_pnpf`), then the mean f; on a flat field
   (every control point of the camera's images on one plane, `calib.planar.plane_frame`) the views'
   homographies instead (`calib.planar.planar_start`, Zhang's closed form as cv2.initCameraMatrix2D's),
   where a view nearly parallel to the image plane weighs next to nothing rather than spoiling the mean;
3. PnP per image with the mean f;
4. Levenberg-Marquardt jointly over fx, fy, cx, cy, d and all image poses (eq. `refine`),
   scipy.optimize.least_squares with an analytic Jacobian.

The same procedure calibrates a camera of OpenCV's model (`model="opencv"`, camera.py): its
distortion (k1, k2, p1, p2, k3) starts at zero as d does and the LM runs over all nine parameters.

Evaluation as the paper's tab:intrinsics: eps_calib is the RMS of the per-point reprojection
distance over the calibration images; eps_eval the same over the held-out images after
re-estimating only their poses with the intrinsics fixed. Parameter standard deviations come from
the covariance (J^T J)^-1 sigma^2, sigma^2 = SSR / (2 n_obs - n_params).

Baselines (the intrinsics stage writes them to tables/intrinsics.csv beside "ours"):
- `opencv`: cv2.calibrateCamera with the camera's model (radial1: k1 = d alone; opencv: its default
  model), seeded with the image centre and a nominal focal length (a non-planar field needs
  CALIB_USE_INTRINSIC_GUESS); a flat field is given in its plane's coordinates (z = 0) without a
  guess, so that OpenCV starts on its own (cv2.initCameraMatrix2D), as its users run it;
- `dlt_lm`: Bouguet/Tsai-style, full intrinsics from a per-image normalized DLT (H&Z alg. 7.1,
  K from the RQ decomposition of P[:, :3], averaged over images), then the same LM (a 3-D field
  only: the DLT of a flat one does not determine K, and the baseline is refused by name).
Every method's eps_eval is computed by the same pose-only estimation on the eval images.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from ..camera import PARAMETER_NAMES, Camera, OneToOneRegion, image_centre, project_unmasked
from ..errors import DmaisError
from ..geometry import Rigid3, exp_so3, pose_jacobian
from .planar import plane_frame, planar_start
from .pnpf import solve_pnpf
from .survey_variance import estimate as estimate_survey_variance
from .survey_variance import inverse_normal

log = logging.getLogger(__name__)

MIN_OBSERVATIONS_PER_IMAGE = 5
MIN_CALIB_IMAGES = 2
#: PnPf focal lengths within this fraction of their median count as agreeing (the rest are dropped
#: from the mean); fewer than half agreeing means the mean would rest on outliers.
PNPF_AGREEMENT = 0.2
METHODS = ("ours", "opencv", "dlt_lm")
#: cv2.calibrateCamera's flags that hold the coefficients a model lacks (radial1: all but k1).
OPENCV_FIXED_FLAGS = {
    "radial1": (cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4
                | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6),
    "opencv": 0,
}


def table_columns(model: str = "radial1") -> tuple[str, ...]:
    """The columns of <camera>.methods.csv for a camera of `model` (radial1: TABLE_COLUMNS)."""
    return ("method", "camera", *PARAMETER_NAMES[model], "eps_calib_px", "eps_eval_px")


#: The columns of a radial1 camera's methods.csv and of the paper's tables/intrinsics.csv.
TABLE_COLUMNS = table_columns()


@dataclass
class IntrinsicsResult:
    """Calibrated camera, its uncertainty and the reprojection errors of one camera."""

    name: str
    camera: Camera
    std: dict[str, float]
    eps_calib_px: float
    eps_eval_px: float | None
    n_images: int
    n_observations: int
    poses: dict[str, Rigid3] = field(default_factory=dict)  # cam_from_world of the calib images
    eval_poses: dict[str, Rigid3] = field(default_factory=dict)
    pnpf_focal_px: dict[str, float] = field(default_factory=dict)
    skipped_images: list[str] = field(default_factory=list)
    method: str = "ours"
    image_eps_px: dict[str, float] = field(default_factory=dict)  # RMS per calibration image
    eval_image_eps_px: dict[str, float] = field(default_factory=dict)  # RMS per held-out image
    #: image -> (n, 2) residuals projected minus observed (px) of its usable observations, in input
    #: order: the calibration images' from the final LM, the held-out images' from their pose-only fit.
    image_residuals_px: dict[str, np.ndarray] = field(default_factory=dict)
    #: point id -> (P, 3) the change of the camera's P parameters (`Camera.parameter_names`) per
    #: one-sigma survey error of the control point along x, y, z (its share of the covariance behind
    #: `std`; empty where no sigma is given).
    survey_effect: dict[str, np.ndarray] = field(default_factory=dict)
    #: the control points' survey sigma per axis (m) estimated from the calibration's residuals
    #: (`survey_variance`) where the dataset gives none (`sigma_m` empty or absent), and the effects
    #: of those points made with it; None where every point's sigma is given (or the points are exact)
    survey_sigma_m: float | None = None
    #: (P, P) the pixel noise's share of the parameters' covariance (the covariance behind `std` less
    #: the survey effects' outer products), correlations included: the rig's calibration covariance
    #: takes it whole (fx and fy move together, cx with a rotation of the camera); None: not known
    pixel_covariance: np.ndarray | None = None
    #: where the model folds inside the image: the part of it where the model is one-to-one, and per
    #: image (calibration and held-out) the largest `Camera.fold_reach` of its fitted points' rays
    one_to_one: OneToOneRegion | None = None
    fold_reach: dict[str, float] = field(default_factory=dict)

    def worst_images(self, count: int = 3) -> list[tuple[str, float]]:
        """The `count` calibration images of largest RMS reprojection distance, worst first."""
        return sorted(self.image_eps_px.items(), key=lambda item: -item[1])[:count]

    def to_dict(self) -> dict:
        """The RESULTS/intrinsics/<camera>.json layout of docs/design.md: the camera's parameters as
        `Camera.to_dict` names them (radial1: fx, fy, cx, cy, d; opencv: "model" and fx .. k3), so
        that `Camera.from_dict` reads the record back."""
        cam = self.camera
        model = {} if cam.model == "radial1" else {"model": cam.model}
        return {
            "camera": self.name, **model, "width": cam.width, "height": cam.height, **self._parameters(),
            "std": {k: float(v) for k, v in self.std.items()},
            "survey_effect": {k: np.asarray(v, dtype=float).tolist() for k, v in self.survey_effect.items()},
            "survey_sigma_estimated_m": None if self.survey_sigma_m is None else float(self.survey_sigma_m),
            **({} if self.pixel_covariance is None else
               {"pixel_covariance": np.asarray(self.pixel_covariance, dtype=float).tolist()}),
            "eps_calib_px": float(self.eps_calib_px),
            "eps_eval_px": None if self.eps_eval_px is None else float(self.eps_eval_px),
            "n_images": int(self.n_images), "n_observations": int(self.n_observations),
            "method": self.method,
            "n_eval_images": len(self.eval_poses),
            "skipped_images": list(self.skipped_images),
            "pnpf_focal_px": {k: float(v) for k, v in self.pnpf_focal_px.items()},
            "image_eps_calib_px": {k: float(v) for k, v in self.image_eps_px.items()},
            "image_eps_eval_px": {k: float(v) for k, v in self.eval_image_eps_px.items()},
            "poses": {k: p.to_dict() for k, p in self.poses.items()},
            "eval_poses": {k: p.to_dict() for k, p in self.eval_poses.items()},
            **({} if self.one_to_one is None else
               {"one_to_one": {**self.one_to_one.to_dict(), "observed_reach": max(self.fold_reach.values())}}),
        }

    def table_row(self) -> dict:
        """The row of <camera>.methods.csv (`table_columns(camera.model)`)."""
        return {"method": self.method, "camera": self.name, **self._parameters(), "eps_calib_px": self.eps_calib_px,
                "eps_eval_px": np.nan if self.eps_eval_px is None else self.eps_eval_px}

    def _parameters(self) -> dict[str, float]:
        """The camera's parameters by name (`Camera.parameter_names`)."""
        return dict(zip(self.camera.parameter_names, map(float, self.camera.parameters)))


# ------------------------------------------------------------------------------ input checks


def _as_mapping(data, what: str) -> dict:
    if data is None:
        return {}
    if isinstance(data, Mapping):
        return dict(data)
    if isinstance(data, Sequence) or isinstance(data, np.ndarray):
        return {str(k): v for k, v in enumerate(data)}
    raise DmaisError(f"{what} must be a mapping image -> array or a list of arrays")


def _prepare(points_per_image, uv_per_image, camera: str, split: str,
             skipped: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{image: (X (n, 3), uv (n, 2))} checked; images with < 5 observations appended to `skipped`."""
    points = _as_mapping(points_per_image, f"camera {camera}: {split} points")
    pixels = _as_mapping(uv_per_image, f"camera {camera}: {split} pixels")
    if set(points) != set(pixels):
        raise DmaisError(f"camera {camera}: {split} points and pixels name different images")
    data = {}
    for image in points:
        X = np.asarray(points[image], dtype=float)
        uv = np.asarray(pixels[image], dtype=float)
        if X.ndim != 2 or X.shape[1] != 3 or uv.shape != (len(X), 2):
            raise DmaisError(f"camera {camera}, image {image}: expected points (n, 3) and pixels (n, 2), "
                             f"got {X.shape} and {uv.shape}")
        bad = ~(np.isfinite(X).all(axis=1) & np.isfinite(uv).all(axis=1))
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise DmaisError(f"camera {camera}, image {image}: observation {row} is not finite "
                             f"(point {X[row].tolist()}, pixel {uv[row].tolist()})")
        if len(X) < MIN_OBSERVATIONS_PER_IMAGE:
            skipped.append(str(image))
            continue
        data[str(image)] = (X, uv)
    return data


# ------------------------------------------------------------------------------ least squares


def _rms(residuals: np.ndarray) -> float:
    """RMS of per-point reprojection distances from stacked (u, v) residuals."""
    r = np.asarray(residuals).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else float("nan")


def refine_pose(camera: Camera, X: np.ndarray, uv: np.ndarray, pose: Rigid3) -> tuple[Rigid3, np.ndarray]:
    """LM over one cam_from_world with intrinsics fixed; returns (pose, residuals (n, 2))."""
    R0 = pose.R

    def fun(p):
        return (project_unmasked(X @ (exp_so3(p[:3]) @ R0).T + p[3:], camera) - uv).ravel()

    def jac(p):
        R = exp_so3(p[:3]) @ R0
        _, J_cam, _ = project_unmasked(X @ R.T + p[3:], camera, jacobian=True)
        return pose_jacobian(X, R, p[:3], J_cam).reshape(-1, 6)

    sol = least_squares(fun, np.concatenate([np.zeros(3), pose.t]), jac=jac, method="lm",
                        x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100)
    return Rigid3(exp_so3(sol.x[:3]) @ R0, sol.x[3:]), sol.fun.reshape(-1, 2)


def estimate_pose(camera: Camera, X: np.ndarray, uv: np.ndarray, guess: Rigid3 | None = None) -> tuple[Rigid3, np.ndarray]:
    """PnP with known intrinsics: SQPnP on undistorted normalized points, then LM on pixels.

    Returns (cam_from_world, residuals (n, 2)). `guess` (e.g. a PnPf pose) is polished as well and
    the better of the two kept.
    """
    xy = camera.undistort_normalized(uv)
    ok = np.isfinite(xy).all(axis=1)
    candidates = [] if guess is None else [guess]
    if ok.sum() >= 4:
        try:
            success, rvec, tvec = cv2.solvePnP(X[ok].astype(np.float64), xy[ok].astype(np.float64), np.eye(3),
                                               None, flags=cv2.SOLVEPNP_SQPNP)
            if success:
                candidates.append(Rigid3(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        except cv2.error as error:
            log.debug("SQPnP failed: %s", error)
    best = None
    for pose in candidates:
        refined, residuals = refine_pose(camera, X, uv, pose)
        if np.all(np.isfinite(residuals)) and (best is None or _rms(residuals) < _rms(best[1])):
            best = (refined, residuals)
    if best is None:
        raise DmaisError("pose estimation failed")
    return best


def bundle_adjust(camera: Camera, poses: dict[str, Rigid3], data: dict[str, tuple[np.ndarray, np.ndarray]],
                  survey: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None):
    """LM over the camera model's parameters (radial1: fx, fy, cx, cy, d) and every pose (eq. `refine`).

    survey: {image: (point ids (n,), survey sigma per axis (n,) m)} of each image's points, for the
    covariance (`_covariance`); None or sigma 0: exact points; NaN: a sigma not given, estimated from
    the residuals (`survey_variance`, one for all such points). Returns (camera, poses, residuals
    (N, 2), covariance of the intrinsics (P, P), survey effect {point id: (P, 3)}: the change of
    the intrinsics per one-sigma survey error of the point along x, y, z; P parameters of the model,
    the estimated survey sigma (m) or None where none was to be estimated).
    """
    names = list(data)
    R0 = [poses[k].R for k in names]
    sizes = [len(data[k][0]) for k in names]
    rows = np.cumsum([0] + [2 * s for s in sizes])
    P = len(camera.parameter_names)
    n_params = P + 6 * len(names)
    x0 = np.concatenate([camera.parameters] + [np.concatenate([np.zeros(3), poses[k].t]) for k in names])

    def fun(p):
        out = np.empty(rows[-1])
        for i, k in enumerate(names):
            X, uv = data[k]
            q = p[P + 6 * i: P + 6 + 6 * i]
            Xc = X @ (exp_so3(q[:3]) @ R0[i]).T + q[3:]
            out[rows[i]:rows[i + 1]] = (project_unmasked(Xc, camera.with_parameters(p[:P])) - uv).ravel()
        return out

    def jac(p):
        J = np.zeros((rows[-1], n_params))
        for i, k in enumerate(names):
            X, _ = data[k]
            q = p[P + 6 * i: P + 6 + 6 * i]
            R = exp_so3(q[:3]) @ R0[i]
            _, J_cam, J_intr = project_unmasked(X @ R.T + q[3:], camera.with_parameters(p[:P]), jacobian=True)
            J[rows[i]:rows[i + 1], :P] = J_intr.reshape(-1, P)
            J[rows[i]:rows[i + 1], P + 6 * i: P + 6 + 6 * i] = pose_jacobian(X, R, q[:3], J_cam).reshape(-1, 6)
        return J

    sol = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                        max_nfev=200)
    p = sol.x
    fitted = camera.with_parameters(p[:P])
    new_poses = {k: Rigid3(exp_so3(p[P + 6 * i: P + 3 + 6 * i]) @ R0[i], p[P + 3 + 6 * i: P + 6 + 6 * i])
                 for i, k in enumerate(names)}
    J = jac(p)
    ids, sigma, unit = _survey_jacobian(fitted, p[P:], names, R0, data, survey or {})
    sigma, estimated = _with_estimated_sigma(J, sol.fun, unit, sigma)
    cov, effect = _covariance(J, sol.fun, unit * np.repeat(sigma, 3))
    return (fitted, new_poses, sol.fun.reshape(-1, 2), cov[:P, :P],
            {str(point): effect[:P, 3 * k:3 * k + 3] for k, point in enumerate(ids)}, estimated)


def _with_estimated_sigma(J: np.ndarray, residuals: np.ndarray, unit: np.ndarray, sigma: np.ndarray
                          ) -> tuple[np.ndarray, float | None]:
    """The points' survey sigmas (P,) with those not given (NaN) estimated from the residuals
    (`survey_variance.estimate`; J (2N, n), residuals (2N,), unit (2N, 3P) per metre of each point's
    error), and that estimate (None where every sigma was given)."""
    unknown = np.isnan(sigma)
    if not unknown.any():
        return sigma, None
    columns = np.repeat(unknown, 3)
    given = unit[:, ~columns] * np.repeat(sigma[~unknown], 3)
    found = estimate_survey_variance(J, residuals, unit[:, columns], given).survey_sigma
    return np.where(unknown, found, sigma), found


def _survey_jacobian(camera: Camera, pose_parameters: np.ndarray, names: list[str], R0: list[np.ndarray], data,
                     survey) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ids (P,) of the points not taken as exact (survey sigma above 0, or NaN: not given), their
    sigmas (P,) and (2N, 3P) the residuals' change per metre of survey error of each along x, y, z
    (the same point in every image that sees it)."""
    n = sum(len(data[k][0]) for k in names)
    if not survey:
        return np.zeros(0, dtype=str), np.zeros(0), np.zeros((2 * n, 0))
    given = [survey.get(k, (np.full(len(data[k][0]), ""), np.zeros(len(data[k][0])))) for k in names]
    point_ids = np.concatenate([np.asarray(ids, dtype=str) for ids, _ in given])
    sigma = np.concatenate([np.asarray(sigma, dtype=float) for _, sigma in given])
    surveyed = ~(sigma <= 0)  # NaN too
    if not surveyed.any():
        return np.zeros(0, dtype=str), np.zeros(0), np.zeros((2 * n, 0))
    ids, first, point = np.unique(point_ids[surveyed], return_index=True, return_inverse=True)
    rows = np.flatnonzero(surveyed)
    blocks = []
    for i, k in enumerate(names):
        q = pose_parameters[6 * i: 6 + 6 * i]
        R = exp_so3(q[:3]) @ R0[i]
        _, J_cam, _ = project_unmasked(data[k][0] @ R.T + q[3:], camera, jacobian=True)
        blocks.append(J_cam @ R)  # (n, 2, 3): d pixel / d world point
    blocks = np.concatenate(blocks)
    S = np.zeros((2 * n, 3 * len(ids)))
    for row, k in zip(rows, point):
        S[2 * row:2 * row + 2, 3 * k:3 * k + 3] = blocks[row]
    return ids, sigma[rows][first], S


def _covariance(J: np.ndarray, residuals: np.ndarray, survey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (n, n) of the parameters of a least-squares fit with Jacobian J (2N, n) at its
    residuals (2N,): pixel noise of variance s^2 on every residual, plus the control points' survey
    errors `survey` (2N, 3P) (`_survey_jacobian`), the same in every image:

        cov = N^-1 s^2 + N^-1 J^T S S^T J N^-1,  N = J^T J,
        s^2 = (SSR - ||(I - H) S||_F^2) / (2N - n),  H = J N^-1 J^T,

    i.e. the residuals' sum of squares less what the survey errors are expected to put in it; and
    (n, 3P) N^-1 J^T S, the parameters' change per one-sigma survey error of each point and axis."""
    n_params = J.shape[1]
    try:
        inverse = inverse_normal(J)
    except np.linalg.LinAlgError:
        return np.full((n_params, n_params), np.nan), np.full((n_params, survey.shape[1]), np.nan)
    effect = inverse @ (J.T @ survey)  # (n, 3P)
    expected = float(np.sum((survey - J @ effect) ** 2))
    sigma2 = max(float(residuals @ residuals) - expected, 0.0) / max(len(residuals) - n_params, 1)
    return inverse * sigma2 + effect @ effect.T, effect


# ------------------------------------------------------------------------------ the procedure


def _evaluate(camera: Camera, eval_data: dict, name: str
              ) -> tuple[float | None, dict[str, Rigid3], dict[str, np.ndarray]]:
    """eps_eval: pose-only estimation per eval image with `camera` fixed; RMS over all their points.

    Returns (eps_eval, cam_from_world per eval image, residuals (n, 2) per eval image)."""
    if not eval_data:
        return None, {}, {}
    residuals, poses = {}, {}
    for image, (X, uv) in eval_data.items():
        try:
            poses[image], residuals[image] = estimate_pose(camera, X, uv)
        except DmaisError:
            raise DmaisError(f"camera {name}, eval image {image}: pose estimation failed") from None
    return _rms(np.vstack(list(residuals.values()))), poses, residuals


def evaluate(camera: Camera, points_world_per_image, uv_per_image, name: str = "camera") -> float | None:
    """eps_eval of a fixed `camera` (e.g. another tool's calibration) on held-out images, computed as
    `calibrate_camera` computes its own: each image's pose alone fitted, the RMS per-point distance
    over all their points. points_world_per_image / uv_per_image: {image: (n, 3)} / {image: (n, 2)};
    images with fewer than 5 observations are skipped; None when none is left."""
    data = _prepare(points_world_per_image, uv_per_image, name, "eval", [])
    return _evaluate(camera, _shift(data, _centre([data])), name)[0]


def _centre(data_sets) -> np.ndarray:
    points = [X for data in data_sets for X, _ in data.values()]
    return np.vstack(points).mean(axis=0) if points else np.zeros(3)


def _shift(data: dict, centre: np.ndarray) -> dict:
    return {k: (X - centre, uv) for k, (X, uv) in data.items()}


def _world_poses(poses: dict[str, Rigid3], centre: np.ndarray) -> dict[str, Rigid3]:
    """Poses of centred points (X - centre) back to the world: t_world = t - R centre."""
    return {k: Rigid3(p.R, p.t - p.R @ centre) for k, p in poses.items()}


def _load_inputs(points_world_per_image, uv_per_image, eval_points_world_per_image, eval_uv_per_image,
                 name: str, min_images: int, warn: bool = True):
    skipped: list[str] = []
    calib = _prepare(points_world_per_image, uv_per_image, name, "calib", skipped)
    evals = _prepare(eval_points_world_per_image, eval_uv_per_image, name, "eval", skipped)
    if skipped and warn:
        log.warning("camera %s: skipping %d image(s) with fewer than %d observations: %s", name, len(skipped),
                    MIN_OBSERVATIONS_PER_IMAGE, ", ".join(skipped))
    if len(calib) < min_images:
        raise DmaisError(f"camera {name}: {len(calib)} usable calibration image(s) (with at least "
                         f"{MIN_OBSERVATIONS_PER_IMAGE} observations), needs at least {min_images}")
    centre = _centre([calib, evals])
    return _shift(calib, centre), _shift(evals, centre), centre, skipped


def _finish(name, method, camera, poses, residuals, cov, calib, evals, centre, skipped, pnpf_focal=None,
            survey_effect=None, survey_sigma_m=None):
    eps_eval, eval_poses, eval_residuals = _evaluate(camera, evals, name)
    std = dict(zip(camera.parameter_names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist()))
    effects = [np.asarray(e, dtype=float) for e in (survey_effect or {}).values()]
    pixel_covariance = np.asarray(cov, dtype=float) - sum((e @ e.T for e in effects), np.zeros_like(cov))
    ends = np.cumsum([len(X) for X, _ in calib.values()])[:-1]  # residuals are stacked in calib's order
    calib_residuals = dict(zip(calib, np.split(np.asarray(residuals).reshape(-1, 2), ends)))
    folds = camera.model != "radial1" and camera.folds_in_image
    return IntrinsicsResult(
        name=name, camera=camera, std=std, eps_calib_px=_rms(residuals), eps_eval_px=eps_eval,
        n_images=len(calib), n_observations=sum(len(X) for X, _ in calib.values()),
        poses=_world_poses(poses, centre), eval_poses=_world_poses(eval_poses, centre),
        pnpf_focal_px=pnpf_focal or {}, skipped_images=skipped, method=method,
        image_eps_px={k: _rms(r) for k, r in calib_residuals.items()},
        eval_image_eps_px={k: _rms(r) for k, r in eval_residuals.items()},
        image_residuals_px={**calib_residuals, **eval_residuals}, survey_effect=survey_effect or {},
        survey_sigma_m=survey_sigma_m, pixel_covariance=pixel_covariance,
        one_to_one=camera.one_to_one_region() if folds else None,
        fold_reach=_fold_reach(camera, {**poses, **eval_poses}, {**calib, **evals}) if folds else {})


def _fold_reach(camera: Camera, poses: dict[str, Rigid3], data: dict) -> dict[str, float]:
    """image -> the largest `Camera.fold_reach` of its points (n, 3) as its fitted pose sees them."""
    reach = {}
    for image, (X, _) in data.items():
        if image in poses:
            points = poses[image].apply(X)
            reach[image] = float(camera.fold_reach(points[:, :2] / points[:, 2:]).max())
    return reach


def calibrate_camera(points_world_per_image, uv_per_image, width: int, height: int, *,
                     eval_points_world_per_image=None, eval_uv_per_image=None, name: str = "camera",
                     min_images: int = MIN_CALIB_IMAGES, survey=None, model: str = "radial1") -> IntrinsicsResult:
    """The paper's intrinsic calibration of one camera (priors, PnPf, mean f, PnP, LM over everything)
    with the lens model `model` (camera.MODELS), whose distortion starts at zero.

    points_world_per_image / uv_per_image: {image: (n, 3)} and {image: (n, 2)} (or lists) of the
    calibration images; the eval_* pair likewise for held-out images (eps_eval; optional);
    survey {image: (point ids (n,), survey sigma (n,) m)} of the calibration images' points, for
    the intrinsics' covariance (`bundle_adjust`; None: exact).
    Images with fewer than 5 observations are skipped with one warning. Raises DmaisError naming
    the camera when fewer than `min_images` calibration images are usable.
    """
    calib, evals, centre, skipped = _load_inputs(points_world_per_image, uv_per_image,
                                                 eval_points_world_per_image, eval_uv_per_image, name, min_images)
    principal = image_centre(width, height)
    if plane_frame(np.vstack([X for X, _ in calib.values()])) is not None:
        pnpf, focal = {}, {}
        f0 = planar_start(calib, principal, name).focal_px
        log.info("camera %s: a flat field; its views' homographies give the focal length %.1f px", name, f0)
    else:
        pnpf, focal, f0 = _pnpf_start(calib, principal, name)
    camera0 = Camera(fx=f0, fy=f0, cx=principal[0], cy=principal[1], d=0.0, width=width, height=height, model=model)
    poses = {}
    for image, (X, uv) in calib.items():
        try:
            poses[image], _ = estimate_pose(camera0, X, uv, guess=pnpf.get(image))
        except DmaisError:
            raise DmaisError(f"camera {name}, image {image}: PnP failed") from None
    camera, poses, residuals, cov, effect, estimated = bundle_adjust(camera0, poses, calib, survey)
    result = _finish(name, "ours", camera, poses, residuals, cov, calib, evals, centre, skipped, focal, effect,
                     estimated)
    log.info("camera %s: %s, eps_calib %.4f px, eps_eval %s px", name, describe(camera), result.eps_calib_px,
             "n/a" if result.eps_eval_px is None else f"{result.eps_eval_px:.4f}")
    return result


def _pnpf_start(calib: dict, principal: np.ndarray, name: str
                ) -> tuple[dict[str, Rigid3], dict[str, float], float]:
    """The paper's start on a 3-D field: PnPf per image ({image: cam_from_world}, {image: f}) and
    the mean f of those that agree (`_mean_focal`)."""
    pnpf, focal = {}, {}
    for image, (X, uv) in calib.items():
        try:
            pnpf[image], focal[image] = solve_pnpf(X, uv, principal)
        except DmaisError as error:
            log.warning("camera %s, image %s: PnPf failed (%s); its pose comes from PnP only", name, image, error)
    if not focal:
        raise DmaisError(f"camera {name}: PnPf failed on every calibration image; cannot initialize the focal length")
    f0 = _mean_focal(focal, name)
    log.info("camera %s: PnPf focal lengths %s px, mean %.1f px", name,
             ", ".join(f"{v:.1f}" for v in focal.values()), f0)
    return pnpf, focal, f0


def describe(camera: Camera, first: int = 0) -> str:
    """The camera's parameters from the `first`-th on, as the log shows them: focal lengths and
    principal point to 0.1 px, radial1's d to 4 decimals (as ever), opencv's k1 .. k3 to 4
    significant digits (the whole camera's text starts with its model)."""
    distortion = ".4f" if camera.model == "radial1" else ".4g"
    text = " ".join(f"{name} {value:{'.1f' if k < 4 else distortion}}"
                    for k, (name, value) in enumerate(zip(camera.parameter_names, camera.parameters)) if k >= first)
    return text if camera.model == "radial1" or first else f"model {camera.model}: {text}"


def _mean_focal(focal: dict[str, float], name: str) -> float:
    """The paper's mean of the per-image PnPf focal lengths, without gross failures (> PNPF_AGREEMENT
    from the median, e.g. a planar view nearly parallel to the image plane) so that one bad view
    cannot spoil it; a mean that fewer than half of the images support is refused."""
    values = np.array(list(focal.values()))
    keep = np.abs(values / np.median(values) - 1.0) < PNPF_AGREEMENT
    if 2 * keep.sum() < len(values) or not keep.any():
        listed = ", ".join(f"{image} {f:.0f}" for image, f in focal.items())
        raise DmaisError(f"camera {name}: the PnPf focal lengths disagree, only {int(keep.sum())} of {len(values)} "
                         f"images lie within {PNPF_AGREEMENT:.0%} of their median ({listed} px); check these "
                         "images' observations and point ids")
    return float(values[keep].mean())


@dataclass(frozen=True)
class Plausibility:
    """Bounds beyond which a calibration is absurd and is refused rather than written.

    max_eps_calib_px: RMS reprojection distance over the calibration images (the paper reaches
    0.2-0.45 px; tens of times the marker noise means wrong observations). max_focal_deviation:
    relative distance of fx and fy from the manifest's focal_px (when given) and of fx from fy.
    Besides these bounds `check_plausible` refuses an opencv-model distortion that folds back where
    the observations are: the fitted ray of no observation of the calibration or held-out images may
    lie beyond 1 - fold_margin of the fold's undistorted radius (`Camera.fold_reach`); one folding
    only beyond them (real wide-angle lenses' polynomials turn in the image corners no board reached)
    is accepted with a warning giving its one-to-one region. radial1 is spared that check: its one coefficient cannot follow a wide-angle lens to
    the image corners without turning there (OpenCV's left*.jpg sample fits to 0.45 px with d = -0.26
    yet folds in the corners), and the paper's results must not change.
    """

    max_eps_calib_px: float = 5.0
    max_focal_deviation: float = 0.2
    fold_margin: float = 0.1


def check_plausible(result: IntrinsicsResult, focal_px: float | None, limits: Plausibility = Plausibility()) -> None:
    """Raise a DmaisError naming the camera, the fault and its worst images when `result` is absurd."""
    cam, faults = result.camera, []
    if not result.eps_calib_px <= limits.max_eps_calib_px:
        faults.append(f"eps_calib {result.eps_calib_px:.3g} px exceeds {limits.max_eps_calib_px:g} px")
    for axis, f in (("fx", cam.fx), ("fy", cam.fy)):
        if focal_px and not abs(f / focal_px - 1.0) <= limits.max_focal_deviation:
            faults.append(f"{axis} {f:.1f} px is {abs(f / focal_px - 1.0):.0%} from focal_px {focal_px:g}")
    if not abs(cam.fx / cam.fy - 1.0) <= limits.max_focal_deviation:
        faults.append(f"fx {cam.fx:.1f} and fy {cam.fy:.1f} px differ by more than {limits.max_focal_deviation:.0%}")
    if not (-0.5 <= cam.cx <= cam.width - 0.5 and -0.5 <= cam.cy <= cam.height - 0.5):
        faults.append(f"principal point ({cam.cx:.1f}, {cam.cy:.1f}) lies outside the image")
    faults += _fold_fault(result, limits.fold_margin)
    if faults:
        worst = ", ".join(f"{image} {eps:.3g} px" for image, eps in result.worst_images())
        raise DmaisError(f"camera {result.name}: calibration refused, {'; '.join(faults)} (worst images: {worst}); "
                         "earlier results are kept")


def _fold_fault(result: IntrinsicsResult, margin: float) -> list[str]:
    """The fault of a model that folds back where its observations are (within `margin` of the way to
    the fold); a warning with the one-to-one region where it folds inside the image beyond them."""
    if result.one_to_one is None:
        return []
    cam, region = result.camera, result.one_to_one
    farthest = max(result.fold_reach, key=result.fold_reach.get)
    reach = result.fold_reach[farthest]
    where = f"the farthest observation's ray at {reach:.0%} of the fold's radius, image {farthest}"
    if not reach <= 1.0 - margin:
        return [f"its {cam.model} distortion ({describe(cam, first=4)}) folds back inside the image at the "
                f"observations ({region.describe()}; {where}; limit {1.0 - margin:.0%})"]
    log.warning("camera %s: its %s distortion folds back inside the image, beyond its observations: %s; %s. "
                "Pixels outside it undistort to NaN", result.name, cam.model, region.describe(), where)
    return []


# ------------------------------------------------------------------------------ baselines


def calibrate_camera_opencv(points_world_per_image, uv_per_image, width: int, height: int, focal_guess: float, *,
                            eval_points_world_per_image=None, eval_uv_per_image=None, name: str = "camera",
                            min_images: int = MIN_CALIB_IMAGES, warn_skipped: bool = True,
                            model: str = "radial1") -> IntrinsicsResult:
    """OpenCV baseline: cv2.calibrateCamera seeded with the image centre and `focal_guess` (a
    non-planar field needs CALIB_USE_INTRINSIC_GUESS), with `model`'s coefficients free: radial1
    k1 only, opencv its default model (k1, k2, p1, p2, k3)."""
    calib, evals, centre, skipped = _load_inputs(points_world_per_image, uv_per_image,
                                                 eval_points_world_per_image, eval_uv_per_image, name, min_images,
                                                 warn_skipped)
    names = list(calib)
    frame = plane_frame(np.vstack([X for X, _ in calib.values()]))
    # a flat field in its plane's coordinates (z = 0): OpenCV's own start (initCameraMatrix2D), no guess
    field_from_data = Rigid3.identity() if frame is None else _plane_from_world(*frame)
    object_points = [_on_plane(field_from_data.apply(calib[k][0]), frame).astype(np.float32).reshape(-1, 1, 3)
                     for k in names]
    image_points = [calib[k][1].astype(np.float32).reshape(-1, 1, 2) for k in names]
    cx, cy = image_centre(width, height)
    guess = focal_guess if frame is None else 1.0  # OpenCV replaces it on a flat field
    K0 = np.array([[guess, 0, cx], [0, guess, cy], [0, 0, 1]], dtype=np.float64)
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS if frame is None else 0) | OPENCV_FIXED_FLAGS[model]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # its threads' partial sums, added in the order they finish, moved the result by 1e-8
    try:
        _, K, dist, rvecs, tvecs, std_intr, _, _ = cv2.calibrateCameraExtended(
            object_points, image_points, (width, height), K0, np.zeros(5), flags=flags, criteria=criteria)
    except cv2.error as error:
        raise DmaisError(f"camera {name}: OpenCV calibrateCamera failed: {str(error).strip()}") from None
    finally:
        cv2.setNumThreads(threads)
    camera = opencv_camera(K, dist, width, height, model)
    poses = {k: Rigid3(cv2.Rodrigues(r)[0], t.ravel()) * field_from_data for k, r, t in zip(names, rvecs, tvecs)}
    residuals = np.vstack([project_unmasked(poses[k].apply(calib[k][0]), camera) - calib[k][1] for k in names])
    # OpenCV's order is ours: fx, fy, cx, cy, k1, k2, p1, p2, k3
    cov = np.diag(np.asarray(std_intr).ravel()[:len(camera.parameter_names)] ** 2)
    return _finish(name, "opencv", camera, poses, residuals, cov, calib, evals, centre, skipped)


def _plane_from_world(centre: np.ndarray, axes: np.ndarray) -> Rigid3:
    """plane_from_world of a plane through `centre` (3,) spanned by the unit `axes` (2, 3): x, y along
    them, z along their normal."""
    R = np.vstack([axes, np.cross(axes[0], axes[1])])
    return Rigid3(R, -R @ centre)


def _on_plane(points: np.ndarray, frame) -> np.ndarray:
    """Points (n, 3) in a plane's frame with z set to 0 (OpenCV's planar rig); unchanged where `frame`
    is None (a 3-D field)."""
    return points if frame is None else np.column_stack([points[:, :2], np.zeros(len(points))])


def opencv_camera(K: np.ndarray, distortion: np.ndarray, width: int, height: int, model: str) -> Camera:
    """The Camera of OpenCV's intrinsic matrix K (3, 3) and distortion vector (k1, k2, p1, p2, k3, ...)
    in `model` (radial1 takes k1 alone: calibrate with the others held at zero)."""
    values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(distortion, dtype=float).ravel()[:5]]
    return Camera.from_parameters(model, values[:len(PARAMETER_NAMES[model])], width, height)


def _dlt_intrinsics(X: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """(3, 3) K from a normalized DLT of one image (H&Z alg. 7.1) and the RQ decomposition of P[:, :3]."""
    from scipy.linalg import rq

    if len(X) < 6:
        return None
    c2 = uv.mean(axis=0)
    s2 = np.sqrt(2.0) / np.mean(np.linalg.norm(uv - c2, axis=1))
    T2 = np.array([[s2, 0, -s2 * c2[0]], [0, s2, -s2 * c2[1]], [0, 0, 1]])
    c3 = X.mean(axis=0)
    s3 = np.sqrt(3.0) / np.mean(np.linalg.norm(X - c3, axis=1))
    T3 = np.diag([s3, s3, s3, 1.0])
    T3[:3, 3] = -s3 * c3
    Xh = np.column_stack([X, np.ones(len(X))]) @ T3.T
    x = (np.column_stack([uv, np.ones(len(uv))]) @ T2.T)[:, :2]
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -x[:, :1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -x[:, 1:] * Xh
    P = np.linalg.inv(T2) @ np.linalg.svd(A)[2][-1].reshape(3, 4) @ T3
    K, _ = rq(P[:, :3])
    K = K @ np.diag(np.sign(np.diag(K)))
    K = K / K[2, 2]
    return K if np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 else None


def calibrate_camera_dlt_lm(points_world_per_image, uv_per_image, width: int, height: int, *,
                            eval_points_world_per_image=None, eval_uv_per_image=None, name: str = "camera",
                            min_images: int = MIN_CALIB_IMAGES, warn_skipped: bool = True,
                            survey=None, model: str = "radial1") -> IntrinsicsResult:
    """Bouguet/Tsai-style baseline: full K from per-image DLT (median over images), PnP, then the same
    LM over `model`'s parameters, its distortion starting at zero (survey as `calibrate_camera`'s)."""
    calib, evals, centre, skipped = _load_inputs(points_world_per_image, uv_per_image,
                                                 eval_points_world_per_image, eval_uv_per_image, name, min_images,
                                                 warn_skipped)
    if plane_frame(np.vstack([X for X, _ in calib.values()])) is not None:
        raise DmaisError(f"camera {name}: dlt_lm needs a 3-D field; the DLT of a flat one does not determine K")
    Ks = [K for K in (_dlt_intrinsics(X, uv) for X, uv in calib.values()) if K is not None]
    if not Ks:
        raise DmaisError(f"camera {name}: the DLT failed on every calibration image")
    K = np.median(np.array(Ks), axis=0)
    camera0 = Camera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], d=0.0, width=width, height=height, model=model)
    poses = {k: estimate_pose(camera0, X, uv)[0] for k, (X, uv) in calib.items()}
    camera, poses, residuals, cov, effect, estimated = bundle_adjust(camera0, poses, calib, survey)
    return _finish(name, "dlt_lm", camera, poses, residuals, cov, calib, evals, centre, skipped, survey_effect=effect,
                   survey_sigma_m=estimated)
