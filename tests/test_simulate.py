"""The simulator: determinism, geometry of rig/field/flights, truth consistency, noise budget."""

from __future__ import annotations

import filecmp

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from dmais_pipe import cli
from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import ConfigError, DmaisError
from dmais_pipe.geometry import Rigid3, rotation_error
from dmais_pipe.rig import Rig
from dmais_pipe.sim.config import DEFAULTS, load_config, merge, settings_to_write
from dmais_pipe.sim.render import render_image
from dmais_pipe.sim.scene import build_rig, flight_frames
from dmais_pipe.sim.simulate import (build_world, flight_shots, markers_for, render_settings, simulate, stream,
                                     truth_observations)

from conftest import observation_only

SMALL = observation_only("small", seed=11, calib_images=2, eval_images=1, frames_per_group=2)


def write_config(path, settings) -> str:
    path.write_text(yaml.safe_dump(settings))
    return str(path)


@pytest.fixture(scope="module")
def small_dataset(simulated_dataset):
    return Dataset.load(simulated_dataset(SMALL))


def with_flight(settings: dict, **flight) -> dict:
    """A simulator settings mapping with more flight settings."""
    return {**settings, "flight": {**settings.get("flight", {}), **flight}}


def pose_from_row(row) -> Rigid3:
    return Rigid3.from_quat([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz])


def test_same_seed_same_dataset_other_seed_differs(tmp_path, small_dataset):
    again = simulate(write_config(tmp_path / "a.yaml", SMALL), tmp_path / "again")
    for name in ["dataset.yaml", "control_points.csv", "ground_points.csv", "images.csv", "frames.csv",
                 "observations.csv", "truth/observations.csv", "truth/images.csv", "truth/rig.json"]:
        assert filecmp.cmp(small_dataset.root / name, again / name, shallow=False), name
    other = simulate(write_config(tmp_path / "b.yaml", {**SMALL, "seed": 12}), tmp_path / "other")
    assert not filecmp.cmp(small_dataset.root / "observations.csv", other / "observations.csv", shallow=False)


def test_rig_is_like_the_papers(small_dataset):
    rig = Rig.load(small_dataset.truth_dir / "rig.json")
    assert rig.reference_camera == "C0" and rig.camera_names == ["C0", "C1", "C2", "C3", "C4"]
    np.testing.assert_allclose(rig.cam_from_rig["C0"].R, np.eye(3))
    for name, camera in rig.cameras.items():
        assert (camera.width, camera.height) == (4096, 3000)
        assert 43700 <= camera.fx <= 45600 and 43700 <= camera.fy <= 45600
        assert abs(camera.cx - 2048) < 50 and abs(camera.cy - 1500) < 50
        assert 1.5 < camera.d < 3.5
        if name != "C0":
            rig_from_cam = rig.cam_from_rig[name].inverse()
            tilt = np.degrees(np.arccos(rig_from_cam.R[2, 2]))
            assert 44.0 <= tilt <= 46.3  # tab:extrinsics_R known column: 44.04 ... 46.23 deg
            assert 0.1 <= np.linalg.norm(rig_from_cam.t) <= 0.2
    axes = np.array([rig.cam_from_rig[n].R[2] for n in ["C1", "C2", "C3", "C4"]])
    # forward, backward, left, right: the four tilted axes point in four directions 90 deg apart
    azimuths = np.sort(np.degrees(np.arctan2(axes[:, 1], axes[:, 0])) % 360)
    np.testing.assert_allclose(np.diff(azimuths), 90.0, atol=2.0)


def test_calibration_field(small_dataset):
    truth = pd.read_csv(small_dataset.truth_dir / "control_points.csv", dtype={"point_id": str})
    assert truth["z"].between(2.0, 10.0).all()
    regions = truth["point_id"].str[0]
    assert set(regions) == {"L", "C", "R"}
    boards = truth[truth["point_id"].str.contains("B")]
    assert len(boards) == 3 * 2 * 6  # two six-corner boards per region
    xyz = truth[["x", "y", "z"]].to_numpy()
    for region in "LCR":
        points = xyz[regions == region]
        singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
        assert singular[2] > 1.0  # metres: far from coplanar
    surveyed = small_dataset.control_points.loc[truth["point_id"], ["x", "y", "z"]].to_numpy()
    error = surveyed - xyz
    assert 0.0005 < error.std() < 0.002  # mm survey noise


def test_truth_observations_are_projections_of_the_truth(small_dataset):
    rig = Rig.load(small_dataset.truth_dir / "rig.json")
    points = pd.concat([
        pd.read_csv(small_dataset.truth_dir / name, dtype={"point_id": str})
        for name in ["control_points.csv", "ground_points.csv"]
    ]).set_index("point_id")
    images = pd.read_csv(small_dataset.truth_dir / "images.csv").set_index("image")
    truth = pd.read_csv(small_dataset.truth_dir / "observations.csv", dtype={"point_id": str})
    for image, obs in truth.groupby("image"):
        row = images.loc[image]
        uv = rig.cameras[row.camera].project(pose_from_row(row).apply(points.loc[obs["point_id"], ["x", "y", "z"]]))
        np.testing.assert_allclose(uv, obs[["u", "v"]].to_numpy(), atol=1e-6)
        assert rig.cameras[row.camera].in_image(uv, margin=19.9).all()


def test_flight_images_use_the_frame_pose_and_in_flight_mounting(small_dataset):
    truth = small_dataset.truth_dir
    frames = pd.read_csv(truth / "frames.csv", dtype={"frame": str, "group": str}).set_index("frame")
    mounts = pd.read_csv(truth / "flight_cam_from_rig.csv", dtype={"frame": str}).set_index(["frame", "camera"])
    images = pd.read_csv(truth / "images.csv").set_index("image")
    rig = Rig.load(truth / "rig.json")
    flight = small_dataset.images_of("flight")
    assert set(flight["placement"]) == set(frames.index)
    assert len(set(frames["group"])) == 5 and set(frames["site"]) == {"A", "B"}
    for row in flight.itertuples():
        rig_from_world = pose_from_row(frames.loc[row.placement])
        cam_from_rig = pose_from_row(mounts.loc[(row.placement, row.camera)])
        expected = cam_from_rig * rig_from_world
        actual = pose_from_row(images.loc[row.image])
        assert rotation_error(actual.R, expected.R) < 1e-12
        # the in-flight mounting deviates from the calibrated rig by arc-seconds, never degrees
        deviation = np.degrees(rotation_error(cam_from_rig.R, rig.cam_from_rig[row.camera].R)) * 60
        assert deviation < (1e-9 if row.camera == "C0" else 3.0)
        seen = small_dataset.observations.loc[small_dataset.observations["image"] == row.image, "point_id"]
        altitude = rig_from_world.center[2] - small_dataset.ground_points.loc[seen, "z"].mean()
        assert 320 < altitude < 380


def test_no_two_ground_markers_overlap(small_dataset):
    truth = pd.read_csv(small_dataset.truth_dir / "ground_points.csv", dtype={"point_id": str})
    xyz = truth[["x", "y", "z"]].to_numpy()
    distances = np.linalg.norm(xyz[:, None] - xyz[None], axis=2) + np.eye(len(xyz)) * 1e9
    assert distances.min() > 2 * np.sqrt(2) * small_dataset.marker_size_m / 2  # two half-diagonals


def test_pos_and_ins_priors(small_dataset):
    frames = small_dataset.frames.set_index("frame")
    truth = pd.read_csv(small_dataset.truth_dir / "frames.csv", dtype={"frame": str}).set_index("frame")
    lever = np.asarray(DEFAULTS["flight"]["lever_arm_m"])
    for frame, row in truth.iterrows():
        rig_from_world = pose_from_row(row)
        expected = rig_from_world.inverse().apply(lever)
        pos = frames.loc[frame, ["pos_x", "pos_y", "pos_z"]].to_numpy(float)
        assert np.linalg.norm(pos - expected) < 0.2
        ins = Rigid3.from_quat(frames.loc[frame, ["prior_qw", "prior_qx", "prior_qy", "prior_qz"]].to_numpy(float), np.zeros(3))
        assert np.degrees(rotation_error(ins.R, rig_from_world.R)) < 3.0


def test_extrinsic_placements_turn_the_rig_about_c0(small_dataset):
    images = small_dataset.images_of("extrinsics")
    placements = images.groupby("placement")["camera"].apply(set)
    assert len(placements) == 5
    assert all("C0" in cameras and len(cameras) == 3 for cameras in placements)
    for camera in ["C1", "C2", "C3", "C4"]:
        assert sum(camera in cameras for cameras in placements) >= 2
    truth = pd.read_csv(small_dataset.truth_dir / "images.csv").set_index("image")
    c0 = [pose_from_row(truth.loc[f"extr_p{j}_C0"]) for j in range(5)]
    for j in range(4):  # successive placements: C0 rolled by ~90 deg about its own optical axis
        rotvec = Rotation.from_matrix(c0[j + 1].R @ c0[j].R.T).as_rotvec()  # in C0's frame
        assert abs(np.degrees(np.linalg.norm(rotvec)) - 90) < 3
        assert abs(rotvec[2]) / np.linalg.norm(rotvec) > 0.999
    priors = images[["prior_x", "prior_y", "prior_z"]].to_numpy()
    centers = np.array([pose_from_row(truth.loc[i]).center for i in images["image"]])
    assert np.all(np.linalg.norm(priors - centers, axis=1) < 0.15)  # cm-level RTK


def test_intrinsic_splits(small_dataset):
    intrinsics = small_dataset.images_of("intrinsics")
    counts = intrinsics.groupby(["camera", "split"]).size().unstack()
    assert (counts["calib"] == 2).all() and (counts["eval"] == 1).all()
    per_image = small_dataset.observations.groupby("image").size()
    assert (per_image.loc[intrinsics["image"]] >= DEFAULTS["intrinsics"]["min_points"]).all()


def fit_rig_pose(rig: Rig, cameras, uv, points, start: Rigid3) -> np.ndarray:
    """Reprojection residuals (n, 2) after a least-squares rig pose fit from `start`."""
    def residuals(p):
        pose = Rigid3(Rotation.from_rotvec(p[:3]).as_matrix() @ start.R, p[3:] + start.t)
        out = np.empty_like(uv)
        for name in np.unique(cameras):
            mask = cameras == name
            out[mask] = rig.project(name, pose, points[mask]) - uv[mask]
        return out.ravel()

    return least_squares(residuals, np.zeros(6), x_scale=[1e-4] * 3 + [0.1] * 3).fun.reshape(-1, 2)


def test_flight_noise_budget_gives_the_papers_reprojection_error(tmp_path):
    """5-camera frames, calibrated (truth) rig, surveyed ground points: eps_proj ~ 4 px (tab:pose_methods)."""
    settings = merge(SMALL, {"flight": {"frames_per_group": 8}})
    dataset = Dataset.load(simulate(write_config(tmp_path / "c.yaml", settings), tmp_path / "budget"))
    rig = Rig.load(dataset.truth_dir / "rig.json")
    truth = pd.read_csv(dataset.truth_dir / "frames.csv", dtype={"frame": str}).set_index("frame")
    observations = dataset.observations.merge(dataset.images[["image", "camera", "placement"]], on="image")
    errors = []
    for frame, obs in observations[observations["image"].str.startswith("flight_")].groupby("placement"):
        points = dataset.ground_points.loc[obs["point_id"], ["x", "y", "z"]].to_numpy()
        residuals = fit_rig_pose(rig, obs["camera"].to_numpy(), obs[["u", "v"]].to_numpy(), points,
                                 pose_from_row(truth.loc[frame]))
        errors.append(np.hypot(*residuals.T).mean())
    assert len(errors) == 40
    assert 3.0 < np.mean(errors) < 5.0
    assert 0.4 < np.std(errors) < 1.6


@pytest.mark.parametrize("pattern, image", [("hover", "extr_p1_C3"), ("hover", "flight_g2_f000_C0"),
                                            ("hover", "flight_g3_f001_C2"), ("line", "flight_g2_f001_C3")])
def test_rendered_marker_centres_are_the_projections(tmp_path, pattern, image):
    """Every marker in a rendered image has its X-corner at the projection of its (true) point."""
    config = load_config(write_config(tmp_path / "r.yaml", with_flight(SMALL, pattern=pattern)))
    world = build_world(config)
    truth = truth_observations(config, world)
    shot = next(s for s in world["shots"] if s.image == image)
    camera = world["rig"].cameras[shot.camera]
    frames = {frame.frame: frame for frame in world["frames"]}
    boards = [m.board for m in markers_for(shot, world, frames)]
    image = render_image(camera, shot.cam_from_world, boards, stream(config["seed"], shot.image),
                         render_settings(config))
    assert image.shape == (3000, 4096) and image.dtype == np.uint8
    expected = truth.loc[truth["image"] == shot.image, ["u", "v"]].to_numpy()
    assert len(expected) >= 5
    start = (expected + np.random.default_rng(0).uniform(-1.5, 1.5, expected.shape)).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    found = cv2.cornerSubPix(image, start.reshape(-1, 1, 2), (11, 11), (-1, -1), criteria).reshape(-1, 2)
    errors = np.hypot(*(found - expected).T)
    assert np.sqrt(np.mean(errors**2)) < 0.1 and errors.max() < 0.25


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="flight.frames_per_grup"):
        load_config(write_config(tmp_path / "bad.yaml", {"flight": {"frames_per_grup": 3}}))
    with pytest.raises(ConfigError, match="'flight.pattern' is 'zigzag'"):
        load_config(write_config(tmp_path / "bad.yaml", {"flight": {"pattern": "zigzag"}}))
    for spacing in (0.0, -5.0, "20 m"):
        with pytest.raises(ConfigError, match="flight.line_spacing_m"):
            load_config(write_config(tmp_path / "bad.yaml", {"flight": {"pattern": "line", "line_spacing_m": spacing}}))
    with pytest.raises(ConfigError, match="flight.pattern"):  # settings that never went through load_config
        flight_frames(merge(DEFAULTS, {"flight": {"pattern": "Line"}}), build_rig(DEFAULTS["rig"]), stream(0, "flight"))
    assert cli.main(["simulate", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "x")]) == 2


def test_refuses_to_replace_a_folder_that_is_not_a_simulated_dataset(tmp_path):
    precious = tmp_path / "mine"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(DmaisError, match="refusing"):
        simulate(write_config(tmp_path / "s.yaml", SMALL), precious)
    assert (precious / "notes.txt").read_text() == "keep me"
    assert not any(p.name.endswith(".partial") for p in tmp_path.iterdir())


# ------------------------------------------------------------------------------ flight patterns

ONE_GROUP = {"A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1]}}


def flight_world(seed: int, **flight) -> tuple[dict, dict]:
    """Settings and the flight part of the world (one group at site A unless `sites` is given):
    rig, frames, ground markers, flight shots."""
    config = merge(DEFAULTS, {"seed": seed, "flight": {"sites": ONE_GROUP, **flight}})
    rig = build_rig(config["rig"])
    frames, ground = flight_frames(config, rig, stream(seed, "flight"))
    return config, {"rig": rig, "field": [], "ground": ground, "frames": frames, "shots": flight_shots(rig, frames)}


def test_hover_is_the_default_and_its_frames_are_as_before():
    """The default pattern is hover, and a seed gives the frames and markers it gave before the
    patterns existed (values from that code)."""
    assert DEFAULTS["flight"]["pattern"] == "hover"
    config = merge(DEFAULTS, {"flight": {"frames_per_group": 3}})
    frames, markers = flight_frames(config, build_rig(config["rig"]), np.random.default_rng(11))
    assert (len(frames), len(markers)) == (15, 200)
    np.testing.assert_allclose(frames[0].rig_from_world.center, [1499.3475457127827, -791.9749975935451,
                                                                 391.55319493698204], rtol=0, atol=1e-9)
    np.testing.assert_allclose(frames[-1].rig_from_world.center, [-2184.7720299318576, 1770.1115784578312,
                                                                  474.9076719797285], rtol=0, atol=1e-9)
    assert markers[-1].point_ids == ["GB080"]
    np.testing.assert_allclose(markers[-1].board.origin, [-2359.994012931139, 2096.686789139952, 122.81808600283239],
                               rtol=0, atol=1e-9)
    hover = settings_to_write(config)["flight"]
    assert "pattern" not in hover and "line_spacing_m" not in hover  # truth/simulation.yaml as before
    line = settings_to_write(merge(config, {"flight": {"pattern": "line"}}))["flight"]
    assert line["pattern"] == "line" and line["line_spacing_m"] == DEFAULTS["flight"]["line_spacing_m"]


def test_line_frames_move_by_the_spacing_along_the_heading():
    """Consecutive frames' rig centres step line_spacing_m along C0's image up (the heading), within
    the hover jitter (1 m per axis), at one height; without jitter exactly."""
    for jitter, tolerance in ((1.0, 5.0), (0.0, 1e-6)):
        _, world = flight_world(3, pattern="line", line_spacing_m=35.0, frames_per_group=8,
                                hover_position_sigma_m=jitter, hover_attitude_sigma_deg=0.2 * jitter)
        frames = world["frames"]
        centres = np.array([f.rig_from_world.center for f in frames])
        heading = -frames[0].rig_from_world.R[1]  # C0's image up in the world: world_from_rig's y column, negated
        assert abs(heading[2]) < 0.01
        steps = np.diff(centres, axis=0)
        along = steps @ heading
        across = np.linalg.norm(steps - along[:, None] * heading, axis=1)
        assert np.all(np.abs(along - 35.0) < tolerance) and np.all(across < tolerance)
        assert abs(np.mean(along) - 35.0) < tolerance / 2
        assert np.ptp(centres[:, 2]) < 2 * tolerance
        # the line passes through the group's pose: the middle of the frames is within the offset of the site
        assert np.linalg.norm(centres.mean(axis=0)[:2] - [1500.0, -800.0]) < np.sqrt(2) * 40.0 + tolerance


def test_line_frames_see_new_markers_and_earlier_frames_markers():
    """C0 sees mostly markers it did not see in the previous frame; markers placed for one frame are
    seen by the others where they fall in their view (a tilted camera keeps some of its markers)."""
    config, world = flight_world(4, pattern="line", frames_per_group=6)
    truth = truth_observations(config, world)
    seen = truth.groupby("image")["point_id"].apply(set)
    per_camera = config["flight"]["markers_per_camera"]
    c0 = [seen[f"flight_g1_f{k:03d}_C0"] for k in range(6)]
    new = np.array([len(now - before) for before, now in zip(c0, c0[1:])])
    assert all(len(now) >= per_camera - 2 for now in c0)
    assert np.all(new > 0.5 * np.array([len(now) for now in c0[1:]]))
    assert new.sum() > 0.75 * sum(len(now) for now in c0[1:])
    kept = [len(seen[f"flight_g1_f{k:03d}_{c}"] & seen[f"flight_g1_f{k - 1:03d}_{c}"])
            for k in range(1, 6) for c in ("C1", "C2", "C3", "C4")]
    assert min(kept) > 0
    assert len(world["ground"]) > 6 * 5 * per_camera * 0.8  # placed per frame, not once per group


def test_the_view_cone_preselection_leaves_out_no_seen_corner(tmp_path, monkeypatch):
    """visible_points looks only at the markers of scene.in_view_cone: the same observations as
    with every marker, for every calibration and flight image of a small line flight."""
    from dmais_pipe.sim import scene

    config = load_config(write_config(tmp_path / "v.yaml", with_flight(SMALL, pattern="line")))
    world = build_world(config)
    chosen = truth_observations(config, world)
    frames = {frame.frame: frame for frame in world["frames"]}
    shot = next(s for s in world["shots"] if s.stage == "flight")
    cone = scene.in_view_cone(world["rig"].cameras[shot.camera], shot.cam_from_world, markers_for(shot, world, frames))
    assert len(cone) < len(world["ground"]) / 4  # it does leave markers out
    monkeypatch.setattr(scene, "in_view_cone", lambda camera, cam_from_world, markers: markers)
    pd.testing.assert_frame_equal(chosen, truth_observations(config, world))
