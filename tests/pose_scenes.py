"""Seeded synthetic scenes for the generalized pose tests, with known truth and explicit noise.

Every generator returns (origins (n, 3), directions (n, 3) unit, points (n, 3), R (3, 3), t (3,))
with x_rig = R @ M + t, noise-free unless a noise level is given. Kinds:

- `generalized_scene`: OpenGV's experiments: cameras within 1 m of the rig origin, points 4-8 m
  around it in every direction, a random rotation;
- `dmais_scene`: the paper's rig (C0 nadir, C1..C4 tilted 45 deg, 0.1 m apart, f = 45000 px,
  4096 x 3000 px) at 350 m over a ground with +-10 m relief (or flat: `planar=True`) in UTM-like
  coordinates, random yaw, roll and pitch within 3 deg; pixel noise in pixels;
- `single_camera_scene`: C0 of that rig alone (a central, 5-degree camera).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dmais_pipe.pose.bench import FOCAL_PX, HEIGHT, WIDTH, dmais_cam_from_rig


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
                relief=10.0):
    """Rays of the DMAIS rig to ground points: pixels uniform over each image, noise in pixels."""
    R, t = dmais_pose(rng, yaw)
    world_from_rig, centre = R.T, -R.T @ t
    origins, directions, points = [], [], []
    for k in cameras:
        cam_from_rig, v = dmais_cam_from_rig(k)
        uv = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], size=(points_per_camera, 2))
        bearing = np.column_stack([(uv - [(WIDTH - 1) / 2, (HEIGHT - 1) / 2]) / FOCAL_PX, np.ones(len(uv))])
        f_rig = _unit(bearing) @ cam_from_rig  # rows: cam_from_rig^T bearing
        origin_world = centre + world_from_rig @ v
        f_world = f_rig @ world_from_rig.T
        ground = np.zeros(len(uv)) if planar else rng.uniform(-relief, relief, size=len(uv))
        depth = (ground - origin_world[2]) / f_world[:, 2]
        points.append(origin_world + depth[:, None] * f_world)
        if noise_px:
            uv = uv + noise_px * rng.normal(size=uv.shape)
            bearing = np.column_stack([(uv - [(WIDTH - 1) / 2, (HEIGHT - 1) / 2]) / FOCAL_PX, np.ones(len(uv))])
            f_rig = _unit(bearing) @ cam_from_rig
        origins.append(np.tile(v, (len(uv), 1)))
        directions.append(f_rig)
    return np.vstack(origins), np.vstack(directions), np.vstack(points), R, t


def single_camera_scene(rng, n=10, noise_px=0.0, planar=False):
    """C0 alone: a central camera with a 5.2 x 3.8 degree field of view."""
    return dmais_scene(rng, points_per_camera=n, cameras=[0], noise_px=noise_px, planar=planar)
