"""poses.csv's attitude and 1-sigma uncertainty columns, and frames.csv's extras carried through.

The uncertainty is checked the way it is defined: one seeded DMAIS-like frame (the paper's rig,
pose_scenes.dmais_scene's geometry, 8 points per camera) solved 300 times with fresh Gaussian
pixel noise, as a 300-frame flight through `estimate_poses`; the predicted per-axis sigma must be
within 15% of the spread of the solves (the sampling error of a standard deviation over 300
draws is 4%).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3, euler_zyx_rates, rotation_from_euler_zyx
from dmais_pipe.bench.pose import HEIGHT, WIDTH, dmais_cam_from_rig, flight_dataset
from dmais_pipe.pose.flight import COLUMNS, estimate_poses
from dmais_pipe.pose.uncertainty import heading_pitch_roll
from dmais_pipe.rig import Rig
from dmais_pipe.workspace import POSE_COLUMNS, POSE_UNCERTAINTY_COLUMNS, Workspace

from pose_scenes import dmais_scene

SOLVES, NOISE_PX, POINTS_PER_CAMERA = 300, 2.0, 8
ATTITUDE = ("heading", "pitch", "roll")


def paper_rig(focal_px: float = 45000.0) -> Rig:
    """The paper's rig (bench.dmais_cam_from_rig) with distortion-free cameras, as dmais_scene."""
    names = [f"C{k}" for k in range(5)]
    camera = Camera(focal_px, focal_px, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, 0.0, WIDTH, HEIGHT)
    cam_from_rig = {}
    for k, name in enumerate(names):
        R, centre = dmais_cam_from_rig(k)
        cam_from_rig[name] = Rigid3(R, -R @ centre)
    return Rig({name: camera for name in names}, cam_from_rig, "C0")


def repeated_frame(seed: int, noise_scale: float = 1.0, extras: dict | None = None):
    """One DMAIS-like frame observed SOLVES times with fresh pixel noise (NOISE_PX * noise_scale,
    the same draws for every scale): (dataset, rig, observations, truth rig_from_world)."""
    rng = np.random.default_rng(seed)
    rig = paper_rig()
    _, _, points, R, t = dmais_scene(rng, points_per_camera=POINTS_PER_CAMERA)
    truth = Rigid3(R, t)
    cameras = np.repeat(rig.camera_names, POINTS_PER_CAMERA)
    uv = np.vstack([rig.project(c, truth, p[None]) for c, p in zip(cameras, points)])
    point_ids = [f"P{k:02d}" for k in range(len(points))]
    names = [f"f{k:03d}" for k in range(SOLVES)]
    noisy = uv + NOISE_PX * noise_scale * rng.normal(size=(SOLVES,) + uv.shape)
    observations = pd.DataFrame({
        "image": [f"{f}_{c}" for f in names for c in cameras], "camera": np.tile(cameras, SOLVES),
        "point_id": np.tile(point_ids, SOLVES), "u": noisy[..., 0].ravel(), "v": noisy[..., 1].ravel()})
    frames = pd.DataFrame({"frame": names, "group": "g", "pos_x": 0.0, "pos_y": 0.0, "pos_z": 0.0, **(extras or {})})
    ground = pd.DataFrame(points, columns=["x", "y", "z"], index=pd.Index(point_ids, name="point_id"))
    return flight_dataset(rig, frames, ground, observations), rig, observations, truth


def attitude_deg(rig_from_world_R) -> np.ndarray:
    """(n, 3) heading, pitch, roll by scipy: world_from_rig as intrinsic ZYX angles, heading in [0, 360)."""
    angles = Rotation.from_matrix(np.swapaxes(rig_from_world_R, -1, -2)).as_euler("ZYX", degrees=True)
    angles[:, 0] %= 360.0
    return angles


def test_heading_pitch_roll_are_scipys_intrinsic_zyx_of_world_from_rig():
    R = Rotation.random(200, random_state=1).as_matrix()
    np.testing.assert_allclose(heading_pitch_roll(R), attitude_deg(R), atol=1e-9)
    angles = heading_pitch_roll(R)
    assert (angles[:, 0] >= 0).all() and (angles[:, 0] < 360).all() and (np.abs(angles[:, 1]) <= 90).all()
    # and the stated composition: world_from_rig = Rz(heading) Ry(pitch) Rx(roll)
    np.testing.assert_allclose(rotation_from_euler_zyx(np.radians(angles)), np.swapaxes(R, 1, 2), atol=1e-12)


def test_euler_rates_match_finite_differences():
    rng = np.random.default_rng(2)
    for angles in rng.uniform([-np.pi, -1.2, -np.pi], [np.pi, 1.2, np.pi], (20, 3)):
        R = rotation_from_euler_zyx(angles)
        h = 1e-6
        numeric = np.column_stack([Rotation.from_matrix(R.T @ rotation_from_euler_zyx(angles + h * e)).as_rotvec() / h
                                   for e in np.eye(3)])
        np.testing.assert_allclose(euler_zyx_rates(angles), numeric, atol=1e-5)


@pytest.mark.parametrize("refine", [False, True])
def test_predicted_sigmas_match_the_spread_of_repeated_solves(refine):
    dataset, rig, observations, truth = repeated_frame(seed=11)
    poses, _ = estimate_poses(dataset, rig, observations, rig.camera_names, refine=refine)
    assert len(poses) == SOLVES and list(poses.columns) == COLUMNS
    R = Rotation.from_quat(poses[["qw", "qx", "qy", "qz"]].to_numpy(), scalar_first=True).as_matrix()
    np.testing.assert_allclose(poses[["heading_deg", "pitch_deg", "roll_deg"]].to_numpy(), attitude_deg(R), atol=1e-9)
    true_attitude = attitude_deg(truth.R[None])[0]
    error = {axis: poses[axis].to_numpy() - truth.center[k] for k, axis in enumerate("xyz")}
    for k, name in enumerate(ATTITUDE):
        error[name] = ((poses[f"{name}_deg"].to_numpy() - true_attitude[k] + 180) % 360 - 180) * 60  # arc-min
    for axis, column in [*((a, f"sigma_{a}_m") for a in "xyz"), *((a, f"sigma_{a}_arcmin") for a in ATTITUDE)]:
        predicted = np.sqrt(np.mean(poses[column] ** 2))
        empirical = np.std(error[axis])
        assert abs(predicted / empirical - 1) < 0.15, (axis, predicted, empirical)
        assert abs(np.mean(error[axis])) < 0.25 * empirical  # unbiased to within the test's resolution
    # the noise behind them is estimated from the frames' residuals (error_model.py)
    assert abs(np.sqrt(np.mean(poses["noise_px"] ** 2)) / NOISE_PX - 1) < 0.05


def test_the_sigmas_follow_the_frames_own_residuals():
    """Twice the pixel noise (the same draws) gives twice the predicted sigmas: the noise comes from
    each frame's residuals, not from a fixed calibration figure."""
    once = estimate_poses(*repeated_frame(seed=12)[:3], cameras=paper_rig().camera_names, calibrated_noise_px=0.1)[0]
    twice = estimate_poses(*repeated_frame(seed=12, noise_scale=2.0)[:3], cameras=paper_rig().camera_names,
                           calibrated_noise_px=0.1)[0]
    for column in POSE_UNCERTAINTY_COLUMNS[3:]:
        np.testing.assert_allclose(twice[column] / once[column], 2.0, rtol=0.03)


def test_frames_csv_extras_are_carried_to_the_poses_file_unchanged(tmp_path):
    extras = {"gps_week": ["2291"] * SOLVES, "gps_seconds": [f"{345600 + 0.125 * k:.6f}" for k in range(SOLVES)],
              "note": ["a, \"quoted\" note", ""] * (SOLVES // 2)}
    dataset, rig, observations, _ = repeated_frame(seed=13, extras=extras)
    poses, per_observation = estimate_poses(dataset, rig, observations, rig.camera_names)
    assert list(poses.columns) == [*COLUMNS, "gps_week", "gps_seconds", "note"]
    rig.save(tmp_path / "rig.json")
    workspace = Workspace(dataset, tmp_path)
    workspace.save_poses(poses, per_observation, tmp_path / "poses.csv")
    written = pd.read_csv(tmp_path / "poses.csv", dtype=str, keep_default_na=False)
    assert list(written.columns) == [*COLUMNS, "gps_week", "gps_seconds", "note"]
    for column, values in extras.items():
        assert written[column].tolist() == values
    loaded = workspace.load_poses()
    np.testing.assert_allclose(loaded["sigma_x_m"], poses["sigma_x_m"], rtol=1e-15)
    assert loaded["gps_seconds"].tolist() == extras["gps_seconds"]

    # a poses file from before the attitude and uncertainty columns still loads, without them
    written[[*POSE_COLUMNS, "certified"]].to_csv(tmp_path / "old.csv", index=False)
    old = workspace.load_poses(tmp_path / "old.csv")
    assert list(old.columns) == [*POSE_COLUMNS, "certified"] and len(old) == SOLVES


def test_the_sigmas_computed_in_blocks_of_frames_equal_those_of_the_whole_group(monkeypatch):
    """flight._linearised_uncertainty takes a group UNCERTAINTY_OBSERVATIONS at a time (the error model's
    memory): every number is a frame's own, equal to those of one block (up to the batched products' rounding)."""
    from dmais_pipe.pose import flight

    dataset, rig, observations, _ = repeated_frame(seed=14)
    whole = flight.solve_flight(dataset, rig, observations, rig.camera_names)
    monkeypatch.setattr(flight, "UNCERTAINTY_OBSERVATIONS", 7 * 2 * len(rig.camera_names) * POINTS_PER_CAMERA + 3)
    blocks = flight.solve_flight(dataset, rig, observations, rig.camera_names)
    columns = list(POSE_UNCERTAINTY_COLUMNS)
    np.testing.assert_allclose(blocks.table[columns], whole.table[columns], rtol=1e-12, atol=0)
    numbers = [c for c in whole.budget.columns if c.startswith("var_")]
    np.testing.assert_allclose(blocks.budget[numbers], whole.budget[numbers], rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(blocks.covariance, whole.covariance, rtol=1e-12, atol=1e-300)
