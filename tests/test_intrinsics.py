"""Intrinsic calibration (paper: PnPf -> mean f -> PnP -> LM, eq. refine) against truth and OpenCV."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.spatial.transform import Rotation

from dmais_pipe.calib.intrinsics import (
    calibrate_camera, calibrate_camera_dlt_lm, calibrate_camera_opencv,
)
from dmais_pipe.camera import Camera
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3, rotation_error
from dmais_pipe.rig import Rig
from dmais_pipe.stages import intrinsics
from dmais_pipe.workspace import Workspace

from conftest import observation_only

SIM = observation_only("intrinsics-small", seed=11, calib_images=6, eval_images=2, frames_per_group=1)
JSON_KEYS = {"camera", "width", "height", "fx", "fy", "cx", "cy", "d", "std", "eps_calib_px", "eps_eval_px",
             "n_images", "n_observations"}

# An ordinary wide-angle camera with strong barrel distortion.
WIDE = Camera(fx=505.0, fy=502.0, cx=317.5, cy=243.0, d=-0.3, width=640, height=480)


@pytest.fixture(scope="module")
def simulated(simulated_dataset, tmp_path_factory):
    dataset = simulated_dataset(SIM)
    results = tmp_path_factory.mktemp("intrinsics") / "results"
    written = intrinsics.run(Workspace.open(dataset, results))
    return dataset, results, written


def test_residual_file_is_observed_minus_projected_and_gives_the_per_image_rms(simulated):
    """intrinsics/<camera>.residuals.csv against an independent projection with the JSON's camera and poses."""
    dataset, results, _ = simulated
    workspace = Workspace.open(dataset, results)
    points = workspace.dataset.points
    for name in ("C0", "C3"):
        camera, record = workspace.load_intrinsics(name)
        residuals = workspace.load_calibration_residuals(name)
        assert set(residuals["split"]) == {"calib", "eval"}
        poses = {**record["poses"], **record["eval_poses"]}
        assert set(residuals["image"]) == set(poses)
        for image, rows in residuals.groupby("image"):
            pose = Rigid3.from_dict(poses[image])
            projected = camera.project(pose.apply(points.loc[rows["point_id"], ["x", "y", "z"]].to_numpy(float)))
            observed = rows[["u", "v"]].to_numpy(float)
            np.testing.assert_allclose(observed - rows[["du", "dv"]].to_numpy(float), projected, atol=1e-5)
            rms = np.sqrt(np.mean(rows["du"] ** 2 + rows["dv"] ** 2))
            split = rows["split"].iloc[0]
            assert rms == pytest.approx(record[f"image_eps_{split}_px"][image], rel=1e-9)
        calib = residuals[residuals["split"] == "calib"]
        assert len(calib) == record["n_observations"]
        assert np.sqrt(np.mean(calib["du"] ** 2 + calib["dv"] ** 2)) == pytest.approx(record["eps_calib_px"])


def test_per_camera_runs_and_table_equal_one_run(simulated, tmp_path):
    dataset, results, _ = simulated
    for camera in ("C3", "C0", "C1", "C2", "C4"):
        intrinsics.run_cameras(Workspace.open(dataset, tmp_path), [camera])
    assert not (tmp_path / "tables" / "intrinsics.csv").exists()
    pd.testing.assert_frame_equal(pd.read_csv(intrinsics.write_table(Workspace.open(dataset, tmp_path))[0]),
                                  pd.read_csv(results / "tables" / "intrinsics.csv"))
    assert (json.loads((tmp_path / "intrinsics" / "C3.json").read_text())
            == json.loads((results / "intrinsics" / "C3.json").read_text()))


def test_table_names_a_camera_not_calibrated_yet(simulated, tmp_path):
    dataset, _, _ = simulated
    intrinsics.run_cameras(Workspace.open(dataset, tmp_path), ["C0"])
    with pytest.raises(DmaisError, match="C1.methods.csv"):
        intrinsics.write_table(Workspace.open(dataset, tmp_path))[0]
    with pytest.raises(DmaisError, match="C9"):
        intrinsics.run_cameras(Workspace.open(dataset, tmp_path), ["C9"])


def test_intrinsics_stage_writes_json_and_table(simulated):
    dataset, results, written = simulated
    names = ["C0", "C1", "C2", "C3", "C4"]
    assert set(written) == ({results / "intrinsics" / f"{c}.json" for c in names}
                            | {results / "intrinsics" / f"{c}.methods.csv" for c in names}
                            | {results / "intrinsics" / f"{c}.residuals.csv" for c in names}
                            | {results / "tables" / "intrinsics.csv"})
    for name in names:
        data = json.loads((results / "intrinsics" / f"{name}.json").read_text())
        assert JSON_KEYS <= set(data)
        assert data["camera"] == name and (data["width"], data["height"]) == (4096, 3000)
        assert data["n_images"] == 6 and set(data["std"]) == {"fx", "fy", "cx", "cy", "d"}
        assert all(0 < v < np.inf for v in data["std"].values())
    table = pd.read_csv(results / "tables" / "intrinsics.csv")
    assert list(table.columns) == ["method", "camera", "fx", "fy", "cx", "cy", "d", "eps_calib_px", "eps_eval_px"]
    assert len(table) == 15 and set(table["method"]) == {"ours", "opencv", "dlt_lm"}


def test_focal_within_0_15_percent_and_eval_no_worse_than_opencv(simulated):
    dataset, results, _ = simulated
    truth = Rig.load(dataset / "truth" / "rig.json").cameras
    table = pd.read_csv(results / "tables" / "intrinsics.csv").set_index(["method", "camera"])
    for name, camera in truth.items():
        ours = table.loc[("ours", name)]
        assert abs(ours.fx / camera.fx - 1) < 0.0015, name
        assert abs(ours.fy / camera.fy - 1) < 0.0015, name
        assert abs(ours.cx - camera.cx) < 40 and abs(ours.cy - camera.cy) < 40, name
        assert abs(ours.d - camera.d) < 0.5, name
        assert 0.15 < ours.eps_calib_px < 0.6 and 0.15 < ours.eps_eval_px < 0.6, name
        opencv = table.loc[("opencv", name)]
        # Both minimise the same cost; when OpenCV converges they agree to ~1e-4 px, so allow 0.1 %.
        assert ours.eps_eval_px <= opencv.eps_eval_px * 1.001, name


def test_calib_poses_match_truth(simulated):
    dataset, results, _ = simulated
    truth = pd.read_csv(dataset / "truth" / "images.csv").set_index("image")
    data = json.loads((results / "intrinsics" / "C0.json").read_text())
    for image, pose in {**data["poses"], **data["eval_poses"]}.items():
        row = truth.loc[image]
        true = Rigid3.from_quat([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz])
        # the attitude error follows the principal-point error (15 px at f = 45000 px is 1.1 arc-min)
        assert np.degrees(rotation_error(np.array(pose["R"]), true.R)) * 60 < 3.0  # arc-min
        assert np.linalg.norm(Rigid3.from_dict(pose).center - true.center) < 1.0  # metres, at 130-280 m


# ------------------------------------------------------------------------------ planar and wide-angle


def board_views(camera: Camera, n_views: int, rng, noise: float = 0.1):
    """A 10 x 7 chessboard (z = 0, 3 cm squares) seen tilted by 20-45 deg from 0.35-0.6 m."""
    gx, gy = np.meshgrid(np.arange(10) * 0.03, np.arange(7) * 0.03)
    board = np.column_stack([gx.ravel() - 0.135, gy.ravel() - 0.09, np.zeros(gx.size)])
    points, pixels, poses = {}, {}, {}
    while len(points) < n_views:
        tilt = np.radians(rng.uniform(20, 45))
        axis_angle = rng.uniform(0, 2 * np.pi)
        R = (Rotation.from_rotvec(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]))
             * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi))).as_matrix()
        depth = rng.uniform(0.35, 0.6)
        t = np.array([rng.uniform(-0.12, 0.12) * depth / 0.5, rng.uniform(-0.08, 0.08) * depth / 0.5, depth])
        pose = Rigid3(R, t)
        seen = _observed(camera, board, pose.apply(board), rng, noise)
        if seen is None:
            continue
        name = f"view{len(points)}"
        points[name], pixels[name] = seen
        poses[name] = pose
    return points, pixels, poses


def _observed(camera: Camera, points: np.ndarray, points_cam: np.ndarray, rng, noise: float):
    """The points (n, 3) whose camera-frame positions points_cam (n, 3) land in the image, and their
    pixels with Gaussian noise; None when fewer than 30 do."""
    uv = camera.project(points_cam)
    keep = np.isfinite(uv).all(axis=1) & camera.in_image(np.nan_to_num(uv, nan=-1e9), margin=2)
    if keep.sum() < 30:
        return None
    return points[keep], uv[keep] + rng.normal(scale=noise, size=(keep.sum(), 2))


def field_views(camera: Camera, n_views: int, rng, noise: float = 0.1):
    """A 3D field (random points in a 3 x 2 x 1.5 m box) seen from 2.5-4 m."""
    field = rng.uniform([-1.5, -1.0, -0.75], [1.5, 1.0, 0.75], size=(120, 3))
    points, pixels = {}, {}
    while len(points) < n_views:
        R = Rotation.from_euler("xyz", rng.uniform(-0.4, 0.4, 3)).as_matrix()
        t = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(2.5, 4.0)])
        seen = _observed(camera, field, field @ R.T + t, rng, noise)
        if seen is None:
            continue
        name = f"view{len(points)}"
        points[name], pixels[name] = seen
    return points, pixels


def assert_close_to(camera: Camera, truth: Camera, focal_rel: float, centre_px: float, d_abs: float):
    assert abs(camera.fx / truth.fx - 1) < focal_rel and abs(camera.fy / truth.fy - 1) < focal_rel
    assert abs(camera.cx - truth.cx) < centre_px and abs(camera.cy - truth.cy) < centre_px
    assert abs(camera.d - truth.d) < d_abs


def test_planar_chessboard_wide_angle_matches_truth_and_opencv():
    rng = np.random.default_rng(21)
    points, pixels, poses = board_views(WIDE, 12, rng)
    calib = {k: points[k] for k in list(points)[:10]}
    evals = {k: points[k] for k in list(points)[10:]}
    result = calibrate_camera(calib, {k: pixels[k] for k in calib}, WIDE.width, WIDE.height,
                              eval_points_world_per_image=evals, eval_uv_per_image={k: pixels[k] for k in evals},
                              name="wide")
    assert_close_to(result.camera, WIDE, focal_rel=0.003, centre_px=1.0, d_abs=0.005)
    # 0.1 px per axis: the RMS point distance is ~0.1 * sqrt(2) = 0.14 px
    assert 0.11 < result.eps_calib_px < 0.16 and 0.08 < result.eps_eval_px < 0.2
    for name, pose in result.poses.items():
        assert np.degrees(rotation_error(pose.R, poses[name].R)) < 0.1
    # OpenCV's planar calibration (Zhang init) with the same model reaches the same optimum.
    opencv = calibrate_camera_opencv(calib, {k: pixels[k] for k in calib}, WIDE.width, WIDE.height, 400.0)
    for key in ("fx", "fy", "cx", "cy"):
        assert getattr(result.camera, key) == pytest.approx(getattr(opencv.camera, key), abs=3 * result.std[key])
    assert result.camera.d == pytest.approx(opencv.camera.d, abs=3 * result.std["d"])
    assert result.eps_calib_px == pytest.approx(opencv.eps_calib_px, rel=1e-3)
    # the reported standard deviations are the actual errors' size
    for key in ("fx", "fy", "cx", "cy", "d"):
        assert abs(getattr(result.camera, key) - getattr(WIDE, key)) < 5 * result.std[key], key


CHESSBOARD = Path(__file__).parent / "data" / "chessboard"  # OpenCV sample photographs, see its README.md


def chessboard_observations(names) -> tuple[dict, dict]:
    """Board points (54, 3) and detected inner corners (54, 2) per photograph: findChessboardCorners + cornerSubPix."""
    gx, gy = np.meshgrid(np.arange(9), np.arange(6))
    board = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]) * 0.025
    points, pixels = {}, {}
    for name in names:
        image = cv2.imread(str(CHESSBOARD / f"{name}.jpg"), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(image, (9, 6))
        assert found and image.shape == (480, 640), name
        corners = cv2.cornerSubPix(image, corners, (11, 11), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
        points[name], pixels[name] = board, corners.reshape(-1, 2).astype(float)
    return points, pixels


def test_real_chessboard_photographs_match_opencv():
    """Real photographs (a 640 x 480 wide-angle camera, d ~ -0.26): our planar path and cv2.calibrateCamera with the
    same model (k1 only) agree within OpenCV's own standard deviations; measured 1.5e-5 of them, so 1e-3."""
    calib_names = [f"left0{k}" for k in range(1, 9)]
    points, pixels = chessboard_observations(calib_names + ["left09", "left11"])
    calib = {k: points[k] for k in calib_names}
    evals = {k: points[k] for k in ("left09", "left11")}
    ours = calibrate_camera(calib, {k: pixels[k] for k in calib}, 640, 480, name="left",
                            eval_points_world_per_image=evals, eval_uv_per_image={k: pixels[k] for k in evals})
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, _, _, std, _, _ = cv2.calibrateCameraExtended(
        [calib[k].astype(np.float32) for k in calib_names], [pixels[k].astype(np.float32) for k in calib_names],
        (640, 480), None, None, flags=flags, criteria=criteria)
    opencv = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "d": dist.ravel()[0]}
    opencv_std = dict(zip(("fx", "fy", "cx", "cy", "d"), std.ravel()[:5]))
    assert 500 < opencv["fx"] < 560 and -0.3 < opencv["d"] < -0.2  # a real wide-angle lens, not a degenerate fit
    for key, value in opencv.items():
        assert abs(getattr(ours.camera, key) - value) < 1e-3 * opencv_std[key], key
        assert ours.std[key] == pytest.approx(opencv_std[key], rel=1e-3), key
    assert ours.eps_calib_px == pytest.approx(rms, rel=1e-6)  # both the RMS per-point distance
    baseline = calibrate_camera_opencv(calib, {k: pixels[k] for k in calib}, 640, 480, 500.0, name="left",
                                       eval_points_world_per_image=evals,
                                       eval_uv_per_image={k: pixels[k] for k in evals})
    assert 0.1 < ours.eps_eval_px < 1.0
    assert ours.eps_eval_px == pytest.approx(baseline.eps_eval_px, rel=1e-4)


def test_3d_field_wide_angle_and_dlt_baseline():
    rng = np.random.default_rng(4)
    points, pixels = field_views(WIDE, 6, rng)
    result = calibrate_camera(points, pixels, WIDE.width, WIDE.height, name="wide3d")
    assert_close_to(result.camera, WIDE, focal_rel=0.003, centre_px=1.0, d_abs=0.005)
    dlt = calibrate_camera_dlt_lm(points, pixels, WIDE.width, WIDE.height, name="wide3d")
    assert dlt.camera.fx == pytest.approx(result.camera.fx, rel=1e-6)
    assert dlt.eps_calib_px == pytest.approx(result.eps_calib_px, rel=1e-6)


def test_noise_free_recovers_exactly():
    rng = np.random.default_rng(8)
    points, pixels = field_views(WIDE, 4, rng, noise=0.0)
    result = calibrate_camera(points, pixels, WIDE.width, WIDE.height)
    assert_close_to(result.camera, WIDE, focal_rel=1e-8, centre_px=1e-5, d_abs=1e-8)
    assert result.eps_calib_px < 1e-6


# ------------------------------------------------------------------------------ bad input


def test_too_few_images_names_the_camera():
    rng = np.random.default_rng(2)
    points, pixels = field_views(WIDE, 2, rng)
    with pytest.raises(DmaisError, match="camera CX: 1 usable calibration image"):
        calibrate_camera({"a": points["view0"]}, {"a": pixels["view0"]}, 640, 480, name="CX")
    with pytest.raises(DmaisError, match="camera CX: 0 usable"):
        calibrate_camera({}, {}, 640, 480, name="CX")


def test_images_with_few_observations_are_skipped_with_one_warning(caplog):
    rng = np.random.default_rng(3)
    points, pixels = field_views(WIDE, 4, rng)
    for name in ("tiny1", "tiny2"):
        points[name], pixels[name] = points["view0"][:4], pixels["view0"][:4]
    points["tiny_eval"], pixels["tiny_eval"] = points["view1"][:3], pixels["view1"][:3]
    with caplog.at_level(logging.WARNING, logger="dmais_pipe.calib.intrinsics"):
        result = calibrate_camera({k: points[k] for k in list(points)[:-1]}, {k: pixels[k] for k in list(points)[:-1]},
                                  640, 480, eval_points_world_per_image={"tiny_eval": points["tiny_eval"]},
                                  eval_uv_per_image={"tiny_eval": pixels["tiny_eval"]}, name="CW")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert all(name in warnings[0].getMessage() for name in ("CW", "tiny1", "tiny2", "tiny_eval"))
    assert result.n_images == 4 and result.skipped_images == ["tiny1", "tiny2", "tiny_eval"]
    assert result.eps_eval_px is None


def test_non_finite_observation_names_the_row():
    rng = np.random.default_rng(3)
    points, pixels = field_views(WIDE, 3, rng)
    pixels["view1"][7, 0] = np.inf
    with pytest.raises(DmaisError, match="camera CN, image view1: observation 7 is not finite"):
        calibrate_camera(points, pixels, 640, 480, name="CN")


def test_stage_skips_sparse_images_and_names_a_camera_without_enough(simulated, tmp_path, caplog):
    """Through the intrinsics stage: C1 loses two calib images (4 and 1 observations left) and an eval image (3): one
    warning lists them and C1 is calibrated on the rest; C2 keeps one usable calib image: an error naming C2."""
    dataset, _, _ = simulated
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    images = pd.read_csv(copy / "images.csv")
    obs = pd.read_csv(copy / "observations.csv")

    def of(camera, split):
        return images.loc[(images.camera == camera) & (images["split"] == split), "image"].tolist()

    c1, c1_eval, c2 = of("C1", "calib"), of("C1", "eval"), of("C2", "calib")
    keep = {c1[0]: 4, c1[1]: 1, c1_eval[0]: 3, **{image: 4 for image in c2[1:]}}
    rank = obs.groupby("image").cumcount()
    obs[rank < obs["image"].map(keep).fillna(np.inf)].to_csv(copy / "observations.csv", index=False)
    results = tmp_path / "results"
    with caplog.at_level(logging.WARNING, logger="dmais_pipe.calib.intrinsics"):
        with pytest.raises(DmaisError, match=r"camera C2: 1 usable calibration image\(s\)"):
            intrinsics.run(Workspace.open(copy, results))
    sparse = [r.getMessage() for r in caplog.records if "fewer than 5 observations" in r.getMessage()]
    c1_warnings = [m for m in sparse if m.startswith("camera C1:")]
    assert len(c1_warnings) == 1 and "3 image(s)" in c1_warnings[0], sparse
    assert all(image in c1_warnings[0] for image in (c1[0], c1[1], c1_eval[0]))
    assert not any(m.startswith(("camera C0:", "camera C3:", "camera C4:")) for m in sparse)
    data = json.loads((results / "intrinsics" / "C1.json").read_text())
    assert sorted(data["skipped_images"]) == sorted([c1[0], c1[1], c1_eval[0]])
    assert data["n_images"] == len(c1) - 2 and data["n_eval_images"] == len(c1_eval) - 1
    assert not (results / "intrinsics" / "C2.json").exists()
    assert not (results / "tables" / "intrinsics.csv").exists()


def test_dataset_with_non_finite_observation_is_rejected_naming_the_line(simulated, tmp_path):
    dataset, _, _ = simulated
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    obs = (copy / "observations.csv").read_text().splitlines()
    fields = obs[3].split(",")
    fields[-1] = "nan"
    obs[3] = ",".join(fields)
    (copy / "observations.csv").write_text("\n".join(obs) + "\n")
    with pytest.raises(DmaisError, match=r"observations.csv, line 4"):
        intrinsics.run(Workspace.open(copy, tmp_path / "results"))
    assert not (tmp_path / "results" / "tables").exists()


# ------------------------------------------------------------------------------ absurd results


def test_pnpf_focal_lengths_that_disagree_are_refused_naming_the_images():
    """Two of four views zoomed by 2 about the image centre: no majority of PnPf focal lengths
    within 20% of their median, so no mean is taken from outliers."""
    rng = np.random.default_rng(4)
    points, pixels = field_views(WIDE, 4, rng, noise=0.0)
    centre = np.array([WIDE.cx, WIDE.cy])
    for name in ("view1", "view3"):
        pixels[name] = centre + 2.0 * (pixels[name] - centre)
    with pytest.raises(DmaisError, match=r"camera CZ: the PnPf focal lengths disagree, only 0 of 4 images .*view1 "):
        calibrate_camera(points, pixels, WIDE.width, WIDE.height, name="CZ")


def test_absurd_calibration_stops_the_stage_and_keeps_the_earlier_result(simulated, tmp_path):
    """Point ids shuffled within two calibration images of C0 (every pixel stays inside the image):
    eps_calib far beyond the limit; the stage names C0 and those images and leaves C0's files."""
    dataset, _, _ = simulated
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    results = tmp_path / "results"
    intrinsics.run_cameras(Workspace.open(copy, results), ["C0"])
    written = {p.name: p.read_bytes() for p in (results / "intrinsics").iterdir()}

    images = pd.read_csv(copy / "images.csv")
    bad = images.loc[(images.camera == "C0") & (images["split"] == "calib"), "image"].tolist()[1:3]
    obs = pd.read_csv(copy / "observations.csv", dtype={"point_id": str})
    rng = np.random.default_rng(0)
    for image in bad:
        rows = obs.index[obs["image"] == image]
        obs.loc[rows, "point_id"] = rng.permutation(obs.loc[rows, "point_id"].to_numpy())
    obs.to_csv(copy / "observations.csv", index=False)
    with pytest.raises(DmaisError) as info:
        intrinsics.run_cameras(Workspace.open(copy, results), ["C0"])
    message = str(info.value)
    assert message.startswith("camera C0: calibration refused, eps_calib ") and "exceeds 5 px" in message
    worst = message.split("worst images: ")[1]
    assert worst.startswith(tuple(bad)) and all(image in worst for image in bad), message
    assert {p.name: p.read_bytes() for p in (results / "intrinsics").iterdir()} == written


def test_a_focal_far_from_the_manifest_is_refused(simulated, tmp_path):
    dataset, _, _ = simulated
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    manifest = yaml.safe_load((copy / "dataset.yaml").read_text())
    manifest["cameras"]["C2"]["focal_px"] = 30000.0
    (copy / "dataset.yaml").write_text(yaml.safe_dump(manifest))
    with pytest.raises(DmaisError, match=r"camera C2: calibration refused, fx 4\d{4}\.\d px is \d+% from focal_px "
                                         r"30000; fy .*\(worst images: intr_C2_"):
        intrinsics.run_cameras(Workspace.open(copy, tmp_path / "results"), ["C2"])
    assert not (tmp_path / "results" / "intrinsics" / "C2.json").exists()


# ------------------------------------------------------------------------------ survey errors of the field


def surveyed_field_views(camera: Camera, n_views: int, rng):
    """A 3D field of 60 points seen from 2.5-4 m, noise-free: its points (P, 3), and per view the
    rows of the field it sees and its cam_from_world."""
    field = rng.uniform([-1.5, -1.0, -0.75], [1.5, 1.0, 0.75], size=(60, 3))
    rows, poses = {}, {}
    while len(rows) < n_views:
        pose = Rigid3(Rotation.from_euler("xyz", rng.uniform(-0.4, 0.4, 3)).as_matrix(),
                      np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(2.5, 4.0)]))
        uv = camera.project(pose.apply(field))
        seen = np.flatnonzero(np.isfinite(uv).all(axis=1) & camera.in_image(np.nan_to_num(uv, nan=-1e9), margin=2))
        if len(seen) >= 30:
            name = f"view{len(rows)}"
            rows[name], poses[name] = seen, pose
    return field, rows, poses


def test_intrinsics_estimate_the_fields_survey_sigma_where_none_is_given():
    """As above with the survey sigma not given (NaN): the calibration estimates it from its residuals
    (3 mm drawn, 0.05 px), and the covariance with the estimate predicts the focal length's spread,
    where the exact points' covariance (the sigma taken as 0) predicts a fraction of it."""
    from dmais_pipe.calib.intrinsics import bundle_adjust

    rng = np.random.default_rng(22)
    field, rows, poses = surveyed_field_views(WIDE, 8, rng)
    survey, noise = 0.003, 0.05
    focal, predicted, estimates, exact = [], [], [], []
    for _ in range(60):
        surveyed = field + rng.normal(scale=survey, size=field.shape)
        data = {k: (surveyed[r], WIDE.project(poses[k].apply(field[r])) + rng.normal(scale=noise, size=(len(r), 2)))
                for k, r in rows.items()}
        unknown = {k: (r.astype(str), np.full(len(r), np.nan)) for k, r in rows.items()}
        camera, _, _, cov, effect, estimated = bundle_adjust(WIDE, poses, data, unknown)
        assert sorted(effect) == sorted({str(k) for r in rows.values() for k in r})
        focal.append(camera.fx)
        predicted.append(np.sqrt(cov[0, 0]))
        estimates.append(estimated)
        exact.append(np.sqrt(bundle_adjust(WIDE, poses, data)[3][0, 0]))
    assert abs(np.sqrt(np.mean(np.square(estimates))) / survey - 1) < 0.1, np.percentile(estimates, [5, 50, 95])
    spread = np.std(focal)
    assert abs(np.mean(predicted) / spread - 1) < 0.25, (np.mean(predicted), spread)
    assert np.mean(exact) < 0.5 * spread


def test_intrinsics_sigma_carries_the_fields_survey_error():
    """The same field surveyed with 3 mm errors and imaged with 0.05 px noise, 150 times: the spread
    of the calibrated focal length is the covariance's with the survey sigma given, and several
    times the pixel-only covariance's (what the intrinsics reported before)."""
    from dmais_pipe.calib.intrinsics import bundle_adjust

    rng = np.random.default_rng(21)
    field, rows, poses = surveyed_field_views(WIDE, 8, rng)
    survey, noise = 0.003, 0.05
    focal, predicted, pixel_only = [], [], []
    for _ in range(150):
        surveyed = field + rng.normal(scale=survey, size=field.shape)
        data = {k: (surveyed[r], WIDE.project(poses[k].apply(field[r])) + rng.normal(scale=noise, size=(len(r), 2)))
                for k, r in rows.items()}
        sigmas = {k: (r.astype(str), np.full(len(r), survey)) for k, r in rows.items()}
        camera, _, _, cov, effect, estimated = bundle_adjust(WIDE, poses, data, sigmas)
        assert estimated is None  # every sigma given
        assert sorted(effect) == sorted({str(k) for r in rows.values() for k in r})
        stacked = np.hstack(list(effect.values()))  # (5, 3P): the survey's share of the covariance
        assert np.all(np.diag(stacked @ stacked.T) <= np.diag(cov) * (1 + 1e-12))
        focal.append(camera.fx)
        predicted.append(np.sqrt(cov[0, 0]))
        pixel_only.append(np.sqrt(bundle_adjust(WIDE, poses, data)[3][0, 0]))
    spread = np.std(focal)
    assert abs(np.mean(predicted) / spread - 1) < 0.2, (np.mean(predicted), spread)
    assert np.mean(pixel_only) < 0.5 * spread


def test_the_pixel_covariance_keeps_the_correlations_the_rig_needs():
    """The record's pixel_covariance (calibrate_camera: the covariance less the survey's share; 0.3 px
    of noise beside a 0.3 mm survey, its sigma estimated) predicts the spread of fx - fy over 40
    seeded calibrations, where the diagonal of the same variances (what the rig's calibration
    covariance took before: fx and fy move together) misses it by several times."""
    rng = np.random.default_rng(23)
    field, rows, poses = surveyed_field_views(WIDE, 8, rng)
    survey, noise = 0.0003, 0.3
    ids = {k: r.astype(str) for k, r in rows.items()}
    parameters, pixel, shared = [], [], []
    for _ in range(40):
        surveyed = field + rng.normal(scale=survey, size=field.shape)
        points = {k: surveyed[r] for k, r in rows.items()}
        pixels = {k: WIDE.project(poses[k].apply(field[r])) + rng.normal(scale=noise, size=(len(r), 2))
                  for k, r in rows.items()}
        result = calibrate_camera(points, pixels, WIDE.width, WIDE.height,
                                  survey={k: (ids[k], np.full(len(r), np.nan)) for k, r in rows.items()})
        effects = np.hstack(list(result.survey_effect.values()))
        np.testing.assert_allclose(np.diag(result.pixel_covariance) + np.sum(effects**2, axis=1),
                                   np.square([result.std[k] for k in WIDE.parameter_names]), rtol=1e-9)
        parameters.append(result.camera.parameters)
        pixel.append(result.pixel_covariance)
        shared.append(effects @ effects.T)
    a = np.array([1.0, -1.0, 0.0, 0.0, 0.0])  # fx - fy
    spread = np.std(np.asarray(parameters) @ a)
    whole = np.sqrt(np.mean([a @ (p + s) @ a for p, s in zip(pixel, shared)]))
    diagonal = np.sqrt(np.mean([a @ (np.diag(np.diag(p)) + s) @ a for p, s in zip(pixel, shared)]))
    assert abs(whole / spread - 1) < 0.25, (whole, spread)
    assert diagonal > 2 * spread, (diagonal, spread)
