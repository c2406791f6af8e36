"""COLMAP export: the rig and the solved frames written by `dmais export-colmap`, read back by pycolmap."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pycolmap
import pytest
import yaml

from dmais_pipe import cli
from dmais_pipe.calib.rig_ba import opencv_params
from dmais_pipe.camera import Camera
from dmais_pipe.colmap import FORMATS, MODEL_FILES, camera_prefixes, colmap_image_names
from dmais_pipe.geometry import Rigid3
from dmais_pipe.stages import export
from dmais_pipe.workspace import POSE_COLUMNS, Workspace

from conftest import observation_only
from test_stages import SCHEMA

SIM = observation_only("colmap-small", seed=11, calib_images=3, eval_images=1, frames_per_group=2)
UNUSED_EVERY = 7  # every 7th observation is marked as not used by the pose (an outlier)


@pytest.fixture(scope="module")
def results(simulated_dataset, tmp_path_factory):
    """A results folder with the true rig, poses.csv at the true frames and its observations file."""
    dataset = simulated_dataset(SIM)
    root = tmp_path_factory.mktemp("colmap-results")
    shutil.copy(dataset / "truth" / "rig.json", root / "rig.json")
    workspace = Workspace.open(dataset, root)
    truth = pd.read_csv(dataset / "truth" / "frames.csv", dtype={"frame": str, "group": str})
    poses = truth.assign(cameras="+".join(workspace.load_rig().camera_names), n_points=0, eps_proj_px=0.0, time_ms=0.0)
    flight = workspace.dataset.images_of("flight")
    observations = workspace.dataset.observations.merge(flight[["image", "camera", "placement"]], on="image")
    observations = observations.rename(columns={"placement": "frame"}).assign(du=0.0, dv=0.0)
    observations["used"] = np.arange(len(observations)) % UNUSED_EVERY != 0
    workspace.save_poses(poses[list(POSE_COLUMNS)], observations, workspace.poses_path())
    return workspace


def _matrix(rigid) -> np.ndarray:
    """(3, 4) [R | t] of a pycolmap.Rigid3d."""
    return np.asarray(rigid.matrix())


def _ours(T: Rigid3) -> np.ndarray:
    return np.column_stack([T.R, T.t])


@pytest.mark.parametrize("fmt", ["text", "binary"])
def test_the_model_reads_back_with_every_pose_camera_and_track(results, fmt):
    written = export.run(results, export.Conf(formats=(fmt,)))
    folder = results.colmap_model_dir(fmt)
    assert [p.name for p in written[:-1]] == list(MODEL_FILES[fmt]) and all(p.parent == folder for p in written[:-1])
    model = pycolmap.Reconstruction(folder)
    rig, dataset = results.load_rig(), results.dataset
    poses = results.load_poses().set_index("frame")
    observations = results.load_pose_observations()

    names = colmap_image_names(dataset.images, camera_prefixes(dataset.images, rig.camera_names))
    image_of = {name: image for image, name in names.items()}
    flight = dataset.images_of("flight").set_index("image")
    ids = {}  # our camera -> COLMAP camera id, through the images
    for image in model.images.values():
        assert ids.setdefault(flight.at[image_of[image.name], "camera"], image.camera_id) == image.camera_id
    assert set(ids) == set(rig.camera_names) and len(set(ids.values())) == len(ids) == model.num_cameras()
    for name, camera_id in ids.items():
        camera, ours = model.cameras[camera_id], rig.cameras[name]
        assert camera.model.name == "OPENCV" and (camera.width, camera.height) == (ours.width, ours.height)
        np.testing.assert_array_equal(camera.params, [ours.fx, ours.fy, ours.cx + 0.5, ours.cy + 0.5, ours.d, 0, 0, 0])
    (colmap_rig,) = model.rigs.values()
    assert colmap_rig.ref_sensor_id.id == ids[rig.reference_camera]
    for name, camera_id in ids.items():
        if name != rig.reference_camera:
            sensor = model.cameras[camera_id].sensor_id
            np.testing.assert_allclose(_matrix(colmap_rig.sensor_from_rig(sensor)), _ours(rig.cam_from_rig[name]),
                                       atol=1e-12)

    assert model.num_frames() == len(poses) and model.num_images() == len(flight)
    for frame in model.frames.values():
        frame_ids = {flight.at[image_of[model.images[i.id].name], "placement"] for i in frame.image_ids}
        (frame_name,) = frame_ids
        row = poses.loc[frame_name]
        rig_from_world = Rigid3.from_quat(row[["qw", "qx", "qy", "qz"]].to_numpy(float),
                                          row[["tx", "ty", "tz"]].to_numpy(float))
        np.testing.assert_allclose(_matrix(frame.rig_from_world), _ours(rig_from_world), atol=1e-9)
        for data_id in frame.image_ids:
            image = model.images[data_id.id]
            ours = image_of[image.name]
            camera = flight.at[ours, "camera"]
            cam_from_world = rig.cam_from_rig[camera] * rig_from_world
            np.testing.assert_allclose(_matrix(image.cam_from_world()), _ours(cam_from_world), atol=1e-9)
            obs = observations[observations["image"] == ours]
            keypoints = np.array([p.xy for p in image.points2D]).reshape(-1, 2)
            np.testing.assert_allclose(keypoints - 0.5, obs[["u", "v"]].to_numpy(), atol=1e-9)
            linked = [p.has_point3D() for p in image.points2D]
            assert linked == obs["used"].tolist()
            # the reprojection through pycolmap's camera and through ours (independent code paths)
            X = dataset.points.loc[obs["point_id"], ["x", "y", "z"]].to_numpy(float)
            theirs = model.cameras[ids[camera]].img_from_cam(X @ cam_from_world.R.T + cam_from_world.t) - 0.5
            np.testing.assert_allclose(theirs, rig.project(camera, rig_from_world, X), atol=1e-6)

    used = observations[observations["used"]]
    assert model.num_points3D() == used["point_id"].nunique()
    assert sum(p.track.length() for p in model.points3D.values()) == len(used)
    for point in model.points3D.values():
        element = point.track.elements[0]
        image = model.images[element.image_id]
        point_id = observations[observations["image"] == image_of[image.name]]["point_id"].iloc[element.point2D_idx]
        np.testing.assert_array_equal(point.xyz, dataset.points.loc[point_id, ["x", "y", "z"]].to_numpy(float))


def test_opencv_cameras_export_as_opencv_or_full_opencv_and_project_as_ours(results, tmp_path):
    """A rig with an opencv camera with k3 != 0 (FULL_OPENCV), one with k3 = 0 (OPENCV) and radial1 ones (OPENCV):
    the model's cameras and rig_config.json's are exactly ours, and COLMAP projects every ray over each image
    as ours + 0.5 px (its pixel convention) within 1e-9 px."""
    out = tmp_path / "results"
    shutil.copytree(results.root, out, ignore=shutil.ignore_patterns("colmap"))
    workspace = Workspace.open(results.dataset.root, out)
    rig = workspace.load_rig()
    order = rig.cameras_reference_first  # COLMAP camera ids 1, 2, ...
    for name, k3 in zip(order[:2], (600.0, 0.0)):  # the long-focal cameras' normalized radius is <= 0.06
        c = rig.cameras[name]
        rig.cameras[name] = Camera(c.fx, c.fy, c.cx, c.cy, 3.0, c.width, c.height, "opencv", -40.0, 2e-4, -3e-4, k3)
        assert not rig.cameras[name].folds_in_image
    workspace.save_rig(rig)
    export.run(workspace)
    expected = {name: opencv_params(rig.cameras[name]) for name in order}
    assert [expected[name][0] for name in order] == ["FULL_OPENCV"] + ["OPENCV"] * (len(order) - 1)
    config = json.loads((workspace.colmap_dir / "rig_config.json").read_text())[0]["cameras"]
    assert [(c["camera_model_name"], c["camera_params"]) for c in config] == [expected[name] for name in order]
    for fmt in FORMATS:
        model = pycolmap.Reconstruction(workspace.colmap_model_dir(fmt))
        for camera_id, name in enumerate(order, start=1):
            camera, ours = model.cameras[camera_id], rig.cameras[name]
            assert (camera.model.name, list(camera.params)) == expected[name]
            u, v = np.meshgrid(np.linspace(-0.5, ours.width - 0.5, 33), np.linspace(-0.5, ours.height - 0.5, 25))
            rays = ours.unproject(np.column_stack([u.ravel(), v.ravel()]))
            pixels = ours.project(rays)
            assert not np.isnan(pixels).any()
            assert np.abs(camera.img_from_cam(rays) - (pixels + 0.5)).max() <= 1e-9


def test_rig_config_prefixes_match_the_image_names_and_bundle_adjustment_runs(results):
    export.run(results)
    model = pycolmap.Reconstruction(results.colmap_model_dir("binary"))
    config = json.loads((results.colmap_dir / "rig_config.json").read_text())
    prefixes = [c["image_prefix"] for c in config[0]["cameras"]]
    assert all(sum(image.name.startswith(p) for p in prefixes) == 1 for image in model.images.values())
    assert pycolmap.read_rig_config(results.colmap_dir / "rig_config.json")  # COLMAP parses it
    # pycolmap's bundle adjuster runs on the exported model: poses refined, points and intrinsics fixed
    for point3D_id in [i for i, p in model.points3D.items() if p.track.length() < 2]:
        model.delete_point3D(point3D_id)  # COLMAP adjusts points seen twice or more
    before = model.compute_mean_reprojection_error()
    options = pycolmap.BundleAdjustmentOptions(refine_focal_length=False, refine_principal_point=False,
                                               refine_extra_params=False, refine_points3D=False)
    options.print_summary = False
    pycolmap.bundle_adjustment(model, options)
    assert model.compute_mean_reprojection_error() <= before + 1e-9


def test_image_names_follow_the_camera_folders_or_get_the_camera_as_prefix():
    own = pd.DataFrame({"image": ["a", "b", "c", "d"], "camera": ["C0", "C0", "C1", "C1"],
                        "path": ["images/C0/1.png", "images/C0/2.png", "images/C1/1.png", ""]})
    prefixes = camera_prefixes(own, ["C0", "C1"])
    assert prefixes == {"C0": "images/C0/", "C1": "images/C1/"}
    assert colmap_image_names(own, prefixes) == {"a": "images/C0/1.png", "b": "images/C0/2.png",
                                                 "c": "images/C1/1.png", "d": "images/C1/d"}
    shared = own.assign(path=["images/flight/a.png", "images/flight/b.png", "images/flight/c.png", ""])
    prefixes = camera_prefixes(shared, ["C0", "C1"])
    assert prefixes == {"C0": "C0/", "C1": "C1/"}
    assert colmap_image_names(shared, prefixes) == {"a": "C0/images/flight/a.png", "b": "C0/images/flight/b.png",
                                                    "c": "C1/images/flight/c.png", "d": "C1/d"}


def test_the_cli_writes_one_format_and_a_missing_pose_file_is_one_line(results, tmp_path, capsys):
    out = tmp_path / "results"
    assert cli.main(["export-colmap", str(results.dataset.root), "--out", str(out)]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    shutil.copytree(results.root, out, ignore=shutil.ignore_patterns("colmap"))
    assert cli.main(["export-colmap", str(results.dataset.root), "--out", str(out), "--format", "text"]) == 0
    assert sorted(p.name for p in (out / "colmap" / "text").iterdir()) == sorted(MODEL_FILES["text"])
    assert not (out / "colmap" / "binary").exists()


def test_the_workflow_schema_knows_the_export_settings():
    section = yaml.safe_load(SCHEMA.read_text())["properties"]["export"]["properties"]
    assert set(section) == {"conf", "formats"} and section["conf"]["enum"] == list(export.CONFS)


def test_images_sharing_a_folder_are_found_through_the_camera_links(results, tmp_path):
    """A dataset whose cameras share one image folder (as the simulator's): names "<camera>/<path>" and
    RESULTS/colmap/images/<camera> links to the dataset, through which every image file is found."""
    dataset = tmp_path / "dataset"
    shutil.copytree(results.dataset.root, dataset)
    images = pd.read_csv(dataset / "images.csv", dtype=str, keep_default_na=False)
    flight = images["stage"] == "flight"
    images.loc[flight, "path"] = "images/flight/" + images.loc[flight, "image"] + ".png"
    images.to_csv(dataset / "images.csv", index=False)
    (dataset / "images" / "flight").mkdir(parents=True)
    for path in images.loc[flight, "path"]:
        (dataset / path).write_bytes(b"")  # existence is all the export needs
    out = tmp_path / "results"
    shutil.copytree(results.root, out, ignore=shutil.ignore_patterns("colmap"))
    workspace = Workspace.open(dataset, out)
    export.run(workspace, export.Conf(formats=("text",)))
    model = pycolmap.Reconstruction(workspace.colmap_model_dir("text"))
    names = sorted(image.name for image in model.images.values())
    assert names == sorted(f"{c}/{p}" for c, p in zip(images.loc[flight, "camera"], images.loc[flight, "path"]))
    assert all((workspace.colmap_dir / "images" / name).is_file() for name in names)
    assert not (results.colmap_dir / "images").exists()  # the observation-only dataset has nothing to link
