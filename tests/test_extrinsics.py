"""Extrinsic calibration (paper: localization with RTK centre, avg_T, rig BA eq. min) against the simulator."""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd
import pytest
import yaml

from dmais_pipe.calib.extrinsics import calibrate_extrinsics, initial_extrinsics, run_extrinsics
from dmais_pipe.calib.intrinsics import run_intrinsics
from dmais_pipe.calib.localize import kabsch_rotation, localize_image, rotation_with_known_center
from dmais_pipe.camera import Camera
from dmais_pipe.dataset import Dataset, load_observations
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3, rotation_error
from dmais_pipe.rig import Rig
from dmais_pipe.sim.simulate import simulate

SIM = {
    "name": "extrinsics-small",
    "seed": 11,
    "intrinsics": {"calib_images_per_camera": 20, "eval_images_per_camera": 2},
    "flight": {"frames_per_group": 1},
    "render": {"intrinsics": False, "extrinsics": False, "flight": False},
}


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    root = tmp_path_factory.mktemp("extrinsics")
    (root / "sim.yaml").write_text(yaml.safe_dump(SIM))
    dataset = simulate(root / "sim.yaml", root / "dataset")
    results = root / "results"
    run_intrinsics(dataset, results, methods=("ours",))
    written = run_extrinsics(dataset, results)
    return dataset, results, written


def _truth_poses(dataset) -> dict[str, Rigid3]:
    images = pd.read_csv(dataset / "truth" / "images.csv")
    return {r.image: Rigid3.from_quat([r.qw, r.qx, r.qy, r.qz], [r.tx, r.ty, r.tz]) for r in images.itertuples()}


def _ray_errors(est: Rig, truth: Rig, step: int = 256):
    """RMS ray angle (deg) per camera and centre distance (m), after the best aligning rotation."""
    u, v = np.meshgrid(np.arange(step / 2, 4096, step), np.arange(step / 2, 3000, step))
    uv = np.column_stack([u.ravel(), v.ravel()])
    names = est.camera_names
    de = {c: est.rays(c, uv)[1] for c in names}
    dt = {c: truth.rays(c, uv)[1] for c in names}
    A = kabsch_rotation(np.vstack([dt[c] for c in names]), np.vstack([de[c] for c in names]))
    out = {}
    for c in names:
        angle = np.arccos(np.clip(np.sum((de[c] @ A.T) * dt[c], axis=1), -1.0, 1.0))
        out[c] = (np.degrees(np.sqrt(np.mean(angle**2))), np.linalg.norm(A @ est.camera_center(c) - truth.camera_center(c)))
    return out


def test_rig_with_priors_matches_truth(calibrated):
    dataset, results, written = calibrated
    truth = Rig.load(dataset / "truth" / "rig.json")
    rig = Rig.load(results / "rig.json")
    assert rig.camera_names == truth.camera_names and rig.reference_camera == "C0"
    np.testing.assert_allclose(rig.cam_from_rig["C0"].R, np.eye(3))
    for camera, (ray_rms_deg, centre_m) in _ray_errors(rig, truth).items():
        assert ray_rms_deg < 0.01, camera
        assert centre_m < 0.05, camera
    data = json.loads((results / "rig.json").read_text())
    assert data["use_priors"] is True
    for camera in truth.camera_names:
        assert 0.15 < data["rms_px"][camera] < 0.6
        assert data["n_observations"][camera] > 20
        assert set(data["std"][camera]) == {"rotation_deg", "center_m"}
    assert all(0 < s < 0.01 for s in data["std"]["C1"]["rotation_deg"] + data["std"]["C1"]["center_m"])


def test_tables_known_and_unknown(calibrated):
    dataset, results, written = calibrated
    assert results / "rig.json" in written
    table_R = pd.read_csv(results / "tables" / "extrinsics_R.csv")
    table_t = pd.read_csv(results / "tables" / "extrinsics_t.csv")
    assert list(table_R["camera"]) == ["C1", "C2", "C3", "C4"] == list(table_t["camera"])
    assert list(table_R.columns) == ["camera", "known_z_deg", "known_y_deg", "known_x_deg", "unknown_z_deg",
                                     "unknown_y_deg", "unknown_x_deg", "eps_R_deg"]
    assert list(table_t.columns) == ["camera", "known_x_m", "known_y_m", "known_z_m", "unknown_x_m", "unknown_y_m",
                                     "unknown_z_m", "eps_t_m"]
    # the known column is the truth's (tab:extrinsics_R "known" column, rig_from_cam ZYX Euler)
    truth = {"C1": (-179.811, -0.152, 46.233), "C3": (0.150, -0.047, 44.038)}
    for camera, angles in truth.items():
        row = table_R.set_index("camera").loc[camera]
        np.testing.assert_allclose([row.known_z_deg, row.known_y_deg, row.known_x_deg], angles, atol=0.1)
    assert (table_R["eps_R_deg"] >= 0).all() and (table_t["eps_t_m"] >= 0).all()
    unknown = Rig.load(results / "extrinsics" / "rig_unknown.json")
    assert json.loads((results / "extrinsics" / "rig_unknown.json").read_text())["use_priors"] is False
    assert unknown.camera_names == ["C0", "C1", "C2", "C3", "C4"]


def test_localization_with_known_centre_is_exact_on_noise_free_data(calibrated):
    dataset, _, _ = calibrated
    truth_rig = Rig.load(dataset / "truth" / "rig.json")
    points = pd.read_csv(dataset / "truth" / "control_points.csv", dtype={"point_id": str}).set_index("point_id")
    obs = pd.read_csv(dataset / "truth" / "observations.csv", dtype={"point_id": str})
    images = pd.read_csv(dataset / "truth" / "images.csv")
    poses = _truth_poses(dataset)
    for image in images.loc[images["stage"] == "extrinsics", "image"]:
        o = obs[obs["image"] == image]
        camera = truth_rig.cameras[image.split("_")[-1]]
        X = points.loc[o["point_id"], ["x", "y", "z"]].to_numpy()
        uv = o[["u", "v"]].to_numpy()
        true = poses[image]
        rotation_only = rotation_with_known_center(camera, X, uv, true.center)
        assert np.degrees(rotation_error(rotation_only.R, true.R)) < 1e-6
        pose, residuals = localize_image(camera, X, uv, true.center)
        assert np.degrees(rotation_error(pose.R, true.R)) < 1e-6
        assert np.linalg.norm(pose.center - true.center) < 1e-5
        assert np.abs(residuals).max() < 1e-5


def test_localization_with_rtk_prior_vs_truth(calibrated):
    dataset, results, _ = calibrated
    ds = Dataset.load(dataset)
    observations = load_observations(ds, results)
    poses = _truth_poses(dataset)
    cameras = {c: Camera.from_dict(json.loads((results / "intrinsics" / f"{c}.json").read_text())) for c in ds.cameras}
    for row in ds.images_of("extrinsics").itertuples():
        o = observations[observations["image"] == row.image]
        X = ds.points.loc[o["point_id"], ["x", "y", "z"]].to_numpy()
        prior = np.array([row.prior_x, row.prior_y, row.prior_z])
        pose, residuals = localize_image(cameras[row.camera], X, o[["u", "v"]].to_numpy(), prior)
        true = poses[row.image]
        assert np.degrees(rotation_error(pose.R, true.R)) < 0.05, row.image
        assert np.linalg.norm(pose.center - true.center) < 0.1, row.image  # RTK prior 2 cm per axis
        assert np.sqrt(np.mean(np.sum(residuals**2, axis=1))) < 0.6


def _inputs(calibrated):
    dataset, results, _ = calibrated
    ds = Dataset.load(dataset)
    cameras = {c: Camera.from_dict(json.loads((results / "intrinsics" / f"{c}.json").read_text())) for c in ds.cameras}
    return ds, cameras, ds.images_of("extrinsics"), load_observations(ds, results)


def test_placement_with_too_few_reference_points_is_skipped(calibrated, caplog):
    ds, cameras, images, observations = _inputs(calibrated)
    ref_p0 = images.loc[(images["placement"] == "p0") & (images["camera"] == "C0"), "image"].iat[0]
    drop = observations.index[observations["image"] == ref_p0][3:]
    with caplog.at_level(logging.WARNING):
        result = calibrate_extrinsics(cameras, "C0", images, observations.drop(drop), ds.points)
    assert result.skipped_placements == ["p0"]
    assert "p0" not in result.ba.rig_from_world and len(result.ba.rig_from_world) == 4
    assert any("skipping placement p0" in r.getMessage() for r in caplog.records)
    assert result.rig.camera_names == ["C0", "C1", "C2", "C3", "C4"]


def test_camera_never_seen_with_the_reference_is_an_error(calibrated):
    ds, cameras, images, observations = _inputs(calibrated)
    # C1 is imaged at placements p1 and p3 only; without C0 there it cannot be tied to the rig frame
    assert set(images.loc[images["camera"] == "C1", "placement"]) == {"p1", "p3"}
    keep = ~((images["camera"] == "C0") & images["placement"].isin(["p1", "p3"]))
    with pytest.raises(DmaisError, match="C1.*never seen together with the reference camera C0"):
        calibrate_extrinsics(cameras, "C0", images[keep], observations, ds.points)
    poses = {"p0": {"C0": Rigid3.identity()}, "p1": {"C1": Rigid3.identity()}}
    with pytest.raises(DmaisError, match="C1"):
        initial_extrinsics(poses, "C0")


def test_two_camera_rig(calibrated):
    """Any number of cameras: a rig of C0 and C2 alone."""
    dataset, _, _ = calibrated
    ds, cameras, images, observations = _inputs(calibrated)
    images = images[images["camera"].isin(["C0", "C2"])]
    result = calibrate_extrinsics({c: cameras[c] for c in ["C0", "C2"]}, "C0", images, observations, ds.points)
    truth = Rig.load(dataset / "truth" / "rig.json")
    assert result.rig.camera_names == ["C0", "C2"]
    assert np.degrees(rotation_error(result.rig.cam_from_rig["C2"].R, truth.cam_from_rig["C2"].R)) < 0.1
    assert np.linalg.norm(result.rig.camera_center("C2") - truth.camera_center("C2")) < 0.1
