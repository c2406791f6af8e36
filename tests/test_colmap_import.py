"""`dmais intrinsics --import`: intrinsics from OpenCV calibration files and COLMAP cameras files."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pycolmap
import pytest

from dmais_pipe import cli
from dmais_pipe.calib.import_intrinsics import (GRID_STEPS, ForeignCamera, one_coefficient_camera, read_opencv_file,
                                                write_opencv_file)
from dmais_pipe.camera import Camera
from dmais_pipe.calib.rig_ba import colmap_camera
from dmais_pipe.errors import DmaisError
from dmais_pipe.stages import intrinsics
from dmais_pipe.workspace import Workspace

from conftest import observation_only

SIM = observation_only("colmap-import", seed=12, calib_images=3, eval_images=1, frames_per_group=1)


@pytest.fixture(scope="module")
def dataset(simulated_dataset):
    return simulated_dataset(SIM)


def _ours(dataset, name: str, d: float = -0.031) -> Camera:
    """A camera of the dataset's size with arbitrary, non-symmetric intrinsics."""
    spec = Workspace.open(dataset, dataset).dataset.cameras[name]
    return Camera(1.013 * spec.focal_px, 0.998 * spec.focal_px, spec.width / 2 + 3.25, spec.height / 2 - 7.5, d,
                  spec.width, spec.height)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_ours_through_an_opencv_file_comes_back_unchanged(dataset, tmp_path, suffix):
    ours = _ours(dataset, "C1")
    source = write_opencv_file(ours, tmp_path / f"C1{suffix}")
    storage = cv2.FileStorage(str(source), cv2.FILE_STORAGE_READ)  # OpenCV's own reader sees our model
    np.testing.assert_array_equal(storage.getNode("camera_matrix").mat(), ours.K)
    np.testing.assert_array_equal(storage.getNode("distortion_coefficients").mat().ravel(), [ours.d, 0, 0, 0, 0])
    workspace = Workspace.open(dataset, tmp_path / "results")
    written = intrinsics.import_cameras(workspace, ["C1"], source)
    assert written == [workspace.intrinsics_path("C1"), workspace.methods_path("C1")]
    camera, record = workspace.load_intrinsics("C1")
    assert camera == ours
    assert record["method"] == f"imported from {source}"
    assert record["imported"]["residual_max_px"] < 1e-9  # OpenCV and our formula agree to rounding
    assert workspace.load_methods("C1")["method"].tolist() == ["imported"]


def test_a_colmap_cameras_file_imports_in_camera_id_order(dataset, tmp_path):
    ours = {"C0": _ours(dataset, "C0", -0.02), "C3": _ours(dataset, "C3", 0.015)}
    model = pycolmap.Reconstruction()
    for camera_id, camera in ((7, ours["C0"]), (9, ours["C3"])):
        model.add_camera(colmap_camera(camera, camera_id))
    model.write_text(tmp_path)
    workspace = Workspace.open(dataset, tmp_path / "results")
    intrinsics.import_cameras(workspace, ["C0", "C3"], tmp_path / "cameras.txt")
    for name, camera in ours.items():
        imported = workspace.load_intrinsics(name)[0]
        np.testing.assert_allclose([imported.fx, imported.fy, imported.cx, imported.cy, imported.d],
                                   [camera.fx, camera.fy, camera.cx, camera.cy, camera.d], rtol=0, atol=1e-12)
    # a hand-written SIMPLE_RADIAL line (COLMAP's pixel convention: the principal point - 0.5 is ours)
    spec = workspace.dataset.cameras["C2"]
    (tmp_path / "one" / "cameras.txt").parent.mkdir()
    (tmp_path / "one" / "cameras.txt").write_text(f"# Camera list\n1 SIMPLE_RADIAL {spec.width} {spec.height} "
                                                  f"{spec.focal_px} {spec.width / 2} {spec.height / 2} -0.05\n")
    intrinsics.import_cameras(workspace, ["C2"], tmp_path / "one" / "cameras.txt")
    assert workspace.load_intrinsics("C2")[0] == Camera(spec.focal_px, spec.focal_px, spec.width / 2 - 0.5,
                                                        spec.height / 2 - 0.5, -0.05, spec.width, spec.height)
    # another camera's file (focal far from the manifest's focal_px) is refused
    (tmp_path / "one" / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {spec.width} {spec.height} 5000 2048 1500 0\n")
    with pytest.raises(DmaisError, match=r"camera C2: .* 89% from dataset.yaml's focal_px"):
        intrinsics.import_cameras(workspace, ["C2"], tmp_path / "one" / "cameras.txt")


def _foreign(dataset, **distortion) -> ForeignCamera:
    """A camera of C2's size with a wider field (focal ~ the image width) than the long-focal rig's, where
    k2 shows."""
    ours = _ours(dataset, "C2", 0.0)
    return ForeignCamera(ours.width, ours.width * 1.01, ours.cx, ours.cy, ours.width, ours.height, "test",
                         {"k1": -0.03, **distortion})


def test_a_k2_rich_model_is_refused_by_name(dataset):
    with pytest.raises(DmaisError, match=r"^camera C2: k2 = 0\.12 is not representable by the one-coefficient model"):
        one_coefficient_camera(_foreign(dataset, k2=0.12, p1=1e-5), "C2")


def test_a_converted_model_states_the_residual_it_leaves(dataset):
    foreign = _foreign(dataset, k2=0.001)
    conversion = one_coefficient_camera(foreign, "C2", max_residual_px=1.0)
    # the stated residual, recomputed with our Camera and OpenCV's projection on the same grid
    camera, K = conversion.camera, conversion.camera.K
    u, v = np.meshgrid(np.linspace(-0.5, camera.width - 0.5, GRID_STEPS),
                       np.linspace(-0.5, camera.height - 0.5, GRID_STEPS))
    xy = cv2.undistortPoints(np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2), K,
                             foreign.coefficients()).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    theirs = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, foreign.coefficients())[0].reshape(-1, 2)
    residual = np.linalg.norm(camera.project(rays) - theirs, axis=1)
    assert conversion.residual_max_px == pytest.approx(residual.max(), rel=1e-9)
    assert conversion.residual_rms_px == pytest.approx(np.sqrt(np.mean(residual**2)), rel=1e-9)
    assert 0 < conversion.residual_max_px < 1.0
    # d is the least-squares optimum: a step either way, or k1 itself, leaves more
    for d in (camera.d - 1e-4, camera.d + 1e-4, -0.03):
        other = Camera(camera.fx, camera.fy, camera.cx, camera.cy, d, camera.width, camera.height)
        assert np.sum((other.project(rays) - theirs) ** 2) > np.sum(residual**2)
    with pytest.raises(DmaisError, match=r"camera C2: k2 = 0\.001 .* px max"):
        one_coefficient_camera(foreign, "C2", max_residual_px=0.5 * conversion.residual_max_px)


@pytest.mark.parametrize("name, content", [
    ("missing.yaml", None),
    ("corrupt.yaml", "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: [oops\n"),
    ("nomatrix.yaml", "%YAML:1.0\n---\nimage_width: 10\n"),
    ("cameras.txt", "1 OPENCV 640 480 not numbers\n"),
    ("cameras.bin", "garbage"),
])
def test_a_corrupt_or_missing_file_is_one_line_and_exit_2(dataset, tmp_path, capsys, name, content):
    if content is not None:
        (tmp_path / name).write_text(content)
    argv = ["intrinsics", str(dataset), "--out", str(tmp_path / "results"), "--camera", "C0",
            "--import", str(tmp_path / name)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"dmais intrinsics: error: {tmp_path / name}") and err.count("\n") == 1, err
    assert not (tmp_path / "results" / "intrinsics").exists()


def test_a_size_mismatch_is_refused(dataset, tmp_path):
    ours = _ours(dataset, "C0")
    source = write_opencv_file(Camera(ours.fx, ours.fy, ours.cx, ours.cy, ours.d, ours.width + 2, ours.height),
                               tmp_path / "C0.yaml")
    assert read_opencv_file(source).width == ours.width + 2
    with pytest.raises(DmaisError, match=r"camera C0: .*C0.yaml is for \d+x\d+ images, dataset.yaml says"):
        intrinsics.import_cameras(Workspace.open(dataset, tmp_path / "results"), ["C0"], source)


def _stereo_file(path, cameras) -> None:
    """A stereo calibration file as OpenCV's stereo_calib sample writes it: M1, D1, M2, D2 (and R, T),
    no image size."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for n, camera in enumerate(cameras, start=1):
        storage.write(f"M{n}", camera.K)
        storage.write(f"D{n}", np.array([[camera.d, 0.0, 0.0, 0.0, 0.0]]))
    storage.write("R", np.eye(3))
    storage.write("T", np.array([[-0.1], [0.0], [0.0]]))
    storage.release()


def test_a_stereo_calibrations_pair_is_named_and_takes_the_datasets_size(dataset, tmp_path):
    left, right = _ours(dataset, "C0", -0.02), _ours(dataset, "C0", 0.012)
    right = Camera(right.fx * 1.004, right.fy * 1.003, right.cx - 11.0, right.cy + 6.0, right.d, right.width,
                   right.height)
    _stereo_file(tmp_path / "intrinsics.yml", [left, right])
    results = tmp_path / "results"
    argv = ["intrinsics", str(dataset), "--out", str(results), "--camera", "C0", "--import"]
    assert cli.main([*argv, f"{tmp_path / 'intrinsics.yml'}:M2"]) == 0
    camera, record = Workspace.open(dataset, results).load_intrinsics("C0")
    assert camera == right  # the size the dataset's, the file has none
    assert record["imported"]["model"] == "OpenCV stereo M2"
    assert record["imported"]["file"] == f"{tmp_path / 'intrinsics.yml'}:M2"
    intrinsics.import_cameras(Workspace.open(dataset, results), ["C0"], tmp_path / "intrinsics.yml:M1")
    assert Workspace.open(dataset, results).load_intrinsics("C0")[0] == left


@pytest.mark.parametrize("suffix, message", [
    ("", r"a stereo calibration \(M1, M2\); name the camera's pair, e.g. --import .*intrinsics.yml:M1"),
    (":M3", r"intrinsics.yml: missing matrix M3"),
])
def test_a_stereo_file_without_its_pair_is_one_line_and_exit_2(dataset, tmp_path, capsys, suffix, message):
    ours = _ours(dataset, "C0")
    _stereo_file(tmp_path / "intrinsics.yml", [ours, ours])
    argv = ["intrinsics", str(dataset), "--out", str(tmp_path / "results"), "--camera", "C0",
            "--import", f"{tmp_path / 'intrinsics.yml'}{suffix}"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(message, err), err
    assert not (tmp_path / "results" / "intrinsics").exists()
