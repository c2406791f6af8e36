"""Frames whose pose the linearised covariance does not describe, and their variances by re-solving
drawn errors (a parametric bootstrap).

error_model.py propagates the errors to a frame's pose through its solve linearised at the solved
pose. That holds while the frame's residuals are linear in the pose over the pose's own
uncertainty. Where the observations barely fix the pose (one camera of 5.4 deg with 8 points: a
rotation and a translation of metres trade each other), the residuals curve within one sigma and
the solve's errors are larger, skewed and biased. On the paper-scale flight, 400 solves of frame
g1_f000 from camera C0 alone with drawn pixel noise and survey errors spread 12.3, 10.1, 0.76 m
(x, y, z) where the linearisation at the true pose gives 8.6, 10.0, 0.28 m.

`curvature_index` measures the nonlinearity of each frame: the second-order part of its residuals
one standard deviation along each principal axis of the linearised covariance, in units of the
observations' noise (Bates & Watts 1980, J. R. Statist. Soc. B 42: 1-25, measure curvature the same
way, relative to the noise). A frame above NONLINEAR_INDEX gets `bootstrap_variances`: DRAWS
Gaussian draws of the whole error model (error_model.model_draw) added to the directions its solved
pose predicts, each draw solved again by the stage's solver, and the second moments of the
solutions' centres and heading, pitch, roll about the solved pose.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geometry import exp_so3
from ..errors import PoseError
from ._error import curvature_sums, noise_rows, predicted_directions
from .error_model import ErrorModel, Geometry, calibration_errors, model_draw, survey_sigma
from .refine import tangent_bases
from .uncertainty import heading_pitch_roll

#: A frame is re-solved where its residuals' second-order part at one sigma along an axis of its
#: covariance exceeds this many noise standard deviations (paper-scale flight: whole-rig frames at
#: most 0.0005, #012 at most 0.02, #0 median 0.31, up to 0.8).
NONLINEAR_INDEX = 0.1
#: Draws of the error model per re-solved frame: their variances to about 1 / sqrt(DRAWS / 2).
DRAWS = 64


def observation_noise(geometry: Geometry, model: ErrorModel) -> np.ndarray:
    """(N,) rad: each observation's standard deviation per axis from the terms independent between
    the observations of a frame (pixel noise, survey). The others (jitter, mounting, focal,
    calibration) move all points of a camera together, and a frame's pose absorbs most of them:
    they are not the noise against which its fit's curvature shows."""
    g = geometry
    return noise_rows(model.si("pixel"), g.focal, survey_sigma(g.point_sigma, model), g.survey)


def curvature_index(geometry: Geometry, covariance: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(F,) the largest, over the principal axes of each frame's covariance (F, 6, 6) of (omega,
    delta_t), of the norm of its residuals' second-order part at one sigma along the axis, in units
    of the observations' noise (N,) rad (observations without noise left out); inf where the
    covariance is not finite."""
    g = geometry
    finite = np.isfinite(covariance).all(axis=(1, 2))
    values, vectors = np.linalg.eigh(np.where(finite[:, None, None], covariance, np.eye(6)))
    R, t = [g.R], [g.t_centred]  # the solved poses, then each axis' step (plus, minus)
    for k in range(6):
        step = vectors[:, :, k] * np.sqrt(np.clip(values[:, k], 0.0, None))[:, None]  # (F, 6)
        R += [_rotated(step[:, :3], g.R), _rotated(-step[:, :3], g.R)]
        t += [g.t_centred + step[:, 3:], g.t_centred - step[:, 3:]]
    # one compiled pass: per axis and frame the sum of ((plus + minus - 2 centre) / (2 noise))^2, the
    # residuals in the tangent bases of the solved poses' directions (the numpy: tests/test_error_model_rows.py)
    sums = curvature_sums(np.stack(R), np.stack(t), g.frame, g.points_centred, g.origins, noise)
    index = np.zeros(g.n_frames)
    for total in sums:
        index = np.maximum(index, np.sqrt(total))
    return np.where(finite, index, np.inf)


def bootstrap_variances(geometry: Geometry, model: ErrorModel, solve: Callable, rng: np.random.Generator,
                        draws: int = DRAWS) -> tuple[np.ndarray, np.ndarray]:
    """Variances of every frame's centre (F, 3) m^2 (world x, y, z) and heading, pitch, roll (F, 3)
    arcmin^2 about its solved pose, from `draws` re-solves (module docstring) by `solve(origins,
    directions, points)` -> (R, t) rig_from_world (the stage's solver: one narrow camera's frames
    have two minima, and which one the solver takes is part of the error); NaN where fewer than
    half of a frame's solves succeed (a PoseError)."""
    g = geometry
    predicted = _predicted_directions(g, g.R, g.t_centred)
    predicted_bases = tangent_bases(predicted)
    calibration = calibration_errors(g)
    directions = [_perturbed(predicted, predicted_bases, model_draw(g, model, rng, calibration)) for _ in range(draws)]
    solved_centre = -np.einsum("fji,fj->fi", g.R, g.t_centred)
    solved_attitude = heading_pitch_roll(g.R)
    position, angles = np.full((g.n_frames, 3), np.nan), np.full((g.n_frames, 3), np.nan)
    bounds = np.append(g.starts, len(g.frame))
    for f in range(g.n_frames):
        rows = slice(bounds[f], bounds[f + 1])
        poses = []
        for drawn in directions:
            try:
                poses.append(solve(g.origins[rows], drawn[rows], g.points_centred[rows]))
            except PoseError:
                continue
        if len(poses) < draws / 2:
            continue
        R = np.array([pose[0] for pose in poses])
        centre = -np.einsum("dji,dj->di", R, np.array([pose[1] for pose in poses]))
        turn = (heading_pitch_roll(R) - solved_attitude[f] + 180.0) % 360.0 - 180.0
        position[f] = np.mean((centre - solved_centre[f]) ** 2, axis=0)
        angles[f] = np.mean(turn**2, axis=0) * 60.0**2
    return position, angles


def _predicted_directions(g: Geometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) unit directions from each ray's origin to its point for poses R (F, 3, 3), t (F, 3)
    (about the frames' centroids)."""
    return predicted_directions(R, t, g.frame, g.points_centred, g.origins)


def _residuals(g: Geometry, bases: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 2) the residuals of poses R (F, 3, 3), t (F, 3) against directions of tangent bases (N, 2, 3)."""
    return predicted_directions(R, t, g.frame, g.points_centred, g.origins, bases)


def _perturbed(directions: np.ndarray, bases: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """(N, 3) unit directions (N, 3) moved by angular errors (N, 2) rad in their tangent bases (N, 2, 3)."""
    moved = directions + np.einsum("nki,nk->ni", bases, errors)
    return moved / np.linalg.norm(moved, axis=1)[:, None]


def _rotated(omega: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(F, 3, 3) exp(omega) R for rotation vectors omega (F, 3)."""
    return exp_so3(omega) @ R
