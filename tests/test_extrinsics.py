"""Extrinsic calibration (paper: localization with RTK centre, avg_T, rig BA eq. min) against the simulator."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pandas as pd
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe import cli
from dmais_pipe.calib import extrinsics as extrinsics_module
from dmais_pipe.calib import rig_ba
from dmais_pipe.calib.extrinsics import (
    DEFAULT_BACKEND,
    CameraNotLinkedError,
    annotate_tables,
    calibrate_extrinsics,
    colmap_rig_config,
    extrinsics_tables,
    image_prefixes,
    initial_extrinsics,
)
from dmais_pipe.calib.localize import kabsch_rotation, localize_image, rotation_with_known_center
from dmais_pipe.camera import Camera
from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.files import write_json_atomic
from dmais_pipe.geometry import Rigid3, rotation_error
from dmais_pipe.rig import Rig
from dmais_pipe.stages import extrinsics, intrinsics
from dmais_pipe.stages.extrinsics import LAYOUT_LABELS
from dmais_pipe.workspace import Workspace

from conftest import observation_only

SIM = observation_only("extrinsics-small", seed=11, calib_images=20, eval_images=2, frames_per_group=1)


@pytest.fixture(scope="module")
def calibrated(simulated_dataset, tmp_path_factory):
    dataset = simulated_dataset(SIM)
    results = tmp_path_factory.mktemp("extrinsics") / "results"
    workspace = Workspace.open(dataset, results)
    intrinsics.run(workspace, intrinsics.CONFS["ours"])
    written = extrinsics.run(workspace)
    return dataset, results, written


def solver_precision(ba, points: pd.DataFrame) -> np.ndarray:
    """(6,) to how much the scipy rig adjustment `ba` determines a camera's rotation vector (rad, 3)
    and centre (m, 3) by its own stopping rule: rig_ba.TOLERANCE x the quantity's scale in the
    problem, 1 rad for a rotation, the scene's extent (the farthest control point of `points` (n rows
    x, y, z) from a placement) for a centre. A finite difference of two solves whose true change is
    zero comes out within twice this, whatever bits a BLAS kernel rounds."""
    placements = np.array([pose.center for pose in ba.rig_from_world.values()])
    points = points[["x", "y", "z"]].to_numpy(dtype=float)
    extent = np.linalg.norm(points[:, None, :] - placements[None], axis=2).max()
    return rig_ba.TOLERANCE * np.r_[np.ones(3), np.full(3, extent)]


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
    assert data["use_priors"] is True and data["backend"] == "pycolmap"
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
                                     "unknown_y_deg", "unknown_x_deg", "eps_R_deg", "known_std_deg",
                                     "unknown_std_deg", "note"]
    assert list(table_t.columns) == ["camera", "known_x_m", "known_y_m", "known_z_m", "unknown_x_m", "unknown_y_m",
                                     "unknown_z_m", "eps_t_m", "known_std_m", "unknown_std_m", "note"]
    # the known column is the truth's (tab:extrinsics_R "known" column, rig_from_cam ZYX Euler)
    truth = {"C1": (-179.811, -0.152, 46.233), "C3": (0.150, -0.047, 44.038)}
    for camera, angles in truth.items():
        row = table_R.set_index("camera").loc[camera]
        np.testing.assert_allclose([row.known_z_deg, row.known_y_deg, row.known_x_deg], angles, atol=0.1)
    assert (table_R["eps_R_deg"] >= 0).all() and (table_t["eps_t_m"] >= 0).all()
    unknown = Rig.load(results / "extrinsics" / "rig_unknown.json")
    assert json.loads((results / "extrinsics" / "rig_unknown.json").read_text())["use_priors"] is False
    assert unknown.camera_names == ["C0", "C1", "C2", "C3", "C4"]


def test_tables_carry_standard_deviations_and_the_note(calibrated):
    """Each row relates eps to the bundle adjustment's standard deviations; the note gives this run's numbers."""
    dataset, results, written = calibrated
    table_t = pd.read_csv(results / "tables" / "extrinsics_t.csv").set_index("camera")
    table_R = pd.read_csv(results / "tables" / "extrinsics_R.csv").set_index("camera")
    for label in ("known", "unknown"):
        data = json.loads((results / "extrinsics" / f"rig_{label}.json").read_text())
        for camera, row in table_t.iterrows():
            assert row[f"{label}_std_m"] == pytest.approx(np.linalg.norm(data["std"][camera]["center_m"]), abs=1e-6)
            assert table_R.loc[camera, f"{label}_std_deg"] == pytest.approx(
                np.linalg.norm(data["std"][camera]["rotation_deg"]), abs=1e-6)
    for camera, row in table_t.iterrows():
        eps_cm, ratio, std_cm = map(float, re.fullmatch(
            r"without priors (\S+) cm = (\S+) x the centre's std without priors \((\S+) cm\)", row.note).groups())
        assert (eps_cm, ratio, std_cm) == pytest.approx(
            (100 * row.eps_t_m, row.eps_t_m / row.unknown_std_m, 100 * row.unknown_std_m), abs=0.051)
        eps_deg, _, std_deg = map(float, re.fullmatch(r"without priors (\S+) deg = (\S+) x its std \((\S+) deg\)",
                                                      table_R.loc[camera, "note"]).groups())
        assert (eps_deg, std_deg) == pytest.approx((table_R.loc[camera, "eps_R_deg"],
                                                    table_R.loc[camera, "unknown_std_deg"]), abs=6e-5)
    note_path = results / "tables" / "extrinsics_note.txt"
    assert note_path in written
    note = note_path.read_text()
    low, high = map(float, re.search(r"centres move by (\S+)-(\S+) m", note).groups())
    assert (low, high) == pytest.approx((table_t.eps_t_m.min(), table_t.eps_t_m.max()), abs=6e-4)
    low, high = map(float, re.search(r"centre standard deviations of (\S+)-(\S+) m", note).groups())
    assert (low, high) == pytest.approx((table_t.unknown_std_m.min(), table_t.unknown_std_m.max()), abs=6e-4)
    # this simulator's field fixes the centres without priors to about a centimetre: eps_t is noise, not metres
    assert (table_t.eps_t_m < 3 * table_t.unknown_std_m).all() and (table_t.unknown_std_m < 0.05).all()
    assert "within the noise" in note


def test_note_calls_a_deviation_beyond_the_noise_systematic(calibrated):
    ds, cameras, images, observations = _inputs(calibrated)
    known, unknown = (calibrate_extrinsics(cameras, "C0", images, observations, ds.points, use_priors=p)
                      for p in (True, False))
    moved = {c: Rigid3(T.R, T.t + [0.0, 0.0, 0.0 if c == "C0" else 0.3]) for c, T in known.rig.cam_from_rig.items()}
    far = Rig(known.rig.cameras, moved, "C0")
    _, table_t, note = annotate_tables(*extrinsics_tables(far, unknown.rig), known, unknown)
    assert (table_t.eps_t_m > 0.25).all()
    assert "more than noise: a systematic error" in note and "within the noise" not in note


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
    observations = Workspace(ds, results).load_observations()
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
    return ds, cameras, ds.images_of("extrinsics"), Workspace(ds, results).load_observations()


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
    with pytest.raises(CameraNotLinkedError, match="C1.*never seen together with the reference camera C0") as error:
        calibrate_extrinsics(cameras, "C0", images[keep], observations, ds.points)
    assert isinstance(error.value, DmaisError) and error.value.cameras == ["C1", "C3"]  # both only at p1, p3
    poses = {"p0": {"C0": Rigid3.identity()}, "p1": {"C1": Rigid3.identity()}}
    with pytest.raises(CameraNotLinkedError, match="C1") as error:
        initial_extrinsics(poses, "C0")
    assert error.value.cameras == ["C1"] and error.value.reference == "C0"


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


# ------------------------------------------------------------------------------ pycolmap backend

# Different per-camera pixel sigmas, so that the pycolmap backend's weighting (pixels scaled by 1 / sigma) is exercised.
SIGMAS = {"C0": 0.20, "C1": 0.22, "C2": 0.24, "C3": 0.26, "C4": 0.28}


def _pose_differences(a: rig_ba.RigBAResult, b: rig_ba.RigBAResult) -> tuple[float, float]:
    """Largest rotation (rad) and translation / centre (m) difference over extrinsics and placements."""
    rot = [rotation_error(a.rig_from_cam[c].R, b.rig_from_cam[c].R) for c in a.rig_from_cam]
    rot += [rotation_error(a.rig_from_world[j].R, b.rig_from_world[j].R) for j in a.rig_from_world]
    dist = [np.linalg.norm(a.rig_from_cam[c].t - b.rig_from_cam[c].t) for c in a.rig_from_cam]
    dist += [np.linalg.norm(a.rig_from_world[j].center - b.rig_from_world[j].center) for j in a.rig_from_world]
    assert set(a.rig_from_cam) == set(b.rig_from_cam) and set(a.rig_from_world) == set(b.rig_from_world)
    return float(max(rot)), float(max(dist))


@pytest.mark.parametrize("use_priors", [True, False])
def test_pycolmap_and_scipy_backends_agree(calibrated, use_priors):
    """Both backends minimise the same cost.

    Measured here: 7.5e-12 rad / 2.0e-10 m with priors, 1.8e-13 rad / 1.5e-10 m without; over simulator
    seeds 1-4 at most 1.2e-10 rad / 5.1e-8 m (without priors the centres have ~8 mm standard deviations:
    the cost is flat enough there for the two solvers to stop 1e-8 m apart). Hence 1e-8 rad and 1e-6 m.
    Dropping the per-camera weights in pycolmap moves the solution by 3.9e-6 rad / 0.4 mm (without
    priors) and 2.2e-5 rad / 3 cm (with), far outside.
    """
    ds, cameras, images, observations = _inputs(calibrated)
    seen = observations[observations["image"].isin(images["image"])].groupby("point_id").size()
    assert (seen == 1).any()  # control points seen once: the pycolmap scene needs its shadow observations
    out = {backend: calibrate_extrinsics(cameras, "C0", images, observations, ds.points, use_priors=use_priors,
                                         pixel_sigma=SIGMAS, backend=backend).ba for backend in ("pycolmap", "scipy")}
    assert out["pycolmap"].backend == "pycolmap" and out["scipy"].backend == "scipy"
    rotation, distance = _pose_differences(out["pycolmap"], out["scipy"])
    assert rotation < 1e-8 and distance < 1e-6
    assert bool(out["pycolmap"].prior_residuals_m) == use_priors
    np.testing.assert_allclose(out["pycolmap"].sigma0, out["scipy"].sigma0, rtol=1e-9)
    for camera in cameras:
        for key in ("rotation_deg", "center_m"):
            np.testing.assert_allclose(out["pycolmap"].std[camera][key], out["scipy"].std[camera][key],
                                       rtol=1e-6, atol=1e-12)
        # per-camera RMS moves along the cost's flat directions: measured up to 3.8e-9 relative (the total, sigma0,
        # agrees to 3e-13), so 1e-7
        assert out["pycolmap"].rms_px[camera] == pytest.approx(out["scipy"].rms_px[camera], rel=1e-7)


def test_pycolmap_backend_with_priors_far_from_the_localized_centres(calibrated):
    """Focal lengths 0.5 % long put every localized centre ~1 m along its axis from its RTK prior: the similarity
    between centres and priors is far from the identity (it used to throw pycolmap's start off and fall back to
    scipy); the shadow images keep COLMAP's alignment the identity and pycolmap still reaches scipy's optimum."""
    ds, cameras, images, observations = _inputs(calibrated)
    longer = {c: dataclasses.replace(cam, fx=cam.fx * 1.005, fy=cam.fy * 1.005) for c, cam in cameras.items()}
    out = {backend: calibrate_extrinsics(longer, "C0", images, observations, ds.points, backend=backend).ba
           for backend in ("pycolmap", "scipy")}
    assert out["pycolmap"].backend == "pycolmap"
    assert max(np.linalg.norm(r) for r in out["scipy"].prior_residuals_m.values()) > 0.1  # priors far off
    rotation, distance = _pose_differences(out["pycolmap"], out["scipy"])
    assert rotation < 1e-8 and distance < 1e-6


def test_pycolmap_backend_checks_its_solution(calibrated, monkeypatch, caplog):
    """With every prior an inlier of COLMAP's prior alignment (not only the shadow images), its pose-prior adjuster
    drags the constant control points along (metres here); the check sees it and solves with scipy instead."""
    ds, cameras, images, observations = _inputs(calibrated)
    reference = calibrate_extrinsics(cameras, "C0", images, observations, ds.points, backend="scipy").ba
    monkeypatch.setattr(rig_ba, "ALIGNMENT_MAX_ERROR_M", 1e6)
    with caplog.at_level(logging.WARNING):
        result = calibrate_extrinsics(cameras, "C0", images, observations, ds.points, backend="pycolmap").ba
    assert any("not the optimum of our cost" in r.getMessage() for r in caplog.records)
    assert result.backend == "scipy"
    rotation, distance = _pose_differences(result, reference)
    assert rotation < 1e-12 and distance < 1e-12  # the same scipy solve


def test_cli_backend_switch(calibrated, tmp_path):
    """`dmais extrinsics --backend scipy` reaches the default (pycolmap) run's rig; the switch offers every backend."""
    dataset, results, _ = calibrated
    command = ["extrinsics", str(dataset), "--out", str(tmp_path)]
    assert cli._parser().parse_args(command).backend is None  # the conf decides
    assert extrinsics.Conf().backend == DEFAULT_BACKEND == "pycolmap"
    for backend in rig_ba.BACKENDS:
        assert cli._parser().parse_args(command + ["--backend", backend]).backend == backend
    with pytest.raises(SystemExit):
        cli._parser().parse_args(command + ["--backend", "ceres"])
    shutil.copytree(results / "intrinsics", tmp_path / "intrinsics")
    assert cli.main(["extrinsics", str(dataset), "--out", str(tmp_path), "--backend", "scipy"]) == 0
    assert json.loads((tmp_path / "rig.json").read_text())["backend"] == "scipy"
    assert json.loads((results / "rig.json").read_text())["backend"] == "pycolmap"
    ours, default = Rig.load(tmp_path / "rig.json"), Rig.load(results / "rig.json")
    for camera in default.camera_names:
        assert rotation_error(ours.cam_from_rig[camera].R, default.cam_from_rig[camera].R) < 1e-8
        assert np.linalg.norm(ours.camera_center(camera) - default.camera_center(camera)) < 1e-6


def test_unknown_backend_is_an_error(calibrated):
    ds, cameras, images, observations = _inputs(calibrated)
    with pytest.raises(DmaisError, match="unknown backend 'ceres'"):
        calibrate_extrinsics(cameras, "C0", images, observations, ds.points, backend="ceres")


# ------------------------------------------------------------------------------ outputs


def test_colmap_rig_config_round_trips(calibrated):
    _, results, written = calibrated
    assert results / "rig_config.json" in written
    rig = Rig.load(results / "rig.json")
    configs = pycolmap.read_rig_config(results / "rig_config.json")
    assert len(configs) == 1
    entries = configs[0].cameras
    assert [e.image_prefix for e in entries] == ["C0/", "C1/", "C2/", "C3/", "C4/"]  # no image files: "<camera>/"
    assert entries[0].ref_sensor and entries[0].cam_from_rig is None
    for entry in entries:
        name = entry.image_prefix.rstrip("/")
        camera = rig.cameras[name]
        # COLMAP's pixel convention: the top-left pixel's centre is at (0.5, 0.5), ours at (0, 0)
        np.testing.assert_allclose(entry.camera.params,
                                   [camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, camera.d, 0, 0, 0],
                                   rtol=1e-15)
        if entry.ref_sensor:
            continue
        expected = rig.cam_from_rig[name]
        np.testing.assert_allclose(entry.cam_from_rig.rotation.matrix(), expected.R, atol=1e-12)
        np.testing.assert_allclose(entry.cam_from_rig.translation, expected.t, atol=1e-15)
        assert np.linalg.norm(expected.t) > 0.05  # a real lever arm, not a default


def test_colmap_rig_config_uses_colmap_pixel_convention(tmp_path):
    """A principal point at our image centre ((W - 1) / 2) is pycolmap's own image centre (W / 2) in the config,
    and the config's camera projects every point half a pixel right of and below our projection."""
    W, H = 4096, 3000
    centred = Camera(fx=45000.0, fy=44900.0, cx=(W - 1) / 2, cy=(H - 1) / 2, d=2.5, width=W, height=H)
    off = Camera(fx=44000.0, fy=44100.0, cx=2031.25, cy=1517.75, d=-1.5, width=W, height=H)
    tilt = Rotation.from_euler("y", 45, degrees=True).as_matrix()
    rig = Rig({"A": centred, "B": off}, {"A": Rigid3.identity(), "B": Rigid3(tilt, [0.1, 0.0, -0.05])}, "A")
    path = write_json_atomic(tmp_path / "rig_config.json", colmap_rig_config(rig))
    entries = {e.image_prefix: e.camera for e in pycolmap.read_rig_config(path)[0].cameras}
    default = pycolmap.Camera.create_from_model_name(1, "OPENCV", 45000.0, W, H)
    assert (entries["A/"].principal_point_x, entries["A/"].principal_point_y) == (
        default.principal_point_x, default.principal_point_y)
    X = np.random.default_rng(3).uniform([-2.0, -1.5, 90.0], [2.0, 1.5, 110.0], size=(50, 3))
    for prefix, camera in (("A/", centred), ("B/", off)):
        np.testing.assert_allclose(entries[prefix].img_from_cam(X), camera.project(X) + 0.5, atol=1e-9)


def test_image_prefixes():
    images = pd.DataFrame({"camera": ["C0", "C0", "C1", "C1"],
                           "path": ["images/C0/a.png", "images/C0/b/c.png", "images/C1/a.png", ""]})
    assert image_prefixes(images, ["C0", "C1"]) == {"C0": "images/C0/", "C1": "images/C1/"}
    shared = images.assign(path=["img/a.png", "img/b.png", "img/c.png", "img/d.png"])
    assert image_prefixes(shared, ["C0", "C1"]) == {"C0": "C0/", "C1": "C1/"}
    assert image_prefixes(images.assign(path=""), ["C0", "C1"]) == {"C0": "C0/", "C1": "C1/"}


def test_layout_figure_of_both_cases(calibrated):
    _, results, written = calibrated
    path = results / "figures" / "extrinsics_layout.svg"
    assert path in written
    svg = ET.parse(path).getroot()
    ns = "{http://www.w3.org/2000/svg}"
    ids = {g.get("id") for g in svg.iter(f"{ns}g") if (g.get("id") or "").startswith("layout-")}
    assert ids == {f"layout-{case}-C{k}" for case in (0, 1) for k in range(5)}
    texts = {"".join(t.itertext()) for t in svg.iter(f"{ns}text")}
    assert set(LAYOUT_LABELS) <= texts


# ------------------------------------------------------------------------------ two cameras vs cv2.stereoCalibrate


def _stereo_scene(seed: int = 7, n_views: int = 8, sigma: float = 0.3):
    """Two cameras 0.25 m apart, converging by 8 deg, both seeing a 9 x 7 target (slightly 3D) in every view.

    Returns cameras, cam_from_rig of "R" (truth), the target (63, 3) and per view the noisy pixels of L and R.
    """
    rng = np.random.default_rng(seed)
    cameras = {"L": Camera(1000.0, 1002.0, 500.0, 395.0, -0.08, 1000, 800),
               "R": Camera(990.0, 995.0, 505.0, 402.0, 0.05, 1000, 800)}
    R_from_L = Rigid3(Rotation.from_euler("y", -8, degrees=True).as_matrix(), [-0.25, 0.01, 0.02])
    gx, gy = np.meshgrid(np.arange(9) * 0.06, np.arange(7) * 0.06)
    target = np.column_stack([gx.ravel() - 0.24, gy.ravel() - 0.18, 0.05 * np.sin(3 * gx.ravel())])
    views = []
    while len(views) < n_views:
        L_from_world = Rigid3(Rotation.from_rotvec(rng.normal(0, 0.25, 3)).as_matrix(),
                              [rng.uniform(0.11, 0.31), rng.uniform(-0.15, 0.15), rng.uniform(1.6, 2.4)])
        uv = [cameras["L"].project(L_from_world.apply(target)),
              cameras["R"].project((R_from_L * L_from_world).apply(target))]
        if all(cameras[c].in_image(p, 5).all() for c, p in zip("LR", uv)):
            views.append([p + rng.normal(0, sigma, p.shape) for p in uv])
    return cameras, R_from_L, target, views


def test_two_camera_rig_matches_cv2_stereo_calibrate():
    """Same observations, intrinsics fixed: our rig refinement and cv2.stereoCalibrate minimise the same cost.

    Measured over seeds 1-5 and 7: they differ by at most 8.8e-8 rad and 2.0e-7 m (OpenCV's LM stopping
    earlier), while both are 1.7e-4-4.1e-4 rad and 0.2-0.8 mm from the truth (0.3 px noise); the
    tolerances (1e-6 rad, 2e-6 m) sit between. Truth within 4x the reported standard deviation.
    """
    sigma = 0.3
    cameras, truth, target, views = _stereo_scene(sigma=sigma)
    ids = [str(i) for i in range(len(target))]
    images = pd.DataFrame([{"image": f"v{k}_{c}", "camera": c, "placement": f"v{k}"} for k in range(len(views))
                           for c in "LR"])
    observations = pd.DataFrame([{"image": f"v{k}_{c}", "point_id": i, "u": u, "v": v} for k, view in enumerate(views)
                                 for c, uv in zip("LR", view) for i, (u, v) in zip(ids, uv)])
    points = pd.DataFrame(target, columns=["x", "y", "z"], index=pd.Index(ids, name="point_id"))
    result = calibrate_extrinsics(cameras, "L", images, observations, points, pixel_sigma=sigma)
    assert result.ba.backend == "pycolmap"
    ours = result.rig.cam_from_rig["R"]

    distortion = {c: np.array([cameras[c].d, 0.0, 0.0, 0.0, 0.0]) for c in cameras}
    stereo = cv2.stereoCalibrate([target.astype(np.float32)] * len(views),
                                 [v[0].astype(np.float32) for v in views], [v[1].astype(np.float32) for v in views],
                                 cameras["L"].K, distortion["L"], cameras["R"].K, distortion["R"], (1000, 800),
                                 flags=cv2.CALIB_FIX_INTRINSIC,
                                 criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-15))
    R_cv, t_cv = stereo[5], stereo[6].ravel()  # cam_R_from_cam_L
    assert rotation_error(ours.R, R_cv) < 1e-6
    assert np.linalg.norm(ours.t - t_cv) < 2e-6

    std = result.ba.std["R"]
    assert rotation_error(ours.R, truth.R) < 4 * np.radians(np.linalg.norm(std["rotation_deg"]))
    assert rotation_error(R_cv, truth.R) < 4 * np.radians(np.linalg.norm(std["rotation_deg"]))
    truth_centre = truth.center
    assert np.linalg.norm(ours.center - truth_centre) < 4 * np.linalg.norm(std["center_m"])
    assert np.linalg.norm(-R_cv.T @ t_cv - truth_centre) < 4 * np.linalg.norm(std["center_m"])
    assert 0 < np.linalg.norm(std["center_m"]) < 2e-3


def test_calibration_covariance_carries_the_intrinsics_errors_into_the_rig(calibrated):
    """rig.json's joint covariance: the rig adjustment's sensitivity to each camera's intrinsics is
    its response when it is solved again with one intrinsic moved (finite differences), and the
    rig's covariance grows by S K S^T over the intrinsics-held one."""
    from dmais_pipe.calib.extrinsics import calibration_covariance
    from dmais_pipe.geometry import log_so3

    dataset, results, _ = calibrated
    workspace = Workspace.open(dataset, results)
    observations, cameras, sigma, std, survey, _, pixel = extrinsics._inputs(workspace, 0.0)
    ds = workspace.dataset

    def solve(cams):
        return calibrate_extrinsics(cams, ds.reference_camera, ds.images_of("extrinsics"), observations, ds.points,
                                    use_priors=True, pixel_sigma=sigma, backend="scipy").ba

    base = solve(cameras)
    precision = 2 * solver_precision(base, ds.points)  # two solves: the base and the moved one
    for camera, name, step in [("C0", "cx", 2.0), ("C0", "d", 0.01), ("C3", "fy", 5.0)]:
        moved = solve({**cameras, camera: dataclasses.replace(cameras[camera],
                                                              **{name: getattr(cameras[camera], name) + step})})
        column = 5 * base.intrinsics_cameras.index(camera) + ("fx", "fy", "cx", "cy", "d").index(name)
        for other in ("C2", "C3"):
            k = base.camera_parameters.index(f"{other}.rx")
            change = np.r_[log_so3(moved.rig_from_cam[other].R @ base.rig_from_cam[other].R.T),
                           moved.rig_from_cam[other].t - base.rig_from_cam[other].t]
            predicted = base.intrinsics_sensitivity[k:k + 6, column] * step
            for part, share in ((slice(0, 3), 0.02), (slice(3, 6), 0.05)):  # rotations (rad), centres (m)
                np.testing.assert_array_less(np.abs(change[part] - predicted[part]),
                                             share * np.abs(predicted[part]).max() + precision[part])
    labels, matrix = calibration_covariance(base, std, survey, pixel)
    assert labels[:5] == [f"{base.intrinsics_cameras[0]}.{k}" for k in ("fx", "fy", "cx", "cy", "d")]
    rig = slice(5 * len(base.intrinsics_cameras), None)
    assert labels[rig] == base.camera_parameters
    assert np.all(np.diag(matrix[rig, rig]) >= np.diag(base.camera_covariance))
    assert np.linalg.eigvalsh(matrix).min() > -1e-9 * np.abs(matrix).max()
    written = json.loads((results / "rig.json").read_text())["calibration_covariance"]
    assert written["parameters"] == labels


def test_the_rig_responds_to_its_control_points_survey_errors(calibrated):
    """The rig adjustment holds the control points at their surveyed coordinates: its survey response
    is its change when one point is moved by its survey sigma (solved again), and rig.json's joint
    covariance is that of the errors' generative model, intrinsics and rig moved by the same points."""
    from dmais_pipe.calib.extrinsics import calibration_covariance
    from dmais_pipe.geometry import log_so3

    dataset, results, _ = calibrated
    workspace = Workspace.open(dataset, results)
    observations, cameras, sigma, std, survey, _, pixel = extrinsics._inputs(workspace, 0.0)
    ds = workspace.dataset

    def solve(points):
        return calibrate_extrinsics(cameras, ds.reference_camera, ds.images_of("extrinsics"), observations, points,
                                    use_priors=True, pixel_sigma=sigma, backend="scipy").ba

    base = solve(ds.points)
    precision = 2 * solver_precision(base, ds.points)  # two solves: the base and the moved one
    assert len(base.survey_points) > 10 and base.survey_response.shape == (6 * 4, 3 * len(base.survey_points))
    seen = observations[observations["image"].isin(ds.images_of("extrinsics")["image"])]
    point = seen["point_id"].value_counts().index[0]  # the point most seen
    for axis in range(3):
        moved = ds.points.copy()
        moved.loc[point, ["x", "y", "z"][axis]] += moved.loc[point, "sigma_m"]
        again = solve(moved)
        column = 3 * base.survey_points.index(point) + axis
        for other in ("C1", "C3"):
            k = base.camera_parameters.index(f"{other}.rx")
            change = np.r_[log_so3(again.rig_from_cam[other].R @ base.rig_from_cam[other].R.T),
                           again.rig_from_cam[other].t - base.rig_from_cam[other].t]
            predicted = base.survey_response[k:k + 6, column]
            np.testing.assert_array_less(np.abs(change - predicted), 0.05 * np.abs(predicted).max() + precision)
    # the joint covariance is M M^T of the model: intrinsics -Z u + d, rig S (-Z u + d) + R u + e
    labels, matrix = calibration_covariance(base, std, survey, pixel)
    D, Z, points = extrinsics_module._intrinsics_parts(base.intrinsics_parameters, std, survey,
                                                       base.survey_points, pixel)
    assert set(pixel) == set(base.intrinsics_cameras)  # every camera's record has its pixel covariance
    for camera in base.intrinsics_cameras:  # its diagonal is the variance less the survey's share
        rows = [k for k, label in enumerate(base.intrinsics_parameters) if label.startswith(f"{camera}.")]
        names = [base.intrinsics_parameters[k].rsplit(".", 1)[1] for k in rows]
        variance = np.array([std[camera][name] ** 2 for name in names])
        np.testing.assert_allclose(np.diag(D)[rows], variance - np.sum(Z[rows] ** 2, axis=1), rtol=1e-9,
                                   atol=1e-9 * variance.max())
    R = np.zeros((len(base.camera_parameters), len(points) * 3))
    for k, p in enumerate(base.survey_points):
        R[:, 3 * points.index(p):3 * points.index(p) + 3] = base.survey_response[:, 3 * k:3 * k + 3]
    S = base.intrinsics_sensitivity
    e = np.linalg.cholesky(base.camera_covariance + 1e-30 * np.eye(len(R)))
    values, vectors = np.linalg.eigh(D)
    d = vectors * np.sqrt(np.clip(values, 0.0, None))
    M = np.block([[-Z, d, np.zeros((len(D), len(R)))],
                  [-(S @ Z) + R, S @ d, e]])
    np.testing.assert_allclose(matrix, M @ M.T, rtol=1e-9, atol=1e-12 * np.abs(matrix).max())
    assert np.linalg.eigvalsh(matrix).min() > -1e-9 * np.abs(matrix).max()


def test_survey_table_names_the_given_sigmas(calibrated):
    """tables/survey_sigma.csv: a row per camera's intrinsics and the rig's, every point's sigma given
    (the simulator's field survey, 1 mm) and none estimated."""
    _, results, written = calibrated
    table = pd.read_csv(results / "tables" / "survey_sigma.csv")
    assert results / "tables" / "survey_sigma.csv" in written
    assert list(table["calibration"]) == ["C0", "C1", "C2", "C3", "C4", "rig", "field"]
    assert (table["points_given"] > 5).all() and (table["points_estimated"] == 0).all()
    np.testing.assert_allclose(table["sigma_given_max_m"], 0.001)
    assert table["sigma_estimated_m"].isna().all()


def test_one_survey_sigma_for_the_field_rescales_a_cameras_estimated_effects():
    """with_field_survey_sigma: a camera's effects of the points it estimated scale by the field's sigma
    over its own, those of given points stay, and each variance keeps its pixel share."""
    from dmais_pipe.calib.extrinsics import with_field_survey_sigma

    effect = {"A": np.full((2, 3), 0.1), "B": np.full((2, 3), 0.2)}
    std = {"C1": {"fx": 1.0, "fy": 2.0}}
    pixel = np.array([1.0, 4.0]) - 3 * (0.1**2 + 0.2**2)
    new_std, new_effect = with_field_survey_sigma(std, {"C1": effect}, {"C1": 0.002}, 0.003, {"A"})
    np.testing.assert_allclose(new_effect["C1"]["A"], 0.15)
    np.testing.assert_allclose(new_effect["C1"]["B"], 0.2)
    np.testing.assert_allclose([new_std["C1"]["fx"] ** 2, new_std["C1"]["fy"] ** 2], pixel + 3 * (0.15**2 + 0.2**2))
    assert with_field_survey_sigma(std, {"C1": effect}, {"C1": None}, 0.003, {"A"}) == (std, {"C1": effect})


def test_a_field_without_survey_sigmas_has_its_sigma_estimated(calibrated, tmp_path):
    """The same dataset with control_points.csv's sigma_m left out: every calibration estimates the
    field's survey sigma (the simulator drew 1 mm), rig.json's covariance carries the cameras' pooled
    estimate, and the rig's rotations' sigmas are those of the run given 1 mm within a third."""
    dataset, results, _ = calibrated
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    control = pd.read_csv(copy / "control_points.csv", dtype={"point_id": str})
    control.drop(columns=["sigma_m"]).to_csv(copy / "control_points.csv", index=False)
    workspace = Workspace.open(copy, tmp_path / "results")
    intrinsics.run(workspace, intrinsics.CONFS["ours"])
    extrinsics.run(workspace)
    table = pd.read_csv(tmp_path / "results" / "tables" / "survey_sigma.csv").set_index("calibration")
    assert (table["points_given"] == 0).all() and (table["points_estimated"] > 5).all()
    assert table["sigma_estimated_m"].between(0.0006, 0.0016).all(), table
    cameras = table.loc[["C0", "C1", "C2", "C3", "C4"]]
    weights = [json.loads((tmp_path / "results" / "intrinsics" / f"{c}.json").read_text())["n_observations"]
               for c in cameras.index]
    assert table.loc["field", "sigma_estimated_m"] == pytest.approx(
        np.sqrt(np.average(cameras["sigma_estimated_m"] ** 2, weights=weights)))

    def rotation_sigmas(folder):
        cov = json.loads((folder / "rig.json").read_text())["calibration_covariance"]
        sigma = dict(zip(cov["parameters"], np.sqrt(np.diag(cov["matrix"]))))
        return np.array([sigma[k] for k in cov["parameters"] if k.rsplit(".", 1)[1] in ("rx", "ry", "rz")])

    ratio = rotation_sigmas(tmp_path / "results") / rotation_sigmas(results)
    assert 0.67 < np.median(ratio) < 1.5, ratio
