"""POS trajectories (issue 41 item 3): SBET and CSV files read back, each frame's position and INS
attitude interpolated at its time, the same lever arm and boresight as frames.csv's pos_* and
prior_q* give, and bad trajectories refused in one line."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest
import yaml

from conftest import observation_only
from test_geo import hand_ecef_from_enu_rotation, hand_ned_from_ecef, refused_in_one_line
from dmais_pipe import geo
from dmais_pipe.dataset import Dataset
from dmais_pipe.evaluate import fit_pos_lever_arm
from dmais_pipe.geometry import (exp_so3, log_so3, quat_from_rotation, rotation_error, rotation_from_euler_zyx,
                                  rotation_from_quat)
from dmais_pipe.pos_calibration import fit_boresight
from dmais_pipe.stages.evaluate import LOCAL_COMPARISON_COLUMNS, with_local_pos_comparison
from dmais_pipe.trajectory import SBET_RECORD_BYTES, Trajectory, TrajectoryError, at_times, sbet_bytes, sbet_from_bytes

ARCMIN = 60.0 * 180.0 / np.pi
QUAT = ["qw", "qx", "qy", "qz"]
PRIOR = ["prior_qw", "prior_qx", "prior_qy", "prior_qz"]


def test_sbet_round_trip_and_true_heading_is_platform_heading_less_wander():
    time = np.array([10.0, 10.005, 10.01])
    geodetic = np.array([[35.0, 17.8, 100.0], [35.00001, 17.80002, 100.5], [35.00002, 17.80004, 101.0]])
    attitude = np.array([[120.0, 1.0, -2.0], [121.0, 1.5, -2.5], [122.0, 2.0, -3.0]])
    data = sbet_bytes(time, geodetic, attitude, wander_deg=[30.0, 31.0, 32.0])
    assert len(data) == 3 * SBET_RECORD_BYTES
    raw = np.frombuffer(data, "<f8").reshape(3, 17)
    assert np.allclose(np.degrees(raw[:, 9]), attitude[:, 0] + [30, 31, 32])  # the platform heading stored
    back = sbet_from_bytes(data)
    assert np.allclose(back.time, time) and np.allclose(back.geodetic, geodetic, rtol=0, atol=1e-12)
    assert np.allclose(back.attitude, attitude, rtol=0, atol=1e-12)


def _trajectory(time, ecef, attitude) -> Trajectory:
    return Trajectory(np.asarray(time, float), geo.geodetic_from_ecef(ecef), np.asarray(attitude, float),
                      np.arange(1, len(time) + 1))


def test_positions_are_cubic_inside_linear_at_the_ends_and_attitudes_slerped():
    t = np.arange(0.0, 1.0, 0.005)
    base = geo.ecef_from_geodetic([35.0, 17.8, 500.0])[0]
    path = lambda x: base + np.outer(x, [3.0, -2.0, 1.0]) + np.outer(x ** 3, [40.0, 25.0, -30.0])  # noqa: E731
    attitude = np.column_stack([100 + 20 * t, 2 * t, -t])
    trajectory = _trajectory(t, path(t), attitude)
    inside = np.array([0.0123, 0.5001, 0.9812])
    positions, _ = at_times(trajectory, inside)
    assert np.abs(positions - path(inside)).max() < 1e-6  # a cubic is reproduced exactly
    edge = np.array([0.0021])  # first interval: no sample before, the line between the two
    line = path(t[0]) + (edge[0] - t[0]) / 0.005 * (path(t[1]) - path(t[0]))
    assert np.abs(at_times(trajectory, edge)[0] - line).max() < 1e-6
    # slerp: halfway between two samples is the rotation halfway along their relative rotation
    _, R = at_times(trajectory, [t[40] + 0.0025])
    R0, R1 = rotation_from_euler_zyx(np.radians(attitude[[40, 41]]))
    halfway = R0 @ exp_so3(0.5 * log_so3(R0.T @ R1))
    assert rotation_error(R[0], halfway) * ARCMIN < 1e-9


@pytest.mark.parametrize("times, message", [
    ([1.5], "outside the trajectory's span"),
    ([0.51], "time 0.51 falls in a gap of 0.11 s between samples 50 and 51"),
])
def test_times_outside_or_in_a_gap_are_refused(times, message):
    t = np.concatenate([np.arange(0.0, 0.5, 0.01), np.arange(0.6, 1.0, 0.01)])
    ecef = np.repeat(geo.ecef_from_geodetic([35.0, 17.8, 500.0]), len(t), 0) + np.outer(t, [1.0, 0, 0])
    with pytest.raises(TrajectoryError, match=message):
        at_times(_trajectory(t, ecef, np.zeros((len(t), 3))), times)


# ------------------------------------------------------------------------------ a flight with a trajectory


def _sim(name: str, trajectory: str | None) -> dict:
    settings = yaml.safe_load(open("config/simulate/geodetic.yaml"))
    small = observation_only(name, settings["seed"], calib_images=2, eval_images=1, frames_per_group=3)
    small["flight"] = {**settings["flight"], **small["flight"]}
    small["geodetic"] = {**settings["geodetic"], "trajectory": trajectory}
    return small


@pytest.mark.parametrize("kind", ["sbet", "csv"])
def test_times_and_a_trajectory_give_the_pos_and_ins_of_frames_csv(simulated_dataset, kind):
    """The same flight given with time and a trajectory instead of pos_* and prior_q*: the same POS
    positions (1e-6 m) and INS attitudes (1e-5'), so the same lever arm and boresight."""
    with_pos = Dataset.load(simulated_dataset(_sim("traj-none", None)))
    with_time = Dataset.load(simulated_dataset(_sim(f"traj-{kind}", kind)))
    assert "pos_x" not in pd.read_csv(with_time.root / "frames.csv").columns
    a, b = (d.frames.set_index("frame") for d in (with_pos, with_time))
    assert np.abs(a[["pos_x", "pos_y", "pos_z"]].to_numpy() - b.loc[a.index, ["pos_x", "pos_y", "pos_z"]].to_numpy()).max() < 1e-6
    turn = rotation_error(rotation_from_quat(a[PRIOR].to_numpy()), rotation_from_quat(b.loc[a.index, PRIOR].to_numpy()))
    assert turn.max() * ARCMIN < 1e-5
    poses = pd.read_csv(with_pos.truth_dir / "frames.csv", dtype={"frame": str, "group": str})  # the true poses
    arms = [fit_pos_lever_arm(poses, dataset, 5.0) for dataset in (with_pos, with_time)]
    assert np.abs(arms[0].value - arms[1].value).max() < 1e-3
    R = rotation_from_quat(poses[QUAT].to_numpy())
    boresights = [fit_boresight(R, rotation_from_quat(d.frames.set_index("frame").loc[poses["frame"], PRIOR].to_numpy()))
                  for d in (with_pos, with_time)]
    assert np.abs(boresights[0].rotvec - boresights[1].rotvec).max() * ARCMIN < 0.01


@pytest.fixture
def sbet_dataset(simulated_dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(simulated_dataset(_sim("traj-sbet", "sbet")), copy)
    return copy


def _spoil_sbet(root, change):
    path = root / "pos" / "trajectory.sbet"
    data = bytearray(path.read_bytes())
    path.write_bytes(bytes(change(data)))


def _swap_records(data: bytearray) -> bytearray:
    values = np.frombuffer(bytes(data), "<f8").reshape(-1, 17).copy()
    values[[10, 11]] = values[[11, 10]]
    return bytearray(values.tobytes())


def _set_time(root, row: int, value: str):
    frames = pd.read_csv(root / "frames.csv", dtype=str, keep_default_na=False)
    frames.loc[row, "time"] = value
    frames.to_csv(root / "frames.csv", index=False)


@pytest.mark.parametrize("spoil, message", [
    (lambda root: _spoil_sbet(root, lambda d: d[:-60]), "trajectory.sbet: ends mid-record: record"),
    (lambda root: _spoil_sbet(root, _swap_records), "trajectory.sbet: record 12: time"),
    (lambda root: _set_time(root, 2, "1.0"), "frames.csv, line 4: frame 'g1_f002': time 1 is outside the trajectory's span"),
    (lambda root: _set_time(root, 2, "388806.5"), "falls in a gap of"),
    (lambda root: _set_time(root, 1, ""), "frames.csv, line 3: frame 'g1_f001' gives neither pos_x, pos_y, pos_z nor time"),
])
def test_bad_trajectory_is_one_line_exit_2_and_nothing_written(sbet_dataset, tmp_path, capsys, spoil, message):
    spoil(sbet_dataset)
    assert message in refused_in_one_line(sbet_dataset, tmp_path / "results", capsys)


def test_ins_angles_per_frame_are_the_ins_quaternions(simulated_dataset, tmp_path):
    """frames.csv's ins_heading/pitch/roll_deg (NED at the frame, made here with the NED rotation
    written out by hand from the frame's latitude and longitude) load as its prior_q* did."""
    root = tmp_path / "dataset"
    shutil.copytree(simulated_dataset(_sim("traj-none", None)), root)
    frames = pd.read_csv(root / "frames.csv", dtype={"frame": str, "group": str})
    lon, lat = frames["pos_x"].to_numpy(), frames["pos_y"].to_numpy()  # pos_crs EPSG:4979: longitude, latitude
    origin = Dataset.load(root).geo.origin
    ecef_from_enu = hand_ecef_from_enu_rotation(*origin[:2])
    imu_from_world = rotation_from_quat(frames[PRIOR].to_numpy())
    ned_from_imu = hand_ned_from_ecef(lat, lon) @ ecef_from_enu @ np.swapaxes(imu_from_world, 1, 2)
    angles = np.degrees(geo.euler_zyx_from_rotation(ned_from_imu))
    given = frames.drop(columns=PRIOR).assign(**dict(zip(("ins_heading_deg", "ins_pitch_deg", "ins_roll_deg"), angles.T)))
    given.to_csv(root / "frames.csv", index=False, float_format="%.17g")
    loaded = Dataset.load(root).frames
    assert rotation_error(rotation_from_quat(loaded[PRIOR].to_numpy()), imu_from_world).max() * ARCMIN < 1e-5


def test_pos_and_ins_comparison_in_north_east_down(simulated_dataset, tmp_path):
    """evaluate's local comparison (issue 41 item 4): one frame's POS moved 1 m north (along the
    north written out by hand) and its INS turned 10' in heading show as -1 m north and -10'."""
    root = tmp_path / "dataset"
    shutil.copytree(simulated_dataset(_sim("traj-none", None)), root)
    poses = pd.read_csv(root / "truth" / "frames.csv", dtype={"frame": str, "group": str})

    def comparison(dataset):
        lever = fit_pos_lever_arm(poses, dataset, 5.0)
        R = rotation_from_quat(poses[QUAT].to_numpy())
        ins = rotation_from_quat(dataset.frames.set_index("frame").loc[poses["frame"], PRIOR].to_numpy())
        table = with_local_pos_comparison(poses, dataset, lever, fit_boresight(R, ins))
        return table[list(LOCAL_COMPARISON_COLUMNS)].to_numpy()

    before = comparison(Dataset.load(root))
    assert np.sqrt(np.mean(before[:, :2] ** 2)) < 0.04 and np.sqrt(np.mean(before[:, 2] ** 2)) < 0.06  # the 2/2/3 cm POS
    frames = pd.read_csv(root / "frames.csv", dtype={"frame": str, "group": str})
    lon, lat, h = frames.loc[4, ["pos_x", "pos_y", "pos_z"]].to_numpy(float)
    north = hand_ned_from_ecef(lat, lon)[0, 0]
    moved = geo.geodetic_from_ecef(geo.ecef_from_geodetic([lat, lon, h]) + north)[0]
    frames.loc[4, ["pos_x", "pos_y", "pos_z"]] = moved[[1, 0, 2]]
    ins = rotation_from_quat(frames.loc[4, PRIOR].to_numpy(float))  # imu_from_world
    ned_from_world = hand_ned_from_ecef(lat, lon)[0] @ hand_ecef_from_enu_rotation(*Dataset.load(root).geo.origin[:2])
    turned = (rotation_from_euler_zyx(np.radians([10 / 60, 0, 0])) @ ned_from_world @ ins.T)  # ned_from_imu, turned
    frames.loc[4, PRIOR] = quat_from_rotation((ned_from_world.T @ turned).T)
    frames.to_csv(root / "frames.csv", index=False, float_format="%.17g")
    change = comparison(Dataset.load(root)) - before
    row = int(np.flatnonzero(poses["frame"].to_numpy() == frames.loc[4, "frame"])[0])
    change = change - np.median(np.delete(change, row, axis=0), axis=0)  # less the lever arm's and boresight's refit
    assert change[row, 0] == pytest.approx(-1.0, abs=0.1) and np.abs(change[row, 1:3]).max() < 0.1
    assert change[row, 3] == pytest.approx(-10.0, abs=1.0) and np.abs(change[row, 4:]).max() < 1.0
