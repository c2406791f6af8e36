"""Seeded synthetic scenes for the generalized pose tests, with known truth and explicit noise.

Every generator returns (origins (n, 3), directions (n, 3) unit, points (n, 3), R (3, 3), t (3,))
with x_rig = R @ M + t, noise-free unless a noise level is given. Kinds:

- `generalized_scene`: OpenGV's experiments: cameras within 1 m of the rig origin, points 4-8 m
  around it in every direction, a random rotation;
- `dmais_scene`: the paper's rig (C0 nadir, C1..C4 tilted 45 deg, 0.1 m apart, f = 45000 px,
  4096 x 3000 px) at 350 m over a ground with +-10 m relief (or flat: `planar=True`) in UTM-like
  coordinates, random yaw, roll and pitch within 3 deg; pixel noise in pixels;
- `single_camera_scene`: C0 of that rig alone (a central, 5-degree camera);
- `narrow_camera_scene`: C0 alone with a field of view of choice (0.5 to 5.4 deg) over flat
  ground: the paper's subset #0 over a flat area, where eq. objfun is ill-conditioned.

`multistart_minimum` is the slow, independent reference for the global minimum of eq. objfun.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dmais_pipe.bench.pose import FOCAL_PX, HEIGHT, WIDTH, dmais_cam_from_rig
from dmais_pipe.bench.pose_hard import multistart_minimum as reference_minimum


def random_rotation(rng, max_angle=np.deg2rad(180)) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * rng.uniform(0, max_angle)).as_matrix()


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def generalized_scene(rng, n=12, n_cameras=4, noise=0.0, offset=(0.0, 0.0, 0.0), max_angle=np.deg2rad(150)):
    """OpenGV-like scene; `noise` is the std of direction perturbations (radians, roughly)."""
    centers = rng.uniform(-1, 1, size=(n_cameras, 3))
    camera = rng.integers(0, n_cameras, size=n)
    camera[:n_cameras] = np.arange(n_cameras)[: min(n, n_cameras)]
    origins = centers[camera]
    directions = _unit(rng.normal(size=(n, 3)))
    depths = rng.uniform(4, 8, size=n)
    x_rig = origins + depths[:, None] * directions
    R = random_rotation(rng, max_angle)
    t = rng.uniform(-2, 2, size=3)
    points = (x_rig - t) @ R + np.asarray(offset)
    t = t - R @ np.asarray(offset)
    if noise:
        directions = _unit(directions + noise * rng.normal(size=(n, 3)))
    return origins, directions, points, R, t


def dmais_pose(rng, yaw=None, tilt_deg=3.0, height=350.0) -> tuple[np.ndarray, np.ndarray]:
    """rig_from_world (R, t) of a down-looking rig (rig z towards the ground) over UTM-like ground."""
    yaw = rng.uniform(0, 2 * np.pi) if yaw is None else yaw
    tilts = np.deg2rad(rng.uniform(-tilt_deg, tilt_deg, size=2))
    world_from_rig = Rotation.from_euler("zxy", [yaw, np.pi + tilts[0], tilts[1]]).as_matrix()
    centre = np.array([5e5, 4e6, height]) + rng.uniform(-50, 50, size=3)
    R = world_from_rig.T
    return R, -R @ centre


def dmais_scene(rng, points_per_camera=4, cameras=range(5), noise_px=0.0, planar=False, yaw=None,
                relief=10.0, focal_px=FOCAL_PX):
    """Rays of the DMAIS rig to ground points: pixels uniform over each image, noise in pixels;
    focal_px sets the cameras' field of view (4096 px wide images)."""
    R, t = dmais_pose(rng, yaw)
    world_from_rig, centre = R.T, -R.T @ t
    origins, directions, points = [], [], []
    for k in cameras:
        cam_from_rig, v = dmais_cam_from_rig(k)
        uv = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], size=(points_per_camera, 2))
        bearing = np.column_stack([(uv - [(WIDTH - 1) / 2, (HEIGHT - 1) / 2]) / focal_px, np.ones(len(uv))])
        f_rig = _unit(bearing) @ cam_from_rig  # rows: cam_from_rig^T bearing
        origin_world = centre + world_from_rig @ v
        f_world = f_rig @ world_from_rig.T
        ground = np.zeros(len(uv)) if planar else rng.uniform(-relief, relief, size=len(uv))
        depth = (ground - origin_world[2]) / f_world[:, 2]
        points.append(origin_world + depth[:, None] * f_world)
        if noise_px:
            uv = uv + noise_px * rng.normal(size=uv.shape)
            bearing = np.column_stack([(uv - [(WIDTH - 1) / 2, (HEIGHT - 1) / 2]) / focal_px, np.ones(len(uv))])
            f_rig = _unit(bearing) @ cam_from_rig
        origins.append(np.tile(v, (len(uv), 1)))
        directions.append(f_rig)
    return np.vstack(origins), np.vstack(directions), np.vstack(points), R, t


def single_camera_scene(rng, n=10, noise_px=0.0, planar=False):
    """C0 alone: a central camera with a 5.2 x 3.8 degree field of view."""
    return dmais_scene(rng, points_per_camera=n, cameras=[0], noise_px=noise_px, planar=planar)


def focal_of_fov(fov_deg: float) -> float:
    """Focal length (px) that gives the 4096 px wide image a horizontal field of view of fov_deg."""
    return (WIDTH / 2) / np.tan(np.deg2rad(fov_deg) / 2)


def narrow_camera_scene(rng, fov_deg, n=10, noise_px=0.3):
    """C0 alone with a horizontal field of view of fov_deg (4096 x 3000 px) over flat ground at
    350 m, random yaw, tilt within 3 deg; n points, pixel noise noise_px."""
    return dmais_scene(rng, points_per_camera=n, cameras=[0], noise_px=noise_px, planar=True,
                       focal_px=focal_of_fov(fov_deg))


# ---------------------------------------------------------------- reference global minimum (slow)


def direct_cost(origins, directions, points, R, t):
    """Eq. objfun at (R (3, 3), t (3,)), summed over the rays; points (n, 3) as given."""
    return float(np.sum(np.cross(directions, points @ R.T + t - origins) ** 2))


def multistart_minimum(origins, directions, points, n_random=16, iterations=60, seed=0, starts=()):
    """Minimum of eq. objfun over SO(3) by LM from 24 axis-aligned + n_random random starts (seeded)
    and the rotations of starts (k, 3, 3) (e.g. a scene's true rotation): `bench.pose_hard`'s
    multi-start reference, independent of the solver. Returns (cost, R (3, 3), t (3,)) of the least
    cost among the minima that put at least half of the points in front of their rays; (inf, None,
    None) if no minimum does."""
    return reference_minimum(origins, directions, points, np.random.default_rng(seed), n_random, iterations, starts)


def centred_cost(origins, directions, points, R, t):
    """Eq. objfun at (R, t) evaluated on the centred points (t + R m for the mean m): the same
    value as `direct_cost` without the rounding of UTM-sized coordinates."""
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    centroid = points.mean(axis=0)
    return direct_cost(origins, directions, points - centroid, R, t + R @ centroid)
